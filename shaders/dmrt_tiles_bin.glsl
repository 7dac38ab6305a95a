// Tile-binned visibility stage, binning (dmrt/runtime/tiles.py): which discs each screen tile needs.
// Run four times per frame, around the scan (dmrt_tiles_scan.glsl):
//   SCATTER 0, LARGE 0: one thread per proxy: cull (empty pixel box: behind the camera, off
//            screen), count the disc in every tile its pixel box overlaps (atomicAdd on Counts);
//            a disc over more than MAX_THREAD_TILES tiles is appended to the Large list instead,
//            whose header holds the dispatch-indirect arguments of the LARGE 1 passes (the host
//            resets it to zero workgroups and an empty list before this pass);
//   SCATTER 0, LARGE 1: workgroups of 256 threads striding over the large list, LARGE_BATCH discs at a
//            time, its threads over the batch's (disc, tile) pairs;
//   SCATTER 1, LARGE 0/1: the same walk again, writing the proxy index and its box in the tile
//            (box_bits, which the raster and labeling passes test pixels against) into the tile's
//            slice of Entries: slot = Offsets[tile] + (Counts[tile] decremented atomically) - 1, so the
//            counts are back to 0 afterwards and the order within a slice is arbitrary (the raster
//            and labeling passes take minima, which need no order). Entries at or past u_capacity
//            are dropped (the host grows the buffer from the frame's total, dmrt_tiles_scan.glsl).
// Both walks recompute the disc's box (cheaper than storing it): the same box, so the same tiles.
// The raster and labeling passes read it from the entry instead of computing it for every tile.
//
// Buffers (binding: layout):
//   B_PROXIES       n x 8 floats (dmrt_tiles_common.glsl)
//   B_LARGE         uint groups_x, groups_y, groups_z, n_large; uint large[n]  (proxy indices)
//   B_TILE_ENTRIES  uvec2[capacity]: proxy index, box_bits in the tile; tile after tile
//   B_TILE_COUNTS   uint[tiles]: discs per tile
//   B_TILE_OFFSETS  uint[tiles + 1]: exclusive prefix sum of Counts (SCATTER 1 only)
#include "dmrt_tiles_common.glsl"

#if defined COMPUTE_SHADER

#ifndef SCATTER
#define SCATTER 0
#endif
#ifndef LARGE
#define LARGE 0
#endif
#ifndef MAX_THREAD_TILES
#define MAX_THREAD_TILES 16
#endif
#define LARGE_BATCH 32u     // large discs a workgroup takes at a time
#define LARGE_GROUPS 1024u  // workgroups striding over the large list

layout(std430, binding = B_LARGE) buffer Large { uint groups_x; uint groups_y; uint groups_z; uint n_large; uint large[]; };
layout(std430, binding = B_TILE_COUNTS) buffer Counts { uint counts[]; };
#if SCATTER
layout(std430, binding = B_TILE_ENTRIES) writeonly buffer Entries { uvec2 entries[]; };
layout(std430, binding = B_TILE_OFFSETS) readonly buffer Offsets { uint offsets[]; };
uniform uint u_capacity;  // entries the buffer holds
#endif

uniform uint u_count;  // number of proxies

// Disc k, whose pixel box is `box`, in tile (tx, ty).
void bin_into(int tx, int ty, uint k, ivec4 box) {
    uint tile = uint(ty * u_tiles.x + tx);
#if SCATTER
    uint pos = offsets[tile] + atomicAdd(counts[tile], ~0u) - 1u;  // decrement: adding 2^32 - 1
    if (pos < u_capacity) entries[pos] = uvec2(k, box_bits(box, ivec2(tx, ty) * TILE));
#else
    atomicAdd(counts[tile], 1u);
#endif
}

#if LARGE

// A workgroup bins LARGE_BATCH listed discs at a time: its first invocations load the discs and their
// boxes into shared memory, then every invocation takes the batch's (disc, tile) pairs in turn, so
// none waits on a disc's loads between its tiles. (A workgroup a disc, looping over the list, took
// 0.057 ms (count) and 0.100 ms (scatter) at 3840x2160 on an H200, session 20; 32 invocations a disc
// 0.148 / 0.416.)
layout(local_size_x = 256) in;

shared uint s_disc[LARGE_BATCH];
shared ivec4 s_box[LARGE_BATCH];
shared uint s_first[LARGE_BATCH + 1u];  // the batch's pairs before its disc d

void main() {
    uint t = gl_LocalInvocationID.x;
    for (uint b0 = gl_WorkGroupID.x * LARGE_BATCH; b0 < n_large; b0 += gl_NumWorkGroups.x * LARGE_BATCH) {
        uint n = min(LARGE_BATCH, n_large - b0);
        if (t < n) {
            uint k = large[b0 + t];
            int label;
            ivec4 box = splat_pixel_box(load_proxy(k, label));
            ivec4 tb = box / TILE;  // the box is non-empty and non-negative here
            s_disc[t] = k;
            s_box[t] = box;
            s_first[t + 1u] = uint((tb.z - tb.x + 1) * (tb.w - tb.y + 1));
        }
        memoryBarrierShared();
        barrier();
        if (t == 0u) {
            s_first[0] = 0u;
            for (uint d = 1u; d <= n; ++d) s_first[d] += s_first[d - 1u];
        }
        memoryBarrierShared();
        barrier();
        for (uint j = t; j < s_first[n]; j += gl_WorkGroupSize.x) {
            uint d = 0u, hi = n - 1u;  // the disc d with s_first[d] <= j < s_first[d + 1]
            while (d < hi) {
                uint mid = (d + hi + 1u) >> 1u;
                if (s_first[mid] <= j) d = mid; else hi = mid - 1u;
            }
            ivec4 box = s_box[d];
            ivec4 tb = box / TILE;
            int w = tb.z - tb.x + 1, i = int(j - s_first[d]);
            bin_into(tb.x + i % w, tb.y + i / w, s_disc[d], box);
        }
        barrier();  // the next batch overwrites the shared arrays
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
        if (box.x > box.z || box.y > box.w) continue;  // culled
        ivec4 tb = box / TILE;
        if ((tb.z - tb.x + 1) * (tb.w - tb.y + 1) > MAX_THREAD_TILES) {
#if !SCATTER
            uint i = atomicAdd(n_large, 1u);
            large[i] = k;
            atomicMax(groups_x, min(i / LARGE_BATCH + 1u, LARGE_GROUPS));
#endif
            continue;
        }
        for (int ty = tb.y; ty <= tb.w; ++ty)
            for (int tx = tb.x; tx <= tb.z; ++tx)
                bin_into(tx, ty, k, box);
    }
}

#endif
#endif
