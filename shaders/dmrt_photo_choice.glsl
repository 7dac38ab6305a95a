// DMRT image management (paper Section 5.2.2) on the GPU: which photos the full-resolution cache
// should hold, from the frame's label histogram, so the CPU never reads the histogram itself.
// The photos with pixels, most pixels first (equal counts: smaller index first, as a stable sort
// of the counts), at most u_slots of them, go into the next frame's FrameStatus record
// (dmrt/runtime/status.py): the CPU reads them with the list length it reads anyway.
//
// The second of two passes (dmrt/runtime/ranking.py issues both): dmrt_photo_compact.glsl has
// listed the m photos with a non-zero count, and one invocation per list entry finds its rank by
// counting the entries ahead of it: m^2 loads of a list that stays in cache (a frame's few hundred
// photos: ~10^5 loads, whatever the scene's number of photos; before the list, every photo of the
// scene compared itself with every other, 10^8 loads at 10,240 photos). The rank compares (count,
// photo), never list positions, so the order in which the compaction appended is irrelevant; ranks
// are unique, so each wanted photo writes its own entry and nothing is cleared first.
//
// Buffers (binding: layout):
//   B_PHOTO_LIST    the compacted list (dmrt_photo_compact.glsl), read
//   STATUS_BINDING  the next frame's record (B_FRAME_STATUS): n_wanted and wanted[] written,
//                   tile_total untouched
// The view-dependent photo choice ranks its scores into its candidate list with the same passes
// (STATUS_BINDING B_VIEW_CANDIDATES: dmrt/runtime/view_choice.py).
#if defined COMPUTE_SHADER

#ifndef STATUS_BINDING
#define STATUS_BINDING B_FRAME_STATUS
#endif

layout(local_size_x = 64) in;

layout(std430, binding = B_PHOTO_LIST) readonly buffer Listed {
    uint n_listed;
    uint spare;
    uvec2 listed[];  // (count, photo)
};
layout(std430, binding = STATUS_BINDING) buffer Status {
    uint tile_total;
    uint n_wanted;
    uint spare_words[STATUS_HEADER_WORDS - 2];
    int wanted[];
};

uniform uint u_slots;  // the cache's slots, >= 1

void main() {
    uint m = n_listed;
    if (gl_GlobalInvocationID.x == 0u) n_wanted = min(m, u_slots);
    // invocations past the list return at once: the dispatch covers every photo, so the CPU never
    // reads the list's length
    uint stride = gl_NumWorkGroups.x * gl_WorkGroupSize.x;
    for (uint e = gl_GlobalInvocationID.x; e < m; e += stride) {
        uvec2 me = listed[e];
        uint rank = 0u;
        for (uint i = 0u; i < m && rank < u_slots; ++i) {
            uvec2 other = listed[i];
            rank += uint(other.x > me.x || (other.x == me.x && other.y < me.y));
        }
        if (rank < u_slots) wanted[rank] = int(me.y);
    }
}

#endif
