// Tile-binned visibility stage (dmrt/runtime/tiles.py): what the binning and raster programs share.
// Included; no #version. The screen is cut into TILE x TILE pixel tiles, tile (tx, ty) has index
// ty * u_tiles.x + tx. A disc goes to every tile its conservative pixel box (splat_pixel_box, the
// box every other splat path tests) overlaps.
#include "dmrt_proxies.glsl"

#ifndef TILE
#define TILE 16
#endif

// The raster's first walk notes, per pixel, which of its tile's first MASK_DISCS discs hit it (a bit
// each, eight words); with TILE 16 the labeling pass's first batch of TILE^2 discs is exactly those,
// so it reads the bits (B_TILE_MASKS) instead of testing the discs again. (Masks of 128 discs, four
// registers fewer, did not speed the raster up: reports/frame-h200, session 16.)
#define MASK_DISCS 256

// The masks' second half (discs 128-255) is written and read only for a list longer than 128 discs:
// the first half holds every hit of a shorter one (half the masks' bytes at 3840x2160, where a tile
// holds ~63 discs). `count`: the list's length as cut to the buffer.
bool masks_second_half(uint count) {
    return count > uint(MASK_DISCS / 2);
}
#ifndef HIT_MASKS  // the stage turns them off for a renderer without the labeling pass
#define HIT_MASKS (TILE * TILE == MASK_DISCS)
#endif

// The pixel of this invocation within its tile. WARP_BLOCKS (TILE a multiple of 8): each run of 32
// invocations (an NVIDIA warp, which runs in lockstep) covers an 8 x 4 block instead of two 16-pixel
// rows, so a disc's pixel box overlaps fewer warps, and the per-disc work of the raster's walk (the
// test, the insertion into the nearest hits) runs for fewer warps in which no lane needs it.
#ifndef WARP_BLOCKS
#define WARP_BLOCKS 0
#endif
#if defined COMPUTE_SHADER
ivec2 tile_local_pixel() {
#if WARP_BLOCKS && TILE % 8 == 0
    uint lid = gl_LocalInvocationIndex;
    uint w = lid >> 5u, lane = lid & 31u;
    return ivec2((w % uint(TILE / 8)) * 8u + (lane & 7u), (w / uint(TILE / 8)) * 4u + (lane >> 3u));
#else
    return ivec2(gl_LocalInvocationID.xy);
#endif
}
#endif

// A disc's pixel box (splat_pixel_box) where it meets a tile, in one word of shared memory: bit x
// for each of the tile's columns x it spans, bit 16 + y for each of its rows y (none: 0). A pixel
// lies in the box when its column's and its row's bits are both set (in_box: one AND, one compare;
// the corners' four compares and their unpacking cost more on the raster's hot path). `origin`: the
// tile's first pixel.
#if TILE > 16
#error "TILE must be at most 16 (a tile's columns and rows are the halves of a box word)"
#endif
uint box_bits(ivec4 box, ivec2 origin) {
    ivec2 lo = max(box.xy - origin, ivec2(0));
    ivec2 hi = min(box.zw - origin, ivec2(TILE - 1));
    if (any(greaterThan(lo, hi))) return 0u;
    uvec2 span = ((uvec2(2u) << uvec2(hi)) - 1u) & ~((uvec2(1u) << uvec2(lo)) - 1u);
    return span.x | (span.y << 16);
}

// A pixel's bits: its column's and its row's (local: its position in the tile).
uint pixel_bits(ivec2 local) {
    return (1u << uint(local.x)) | (1u << uint(16 + local.y));
}

bool in_box(uint pixel, uint box) {
    return (box & pixel) == pixel;
}

// Binding points (B_PROXIES, B_LARGE, B_LAYER_DEPTH, B_LAYER_LABEL, B_TILE_*) and the sentinels
// EMPTY_BITS, EMPTY_LABEL come from dmrt/gl/abi.py, injected as #defines by the loader.
uniform ivec2 u_tiles;  // tiles per row, tile rows

