// Tile-binned visibility stage, binning (dmrt/runtime/tiles.py): which discs each screen tile needs.
// Run four times per frame, around the scan (dmrt_tiles_scan.glsl):
//   SCATTER 0, LARGE 0: one thread per proxy: cull (empty pixel box: behind the camera, off
//            screen), count the disc in every tile its pixel box overlaps (atomicAdd on Counts);
//            a disc over more than MAX_THREAD_TILES tiles is appended to the Large list instead,
//            whose header holds the dispatch-indirect arguments of the LARGE 1 passes (the host
//            resets it to zero workgroups and an empty list before this pass);
//   SCATTER 0, LARGE 1: one workgroup per listed large disc, its threads striding over its tiles;
//   SCATTER 1, LARGE 0/1: the same walk again, writing the proxy index and its box in the tile
//            (box_bits, which the raster and labeling passes test pixels against) into the tile's
//            slice of Entries: slot = Offsets[tile] + (Counts[tile] decremented atomically) - 1, so the
//            counts are back to 0 afterwards and the order within a slice is arbitrary (the raster
//            and labeling passes take minima, which need no order). Entries at or past u_capacity
//            are dropped (the host grows the buffer from the frame's total, dmrt_tiles_scan.glsl).
//   SPLIT 1 (with SCATTER 1): a tile whose list the split plan took over (dmrt_tiles_split.glsl,
//            STEP 0: its count set to 0) gets its discs in the split buffer instead, at its base
//            there + (its count left, decremented atomically) - 1.
// Both walks recompute the disc's box (cheaper than storing it): the same box, so the same tiles.
// The raster and labeling passes read it from the entry instead of computing it for every tile.
//
// Buffers (binding: layout):
//   B_PROXIES       n x 8 floats (dmrt_tiles_common.glsl)
//   B_LARGE         uint groups_x, groups_y, groups_z, n_large; uint large[n]  (proxy indices)
//   B_TILE_ENTRIES  uvec2[capacity]: proxy index, box_bits in the tile; tile after tile
//   B_TILE_COUNTS   uint[tiles]: discs per tile
//   B_TILE_OFFSETS  uint[tiles + 1]: exclusive prefix sum of Counts (SCATTER 1 only)
//   B_TILE_SPLIT    SPLIT 1: the long lists' discs (dmrt_tiles_common.glsl)
#ifndef SPLIT
#define SPLIT 0
#endif
#define SPLIT_BUFFER SPLIT
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
#if SPLIT
    uint base = split[split_base_at() + tile];
    if (base != EMPTY_BITS) {  // a long list, taken over by the split passes
        uint at = split_entries_at() + 2u * (base + atomicAdd(split[split_left_at() + tile], ~0u) - 1u);
        split[at] = k;
        split[at + 1u] = box_bits(box, ivec2(tx, ty) * TILE);
        return;
    }
#endif
    uint pos = offsets[tile] + atomicAdd(counts[tile], ~0u) - 1u;  // decrement: adding 2^32 - 1
    if (pos < u_capacity) entries[pos] = uvec2(k, box_bits(box, ivec2(tx, ty) * TILE));
#else
    atomicAdd(counts[tile], 1u);
#endif
}

#if LARGE

layout(local_size_x = 256) in;

void main() {
    for (uint i = gl_WorkGroupID.x; i < n_large; i += gl_NumWorkGroups.x) {
        uint k = large[i];
        int label;
        Splat s = load_proxy(k, label);
        ivec4 box = splat_pixel_box(s);
        ivec4 tb = box / TILE;  // the box is non-empty and non-negative here
        int w = tb.z - tb.x + 1;
        int n = w * (tb.w - tb.y + 1);
        for (int j = int(gl_LocalInvocationID.x); j < n; j += int(gl_WorkGroupSize.x))
            bin_into(tb.x + j % w, tb.y + j / w, k, box);
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
            atomicMax(groups_x, min(i + 1u, LARGE_GROUPS));
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
