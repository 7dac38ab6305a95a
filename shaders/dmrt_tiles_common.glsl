// Tile-binned visibility stage (dmrt/runtime/tiles.py): what the binning and raster programs share.
// Included; no #version. The screen is cut into TILE x TILE pixel tiles, tile (tx, ty) has index
// ty * u_tiles.x + tx. A disc goes to every tile its conservative pixel box (splat_pixel_box, the
// box every other splat path tests) overlaps, keyed by its near depth (near_key).
#include "dmrt_proxies.glsl"

#ifndef TILE
#define TILE 16
#endif

// Binding points (B_PROXIES, B_LARGE, B_LAYER_DEPTH, B_LAYER_LABEL, B_TILE_*) and the sentinels
// EMPTY_BITS, EMPTY_LABEL come from dmrt/gl/abi.py, injected as #defines by the loader.
uniform ivec2 u_tiles;  // tiles per row, tile rows

// Float bits of a lower bound of every depth splat_depth_at can return for the disc: the disc's
// nearest camera z (centre z minus its half-extent in z), lowered by 2e-4 of its distance, which
// covers the float32 error of the ray-plane depth (up to ~1e3 ulp for the most grazing rays the
// regular branch takes, |cos| = GRAZING_COS) and of the rim test. Clamped at 0: a disc reaching
// the camera plane sorts first. Non-negative floats order like their bits, so keys compare as uint.
uint near_key(Splat s) {
    float extent = s.r * sqrt(max(1.0 - s.nc.z * s.nc.z, 0.0));
    float near = s.pc.z - extent - 2e-4 * (abs(s.pc.z) + s.r);
    return floatBitsToUint(max(near, 0.0));
}
