// The first pass of the photo choice (dmrt_photo_choice.glsl ranks what it leaves): the photos with
// a non-zero count, appended to a list as (count, photo) pairs in whatever order the atomic counter
// hands out places. A frame sees a few hundred photos of thousands, and the ranking then compares
// only these: its cost follows the frame's photos, not the scene's. The list's length must be 0
// before the pass (dmrt/runtime/ranking.py clears it on the GPU each frame).
//
// Buffers (binding: layout):
//   COUNTS_BINDING  uint[N_PHOTOS]: the label histogram (B_COUNTS) or the view scores (B_VIEW_SCORES)
//   B_PHOTO_LIST    uint n_listed, uint spare, uvec2 listed[N_PHOTOS]: (count, photo), appended
#if defined COMPUTE_SHADER

#ifndef N_PHOTOS
#define N_PHOTOS 1
#endif
#ifndef COUNTS_BINDING
#define COUNTS_BINDING B_COUNTS
#endif

layout(local_size_x = 64) in;

layout(std430, binding = COUNTS_BINDING) readonly buffer Counts { uint counts[]; };
layout(std430, binding = B_PHOTO_LIST) buffer Listed {
    uint n_listed;
    uint spare;  // pads listed[] to its 8-byte alignment, as std430 would
    uvec2 listed[];
};

void main() {
    uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;  // a dispatch holds 65535 groups at most
    for (uint j = gl_GlobalInvocationID.x; j < uint(N_PHOTOS); j += stride) {
        uint c = counts[j];
        if (c > 0u) listed[atomicAdd(n_listed, 1u)] = uvec2(c, j);
    }
}

#endif
