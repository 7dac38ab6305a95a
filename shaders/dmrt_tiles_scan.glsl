// Tile-binned visibility stage, scan (dmrt/runtime/tiles.py): the exclusive prefix sum of the
// per-tile disc counts, i.e. where each tile's slice of the Entries list starts.
// One workgroup of SCAN_THREADS threads: thread t sums a contiguous run of ceil(tiles / SCAN_THREADS)
// counts, the run sums are scanned in shared memory (Hillis-Steele), then each thread writes its
// run's offsets. Tens of thousands of tiles (3840 x 2160 / 16^2 = 32400) take a few microseconds;
// a multi-workgroup scan would only pay off at millions.
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

layout(local_size_x = SCAN_THREADS) in;

layout(std430, binding = B_FRAME_STATUS) buffer Status { uint total; };  // tile_total
layout(std430, binding = B_TILE_COUNTS) readonly buffer Counts { uint counts[]; };
layout(std430, binding = B_TILE_OFFSETS) writeonly buffer Offsets { uint offsets[]; };

uniform uint u_tile_count;  // tiles_x * tiles_y

shared uint s_sum[SCAN_THREADS];

void main() {
    uint t = gl_LocalInvocationID.x;
    uint per = (u_tile_count + uint(SCAN_THREADS) - 1u) / uint(SCAN_THREADS);
    uint b = min(t * per, u_tile_count), e = min(b + per, u_tile_count);
    uint sum = 0u;
    for (uint i = b; i < e; ++i) sum += counts[i];
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
    for (uint i = b; i < e; ++i) {
        offsets[i] = run;
        run += counts[i];
    }
    if (t == uint(SCAN_THREADS) - 1u) {
        offsets[u_tile_count] = s_sum[t];
        total = s_sum[t];
    }
}

#endif
