// Proxy splats P_LD for the DMRT screen-space compute passes (visibility stage, labeling pass).
// Included; no #version. The including program defines
//     void visit(Splat s, int label, int col, int row);
// which is called for every pixel of a disc's pixel box (the disc test itself is the program's
// business: splat_depth_at from splat_depth_common.glsl). Two entry points, chosen by LARGE:
//
//   LARGE 0: one thread per splat; discs whose pixel box exceeds MAX_THREAD_PIXELS are skipped and,
//            when u_build_list is set (first splat pass of a frame), appended to the large list;
//   LARGE 1: one workgroup per listed disc, run with dispatch-indirect arguments the LARGE 0 pass
//            wrote (zero workgroups when no disc is large).
//
// The list depends on the camera only, so one frame's passes (k visibility layers x 2, labeling x 2)
// share it.
#include "dmrt_proxies.glsl"

// Dispatch-indirect arguments of the LARGE pass, the list length, then proxy indices.
layout(std430, binding = B_LARGE) buffer Large { uint groups_x; uint groups_y; uint groups_z; uint n_large; uint large[]; };

#ifndef LARGE
#define LARGE 0
#endif
#ifndef RESOLVE
#define RESOLVE 0
#endif
#ifndef MAX_THREAD_PIXELS
#define MAX_THREAD_PIXELS 256
#endif
#ifndef LARGE_GROUPS
#define LARGE_GROUPS 1024u
#endif

uniform uint u_count;     // number of proxies
uniform int u_build_list; // 1: append large discs to the list in this pass

// EMPTY_BITS (an untouched key, above every positive float's bits) and EMPTY_LABEL (an untouched
// label: atomicMin keeps the smallest) come from dmrt/gl/abi.py

void visit(Splat s, int label, int col, int row);

#if defined COMPUTE_SHADER
#if LARGE

layout(local_size_x = 256) in;

void main() {
    for (uint i = gl_WorkGroupID.x; i < n_large; i += gl_NumWorkGroups.x) {
        int label;
        Splat s = load_proxy(large[i], label);
        ivec4 box = splat_pixel_box(s);
        int w = box.z - box.x + 1;
        int area = w * (box.w - box.y + 1);
        for (int p = int(gl_LocalInvocationID.x); p < area; p += int(gl_WorkGroupSize.x))
            visit(s, label, box.x + p % w, box.y + p / w);
    }
}

#else

layout(local_size_x = 64) in;

void main() {
    uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
    for (uint k = gl_GlobalInvocationID.x; k < u_count; k += stride) {
        int label;
        Splat s = load_proxy(k, label);
        ivec4 box = splat_pixel_box(s);
        if (box.x > box.z || box.y > box.w) continue;
        int area = (box.z - box.x + 1) * (box.w - box.y + 1);
        if (area > MAX_THREAD_PIXELS) {
            if (u_build_list != 0) {
                uint i = atomicAdd(n_large, 1u);
                large[i] = k;
                atomicMax(groups_x, min(i + 1u, LARGE_GROUPS));
            }
            continue;
        }
        for (int row = box.y; row <= box.w; ++row)
            for (int col = box.x; col <= box.z; ++col)
                visit(s, label, col, row);
    }
}

#endif
#endif