// -- long lists split over workgroups (TileVisibility's split_min) ------------------------------
// After the count, a plan pass (dmrt_tiles_split.glsl, STEP 0) takes each tile whose list is longer
// than u_split_min out of the tile lists: its count goes to 0 (the scan gives it an empty slice of
// Entries, which the raster and labeling passes walk as any empty list) and the scatter writes its
// discs into the split buffer instead (SPLIT 1 in dmrt_tiles_bin.glsl). Per layer, a pass with a
// workgroup per slice of BATCH of its discs writes each pixel's result over the slice (its
// partial), and a pass with a workgroup per split tile takes the smallest of its slices' (STEP 1,
// 2; the labeling pass's SPLIT_PASS 1, 2). The raster and labeling passes themselves are the ones
// without the split. The buffer's layout is dmrt/gl/abi.py's B_TILE_SPLIT, in uint words.
#ifndef SPLIT_BUFFER
#define SPLIT_BUFFER 0
#endif
#if SPLIT_BUFFER
#ifndef BATCH
#define BATCH 288  // discs a slice: the raster's batch (TileVisibility.batch, a define of every tiles program)
#endif
layout(std430, binding = B_TILE_SPLIT) buffer Split { uint split[]; };
uniform uint u_slots;          // slices the buffer holds
uniform uint u_split_entries;  // discs it holds

struct SplitSlice {
    uint tile;   // the tile (ty * tiles per row + tx)
    uint first;  // the tile's first slice
    uint count;  // the tile's slices
    uint index;  // this slice's index among them: discs [index * BATCH, (index + 1) * BATCH) of the tile's
};

uint split_tiles() { return uint(u_tiles.x * u_tiles.y); }
uint split_tile_items_at() { return 8u + 4u * u_slots; }
uint split_base_at() { return 8u + 8u * u_slots; }              // per tile: its first disc, EMPTY_BITS: not split
uint split_count_at() { return split_base_at() + split_tiles(); }  // per tile: its discs
uint split_left_at() { return split_count_at() + split_tiles(); }  // per tile: its discs not yet scattered
uint split_partial_at(uint slot) { return split_left_at() + split_tiles() + 2u * uint(TILE * TILE) * slot; }
uint split_entries_at() { return split_partial_at(u_slots); }   // uvec2 a disc, as Entries

// Slice `slot` of the slice pass's dispatch.
SplitSlice split_slice(uint slot) {
    uint o = 8u + 4u * slot;
    return SplitSlice(split[o], split[o + 1u], split[o + 2u], split[o + 3u]);
}

// Split tile `i` of the merge pass's dispatch (index 0).
SplitSlice split_tile(uint i) {
    uint o = split_tile_items_at() + 4u * i;
    return SplitSlice(split[o], split[o + 1u], split[o + 2u], 0u);
}

ivec2 split_tile_origin(uint tile) {
    return ivec2(int(tile % uint(u_tiles.x)), int(tile / uint(u_tiles.x))) * TILE;
}

// The slice's discs: [first, end) of the split entries.
uvec2 split_slice_range(SplitSlice slice) {
    uint first = split[split_base_at() + slice.tile] + slice.index * uint(BATCH);
    uint end = split[split_base_at() + slice.tile] + split[split_count_at() + slice.tile];
    return uvec2(first, min(end, first + uint(BATCH)));
}

uvec2 split_entry(uint i) {
    return uvec2(split[split_entries_at() + 2u * i], split[split_entries_at() + 2u * i + 1u]);
}

// The slice pass: the slice's result for pixel `lid` of its tile (a key, smaller is better:
// (depth or distance bits, label)).
void split_write_partial(SplitSlice slice, uint lid, uvec2 key) {
    uint at = split_partial_at(slice.first + slice.index) + 2u * lid;
    split[at] = key.x;
    split[at + 1u] = key.y;
}

// The merge pass: the smallest of the tile's slices' results for pixel `lid`.
uvec2 split_merged(SplitSlice tile, uint lid) {
    uvec2 best = uvec2(EMPTY_BITS);
    for (uint q = tile.first; q < tile.first + tile.count; ++q) {
        uint a = split_partial_at(q) + 2u * lid;
        uvec2 v = uvec2(split[a], split[a + 1u]);
        if (v.x < best.x || (v.x == best.x && v.y < best.y)) best = v;
    }
    return best;
}
#endif
