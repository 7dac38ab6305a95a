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
