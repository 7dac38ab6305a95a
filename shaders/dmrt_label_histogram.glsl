// DMRT image management (paper Section 5.2.2): the frame's label histogram, the relevance of each
// photo. Contended atomics are the cost here - one atomicAdd per pixel on a handful of counters
// took 60 ms per 1280x720 frame on an H200 - so each thread walks a column of PIXELS_PER_THREAD
// pixels counting runs of equal labels in registers (labels come in regions: columns have long
// runs), adds a run to the workgroup's shared histogram only when the label changes, and the
// workgroup adds its non-zero bins to the global counts once: a few hundred global atomics per
// frame. Neighbouring threads take neighbouring columns, so each step's loads are coalesced; with
// a row of 64 pixels per thread instead, the loads of a warp lay 2 KB apart and the pass took
// 2.4 ms at 3840x2160 on an H200.
#include "splat_depth_common.glsl"
#include "dmrt_frame.glsl"

#if defined COMPUTE_SHADER

#ifndef N_PHOTOS
#define N_PHOTOS 1
#endif
#ifndef PIXELS_PER_THREAD
#define PIXELS_PER_THREAD 64
#endif

layout(local_size_x = 64) in;

layout(std430, binding = B_COUNTS) buffer Counts { uint counts[]; };

#ifndef VIEW_CANDIDATES
#define VIEW_CANDIDATES 0
#endif
#if VIEW_CANDIDATES
// The view-dependent photo choice's candidates (dmrt_view_choice.glsl) each count one pixel more:
// a photo that only ever takes part in blends is then wanted by the photo cache too, after every
// photo that is some pixel's best.
layout(std430, binding = B_VIEW_CANDIDATES) readonly buffer Candidates {
    uint candidates_header[STATUS_HEADER_WORDS];
    int candidates[];
};
#endif

shared uint local_counts[N_PHOTOS];

void main() {
    uint lid = gl_LocalInvocationIndex;
    for (uint i = lid; i < uint(N_PHOTOS); i += gl_WorkGroupSize.x) local_counts[i] = 0u;
    barrier();
    // u_size (splat_depth_common.glsl): the frame's width and height here.
    // workgroup (gx, gy) takes the 64 x PIXELS_PER_THREAD block of columns gx * 64 .. and rows
    // gy * PIXELS_PER_THREAD ..; thread lid its column
    int x = int(gl_WorkGroupID.x * gl_WorkGroupSize.x + lid);
    int y0 = int(gl_WorkGroupID.y) * PIXELS_PER_THREAD;
    int y1 = x < u_size.x ? min(y0 + PIXELS_PER_THREAD, u_size.y) : y0;
    int run_label = -1;
    uint run = 0u;
    for (int y = y0; y < y1; ++y) {
        int l = hits[y * u_size.x + x].final_label;
        if (l != run_label) {
            if (run_label >= 0) atomicAdd(local_counts[run_label], run);
            run_label = l;
            run = 0u;
        }
        ++run;
    }
    if (run_label >= 0 && run > 0u) atomicAdd(local_counts[run_label], run);
    barrier();
    for (uint i = lid; i < uint(N_PHOTOS); i += gl_WorkGroupSize.x)
        if (local_counts[i] > 0u) atomicAdd(counts[i], local_counts[i]);
#if VIEW_CANDIDATES
    if (gl_WorkGroupID.x == 0u && gl_WorkGroupID.y == 0u)
        for (uint i = lid; i < candidates_header[1]; i += gl_WorkGroupSize.x) atomicAdd(counts[candidates[i]], 1u);
#endif
}

#endif
