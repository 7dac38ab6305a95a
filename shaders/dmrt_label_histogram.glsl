// DMRT image management (paper Section 5.2.2): the frame's label histogram, the relevance of each
// photo. Contended atomics are the cost here - one atomicAdd per pixel on a handful of counters
// took 60 ms per 1280x720 frame on an H200 - so each thread walks a column of PIXELS_PER_THREAD
// pixels counting runs of equal labels in registers (labels come in regions: columns have long
// runs), adds a run to the workgroup's shared histogram only when the label changes, and the
// workgroup adds its non-zero bins to the global counts once: a few hundred global atomics per
// frame. Neighbouring threads take neighbouring columns, so each step's loads are coalesced; with
// a row of 64 pixels per thread instead, the loads of a warp lay 2 KB apart and the pass took
// 2.4 ms at 3840x2160 on an H200. The workgroup's histogram is a small hash table of the labels
// its block holds (a handful), not a bin per photo: its cost does not grow with the photos (a bin
// per photo of 10,000 is 40 KB of shared memory, cleared and scanned by every workgroup).
#include "splat_depth_common.glsl"
#include "dmrt_frame.glsl"

#if defined COMPUTE_SHADER

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

// The workgroup's labels and their pixel counts: open addressing, a few probes; a label that finds
// no room (more distinct labels in the block than the table takes) is counted globally at once.
const uint TABLE = 128u;  // a power of two, twice the workgroup
const uint PROBES = 8u;
const uint NO_LABEL = uint(EMPTY_LABEL);  // the ABI's empty label: no photo index
shared uint table_label[TABLE];
shared uint table_count[TABLE];

void count(int label, uint run) {
    uint l = uint(label);
    uint h = (l * 2654435761u) >> 25;  // Knuth's multiplicative hash, top 7 bits: 0..TABLE-1
    for (uint i = 0u; i < PROBES; ++i, h = (h + 1u) & (TABLE - 1u)) {
        uint held = atomicCompSwap(table_label[h], NO_LABEL, l);
        if (held == NO_LABEL || held == l) {
            atomicAdd(table_count[h], run);
            return;
        }
    }
    atomicAdd(counts[l], run);
}

void main() {
    uint lid = gl_LocalInvocationIndex;
    for (uint i = lid; i < TABLE; i += gl_WorkGroupSize.x) {
        table_label[i] = NO_LABEL;
        table_count[i] = 0u;
    }
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
            if (run_label >= 0) count(run_label, run);
            run_label = l;
            run = 0u;
        }
        ++run;
    }
    if (run_label >= 0 && run > 0u) count(run_label, run);
    barrier();
    for (uint i = lid; i < TABLE; i += gl_WorkGroupSize.x)
        if (table_label[i] != NO_LABEL) atomicAdd(counts[table_label[i]], table_count[i]);
#if VIEW_CANDIDATES
    if (gl_WorkGroupID.x == 0u && gl_WorkGroupID.y == 0u)
        for (uint i = lid; i < candidates_header[1]; i += gl_WorkGroupSize.x) atomicAdd(counts[candidates[i]], 1u);
#endif
}

#endif
