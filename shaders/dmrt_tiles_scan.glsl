// Tile-binned visibility stage, scan (dmrt/runtime/tiles.py): the exclusive prefix sum of the
// per-tile disc counts, i.e. where each tile's slice of the Entries list starts.
// One workgroup of SCAN_THREADS threads. The counts are read four at a time (uvec4), thread t taking
// quads t, t + SCAN_THREADS, ... (ROUNDS of them at once, a sweep), so that each load of a warp is
// 512 contiguous bytes and all of a thread's loads are in flight together; each round's quad sums
// are scanned in shared memory (Hillis-Steele, all rounds in the same steps), the rounds follow each
// other, and each quad's four offsets are written as one uvec4. (Thread t summing a contiguous run
// of counts, a load each, took 0.081 ms at 3840x2160 on an H200; the same four at a time 0.057 ms:
// the pass is one workgroup, so its loads' and stores' transactions, one a lane, were its time.
// Session 20.) Both buffers hold a multiple of four words, the counts' padding zero
// (dmrt/runtime/tiles.py).
//
// Buffers (binding: layout):
//   B_FRAME_STATUS  the frame's FrameStatus record (dmrt/runtime/status.py): its first word, the
//                   entries this frame (the host sizes the list from it); its third, the tiles whose
//                   list is longer than u_split_min (the host runs the split passes while frames
//                   have them: TileVisibility.split_hold)
//   B_TILE_COUNTS   uint[tiles] (dmrt_tiles_bin.glsl SCATTER 0)
//   B_TILE_OFFSETS  uint[tiles + 1]: Offsets[t] = sum of Counts[0..t), Offsets[tiles] = total (and the
//                   padding after it)
//   B_TILE_SPLIT    SPLIT 1, with u_planned: its header's fifth word, the tiles the split plan took
//                   out of the lists (their counts here are 0) (dmrt_tiles_split.glsl)
#if defined COMPUTE_SHADER

#ifndef SCAN_THREADS
#define SCAN_THREADS 1024
#endif
// quads a thread holds in a sweep, at most 8 (SCAN_ROUNDS in dmrt/runtime/tiles.py, which sets the
// rounds a frame needs: shared memory for eight took 0.004 ms more at 1280x720, which needs one): a
// sweep covers 4 x 8 x 1024 = 32768 tiles (3840 x 2160 pixels in 16 x 16 tiles: 32400); larger
// frames take more sweeps
#ifndef ROUNDS
#define ROUNDS 8
#endif
#ifndef SPLIT
#define SPLIT 0  // 1: a split plan may run before the scan (TileVisibility's split_min > 0)
#endif

layout(local_size_x = SCAN_THREADS) in;

layout(std430, binding = B_FRAME_STATUS) buffer Status { uint total; uint n_wanted; uint long_tiles; };
layout(std430, binding = B_TILE_COUNTS) readonly buffer Counts { uvec4 counts4[]; };
layout(std430, binding = B_TILE_OFFSETS) writeonly buffer Offsets { uvec4 offsets4[]; };
#if SPLIT
layout(std430, binding = B_TILE_SPLIT) readonly buffer SplitHeader { uint split_header[]; };
#endif

uniform uint u_tile_count;  // tiles_x * tiles_y
uniform uint u_split_min;   // a list longer than this is long (0xFFFFFFFF: no split)
uniform uint u_planned;     // SPLIT 1: the split plan ran this frame (B_TILE_SPLIT bound)

shared uint s_sum[ROUNDS * SCAN_THREADS];  // per round, the inclusive scan of its quad sums

void main() {
    uint t = gl_LocalInvocationID.x;
    uint quads = (u_tile_count + 3u) / 4u;
    uint carry = 0u;  // the counts of the sweeps before
    uint long_lists = 0u;  // this thread's
    for (uint q0 = 0u; q0 < quads; q0 += uint(ROUNDS * SCAN_THREADS)) {
        // the rounds that hold quads (one at 1280x720): the others are skipped, not scanned as zeros
        uint live = min(uint(ROUNDS), (quads - q0 + uint(SCAN_THREADS) - 1u) / uint(SCAN_THREADS));
        uint v[ROUNDS];  // this thread's quad sums
        for (int r = 0; r < ROUNDS; ++r) {  // constant bounds and guarded bodies: unrolled, v and add in registers
            uint q = q0 + uint(r * SCAN_THREADS) + t;
            uvec4 c = q < quads ? counts4[q] : uvec4(0u);
            v[r] = c.x + c.y + c.z + c.w;
            long_lists += uint(c.x > u_split_min) + uint(c.y > u_split_min) + uint(c.z > u_split_min)
                          + uint(c.w > u_split_min);
            if (uint(r) < live) s_sum[r * SCAN_THREADS + int(t)] = v[r];
        }
        memoryBarrierShared();
        barrier();
        for (uint d = 1u; d < uint(SCAN_THREADS); d <<= 1u) {
            uint add[ROUNDS];
            for (int r = 0; r < ROUNDS; ++r) add[r] = uint(r) < live && t >= d ? s_sum[r * SCAN_THREADS + int(t - d)] : 0u;
            memoryBarrierShared();
            barrier();
            for (int r = 0; r < ROUNDS; ++r) if (uint(r) < live) s_sum[r * SCAN_THREADS + int(t)] += add[r];
            memoryBarrierShared();
            barrier();
        }
        for (int r = 0; r < ROUNDS; ++r) {
            if (uint(r) >= live) continue;
            uint q = q0 + uint(r * SCAN_THREADS) + t;
            if (q < quads) {
                uvec4 c = counts4[q];
                uint run = carry + s_sum[r * SCAN_THREADS + int(t)] - v[r];  // exclusive
                offsets4[q] = uvec4(run, run + c.x, run + c.x + c.y, run + c.x + c.y + c.z);
            }
            carry += s_sum[r * SCAN_THREADS + SCAN_THREADS - 1];
        }
        memoryBarrierShared();
        barrier();  // the next sweep overwrites s_sum
    }
    // the long lists summed in s_sum[0] (free after the last sweep; 8 rounds fill shared memory)
    if (t == 0u) s_sum[0] = 0u;
    memoryBarrierShared();
    barrier();
    if (long_lists > 0u) atomicAdd(s_sum[0], long_lists);
    memoryBarrierShared();
    barrier();
    // Offsets[tiles]: in the last quad written when tiles is not a multiple of four (the padded
    // counts are zero, so its offset is the total), else the first of the next
    if (t == 0u) {
        if (u_tile_count % 4u == 0u) offsets4[quads] = uvec4(carry);
        total = carry;
        long_tiles = s_sum[0];
#if SPLIT
        if (u_planned != 0u) long_tiles += split_header[4];
#endif
    }
}

#endif
