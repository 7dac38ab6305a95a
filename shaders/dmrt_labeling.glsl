// DMRT labeling pass (paper Section 5.2.1): a geometry-aware Voronoi decomposition of the screen.
// The proxies are splatted again over their footprints (the pixels whose ray meets the disc, the
// same test as the visibility stage), but the z-buffer key of disc c_j at pixel p is the 3D
// distance |c_j - q_p| to the raytraced surface point q_p of that pixel, so each pixel keeps the
// label of its nearest covering proxy. Only pixels with a raytraced hit take part.
//   RESOLVE 0: atomicMin of the distance bits;  RESOLVE 1: equal distance -> atomicMin label;
//   INT64 1 (NVIDIA): one pass, atomicMin of (distance bits << 32 | label) into Key (8 bytes/pixel).
// Distances are taken in the render camera's space (rotation invariant: the same as in the world).
#include "int64_atomics.glsl"
#include "dmrt_splat_common.glsl"
#include "dmrt_frame.glsl"

#if defined COMPUTE_SHADER

#if INT64
layout(std430, binding = B_KEY) buffer Key { uint64_t key[]; };
#else
layout(std430, binding = B_KEY) buffer Key { uint key[]; };
layout(std430, binding = B_VLABEL) buffer Label { int vlabel[]; };
#endif

void visit(Splat s, int label, int col, int row) {
    vec2 uv = vec2(col, row) + 0.5;
    if (splat_depth_at(s, uv) <= 0.0) return;
    uint pix = uint(row * u_size.x + col);
    float z = hits[pix].depth;
    if (z <= 0.0) return;
    uint bits = floatBitsToUint(distance(z * camera_ray(uv), s.pc));
#if INT64
    uint64_t k = packUint2x32(uvec2(uint(label), bits));
    if (k < key[pix]) atomicMin(key[pix], k);
#elif RESOLVE
    if (bits == key[pix]) atomicMin(vlabel[pix], label);
#else
    if (bits < key[pix]) atomicMin(key[pix], bits);
#endif
}

#endif
