// DMRT image management (paper Section 5.2.2) on the GPU: which photos the full-resolution cache
// should hold, from the frame's label histogram, so the CPU never reads the histogram itself.
// The photos with pixels, most pixels first (equal counts: smaller index first, as a stable sort
// of the counts), at most u_slots of them, go into the next frame's FrameStatus record
// (dmrt/runtime/status.py): the CPU reads them with the list length it reads anyway.
//
// One invocation per photo finds its rank by counting the photos ahead of it: n^2 loads of a
// few-kilobyte buffer that stays in cache (10,000 photos: 10^8 cached loads spread over the GPU);
// ranks are unique, so each wanted photo writes its own entry and nothing is cleared first.
//
// Buffers (binding: layout):
//   B_COUNTS        uint[N_PHOTOS]: pixels per final label (dmrt_label_histogram.glsl)
//   B_FRAME_STATUS  the next frame's record: n_wanted and wanted[] written, tile_total untouched
// The view-dependent photo choice ranks its scores into its candidate list with the same program
// (COUNTS_BINDING B_VIEW_SCORES, STATUS_BINDING B_VIEW_CANDIDATES: dmrt/runtime/view_choice.py).
#if defined COMPUTE_SHADER

#ifndef N_PHOTOS
#define N_PHOTOS 1
#endif
#ifndef COUNTS_BINDING
#define COUNTS_BINDING B_COUNTS
#endif
#ifndef STATUS_BINDING
#define STATUS_BINDING B_FRAME_STATUS
#endif

layout(local_size_x = 64) in;

layout(std430, binding = COUNTS_BINDING) readonly buffer Counts { uint counts[]; };
layout(std430, binding = STATUS_BINDING) buffer Status {
    uint tile_total;
    uint n_wanted;
    uint spare[STATUS_HEADER_WORDS - 2];
    int wanted[];
};

uniform uint u_slots;  // the cache's slots, >= 1

void main() {
    uint j = gl_GlobalInvocationID.x;
    if (j == 0u) {  // the list's length: every photo with pixels, up to the slots
        uint nonzero = 0u;
        for (uint i = 0u; i < uint(N_PHOTOS); ++i) nonzero += uint(counts[i] > 0u);
        n_wanted = min(nonzero, u_slots);
    }
    if (j >= uint(N_PHOTOS)) return;
    uint c = counts[j];
    if (c == 0u) return;
    uint rank = 0u;
    for (uint i = 0u; i < uint(N_PHOTOS) && rank < u_slots; ++i) {
        uint ci = counts[i];
        rank += uint(ci > c || (ci == c && i < j));
    }
    if (rank < u_slots) wanted[rank] = int(j);
}

#endif
