// Depth map from oriented circular splats, compute path: one thread per splat (paper Section 4.1).
// Each thread walks its disc's pixel box and atomicMin's the float bits of z into the depth buffer.
// Discs covering more than MAX_THREAD_PIXELS pixels are appended to a list that
// splat_depth_compute_large splats with a whole workgroup each: no disc is ever cut, and one near,
// huge disc does not stall the other 31 threads of its warp.
#include "splat_depth_common.glsl"
#include "splat_depth_buffers.glsl"

#if defined COMPUTE_SHADER

#ifndef MAX_THREAD_PIXELS
#define MAX_THREAD_PIXELS 256
#endif

layout(local_size_x = 64) in;

uniform uint u_first;  // this dispatch splats u_count splats from splat u_first on (a run of the batch)

void main() {
    // grid-stride loop: a batch may hold more than 65535 workgroups' worth of splats
    uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
    for (uint i = gl_GlobalInvocationID.x; i < u_count; i += stride) {
        uint k = u_first + i;
        Splat s = load_splat(k);
        ivec4 box = splat_pixel_box(s);
        if (box.x > box.z || box.y > box.w) continue;
        int area = (box.z - box.x + 1) * (box.w - box.y + 1);
        if (area > MAX_THREAD_PIXELS) {
            uint i = atomicAdd(n_large, 1u);
            large[i] = k;
            atomicMax(groups_x, min(i + 1u, LARGE_GROUPS));
            continue;
        }
        for (int row = box.y; row <= box.w; ++row)
            for (int col = box.x; col <= box.z; ++col)
                splat_pixel(s, col, row);
    }
}

#endif
