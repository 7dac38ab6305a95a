// DMRT image management (paper Section 5.2.2): the frame's label histogram, the relevance of each
// photo. Contended atomics are the cost here - one atomicAdd per pixel on a handful of counters
// took 60 ms per 1280x720 frame on an H200 - so each thread walks PIXELS_PER_THREAD consecutive
// pixels counting runs of equal labels in registers, adds a run to the workgroup's shared
// histogram only when the label changes, and the workgroup adds its non-zero bins to the global
// counts once: a few hundred global atomics per frame.
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

uniform uint u_count;  // pixels

shared uint local_counts[N_PHOTOS];

void main() {
    uint lid = gl_LocalInvocationIndex;
    for (uint i = lid; i < uint(N_PHOTOS); i += gl_WorkGroupSize.x) local_counts[i] = 0u;
    barrier();
    // thread t of group g takes pixels [start, start + PIXELS_PER_THREAD): coalescing matters less
    // than long runs here (a run of one label is one shared atomic)
    uint start = (gl_WorkGroupID.x * gl_WorkGroupSize.x + lid) * uint(PIXELS_PER_THREAD);
    uint end = min(start + uint(PIXELS_PER_THREAD), u_count);
    int run_label = -1;
    uint run = 0u;
    for (uint pix = start; pix < end; ++pix) {
        int l = hits[pix].final_label;
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
}

#endif
