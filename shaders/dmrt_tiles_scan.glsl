// Tile-binned visibility stage, scan (dmrt/runtime/tiles.py): the exclusive prefix sum of the
// per-tile disc counts, i.e. where each tile's slice of the Entries list starts.
// One workgroup of SCAN_THREADS threads: thread t sums a contiguous run of the counts, read four at
// a time and LOADS_IN_FLIGHT of those loads issued before the first is used (the pass is one
// workgroup, so it takes as long as its chain of loads: a count a load, one after the other, it
// took 0.081 ms for 32400 tiles at 3840x2160 on an H200, session 20); the run sums are scanned in
// shared memory (Hillis-Steele), then each thread writes its run's offsets. The counts buffer holds
// a multiple of four words, its padding zero (dmrt/runtime/tiles.py).
//
// Buffers (binding: layout):
//   B_FRAME_STATUS  the frame's FrameStatus record (dmrt/runtime/status.py): its first word, the
//                   entries this frame (the host sizes the list from it)
//   B_TILE_COUNTS   uint[tiles] (dmrt_tiles_bin.glsl SCATTER 0)
//   B_TILE_OFFSETS  uint[tiles + 1]: Offsets[t] = sum of Counts[0..t), Offsets[tiles] = total
#if defined COMPUTE_SHADER

#ifndef SCAN_THREADS
#define SCAN_THREADS 1024
#endif
#define LOADS_IN_FLIGHT 8

layout(local_size_x = SCAN_THREADS) in;

layout(std430, binding = B_FRAME_STATUS) buffer Status { uint total; };  // tile_total
layout(std430, binding = B_TILE_COUNTS) readonly buffer Counts { uvec4 counts4[]; };  // padded
layout(std430, binding = B_TILE_OFFSETS) writeonly buffer Offsets { uint offsets[]; };

uniform uint u_tile_count;  // tiles_x * tiles_y

shared uint s_sum[SCAN_THREADS];

// Counts [4q, 4q + 4) for q in [q0, q0 + LOADS_IN_FLIGHT) within [q0, e), zero past e.
void load_counts(uint q0, uint e, out uvec4 c[LOADS_IN_FLIGHT]) {
    for (uint j = 0u; j < uint(LOADS_IN_FLIGHT); ++j) c[j] = q0 + j < e ? counts4[q0 + j] : uvec4(0u);
}

void main() {
    uint t = gl_LocalInvocationID.x;
    uint quads = (u_tile_count + 3u) / 4u;
    uint per = (quads + uint(SCAN_THREADS) - 1u) / uint(SCAN_THREADS);
    uint b = min(t * per, quads), e = min(b + per, quads);
    uvec4 c[LOADS_IN_FLIGHT];
    uint sum = 0u;
    for (uint q0 = b; q0 < e; q0 += uint(LOADS_IN_FLIGHT)) {
        load_counts(q0, e, c);
        for (uint j = 0u; j < uint(LOADS_IN_FLIGHT); ++j) sum += c[j].x + c[j].y + c[j].z + c[j].w;
    }
    s_sum[t] = sum;
    memoryBarrierShared();
    barrier();
    for (uint d = 1u; d < uint(SCAN_THREADS); d <<= 1u) {
        uint add = t >= d ? s_sum[t - d] : 0u;
        memoryBarrierShared();
        barrier();
        s_sum[t] += add;
        memoryBarrierShared();
        barrier();
    }
    uint run = s_sum[t] - sum;  // exclusive
    for (uint q0 = b; q0 < e; q0 += uint(LOADS_IN_FLIGHT)) {
        load_counts(q0, e, c);
        for (uint j = 0u; j < uint(LOADS_IN_FLIGHT); ++j) {  // a constant count: unrolled, c stays in registers
            for (uint m = 0u; m < 4u; ++m) {
                uint i = 4u * (q0 + j) + m;
                if (q0 + j < e && i < u_tile_count) offsets[i] = run;
                run += c[j][m];  // 0 past e
            }
        }
    }
    if (t == uint(SCAN_THREADS) - 1u) {
        offsets[u_tile_count] = s_sum[t];
        total = s_sum[t];
    }
}

#endif
