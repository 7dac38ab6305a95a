// Depth map from oriented circular splats, compute path, second pass: the discs that
// splat_depth_compute deferred (more than MAX_THREAD_PIXELS pixels), one workgroup per disc, its
// threads striding over the disc's pixel box. Same per-pixel test and atomicMin as the first pass.
#include "splat_depth_common.glsl"
#include "splat_depth_buffers.glsl"

#if defined COMPUTE_SHADER

layout(local_size_x = 256) in;

void main() {
    // up to LARGE_GROUPS workgroups (the indirect dispatch's) stride over the list
    for (uint i = gl_WorkGroupID.x; i < n_large; i += gl_NumWorkGroups.x) {
        Splat s = load_splat(large[i]);
        ivec4 box = splat_pixel_box(s);
        int w = box.z - box.x + 1;
        int area = w * (box.w - box.y + 1);
        for (int p = int(gl_LocalInvocationID.x); p < area; p += int(gl_WorkGroupSize.x))
            splat_pixel(s, box.x + p % w, box.y + p / w);
    }
}

#endif
