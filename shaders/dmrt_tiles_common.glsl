// Tile-binned visibility stage (dmrt/runtime/tiles.py): what the binning and raster programs share.
// Included; no #version. The screen is cut into TILE x TILE pixel tiles, tile (tx, ty) has index
// ty * u_tiles.x + tx. A disc goes to every tile its conservative pixel box (splat_pixel_box, the
// box every other splat path tests) overlaps.
#include "dmrt_proxies.glsl"

#ifndef TILE
#define TILE 16
#endif

// Binding points (B_PROXIES, B_LARGE, B_LAYER_DEPTH, B_LAYER_LABEL, B_TILE_*) and the sentinels
// EMPTY_BITS, EMPTY_LABEL come from dmrt/gl/abi.py, injected as #defines by the loader.
uniform ivec2 u_tiles;  // tiles per row, tile rows
