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
// so it reads the bits (B_TILE_MASKS) instead of testing the discs again.
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

// A disc's pixel box (splat_pixel_box) in 8 bytes of shared memory: col0 | row0 << 16,
// col1 | row1 << 16. A disc in a tile's list overlaps the tile, so its box is not empty and its
// coordinates lie in 0..65535 (frames are smaller).
uvec2 pack_box(ivec4 box) {
    return uvec2(uint(box.x) | (uint(box.y) << 16), uint(box.z) | (uint(box.w) << 16));
}

bool in_box(uvec2 px, uvec2 b) {
    return px.x >= (b.x & 0xFFFFu) && px.x <= (b.y & 0xFFFFu) && px.y >= (b.x >> 16) && px.y <= (b.y >> 16);
}

// Binding points (B_PROXIES, B_LARGE, B_LAYER_DEPTH, B_LAYER_LABEL, B_TILE_*) and the sentinels
// EMPTY_BITS, EMPTY_LABEL come from dmrt/gl/abi.py, injected as #defines by the loader.
uniform ivec2 u_tiles;  // tiles per row, tile rows
