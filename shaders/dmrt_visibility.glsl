// DMRT visibility stage, compute path (paper Section 5.1.1): one label layer (depth + label) of the
// proxy splats per run of the pair of passes
//   RESOLVE 0: z-buffer: atomicMin on the float bits of the camera z of every disc hit;
//   RESOLVE 1: label resolve: discs whose z bits equal the stored ones atomicMin their label
//              (ties between equal depths go to the smallest label, deterministically).
// Portable: no 64-bit atomics (Mesa llvmpipe has none). With INT64 1 (NVIDIA:
// GL_NV_shader_atomic_int64) one pass does both: atomicMin on the 64-bit key (z bits << 32 | label)
// into VisKey, which dmrt_layer_unpack then splits into the layer buffers - the same result
// (nearest z, ties to the smallest label) from half the splatting. Layer u_layer > 0 peels as in the paper:
// a disc hit is discarded where its label equals layer u_layer-1's label at that pixel or its
// depth is <= that layer's depth; where layer u_layer-1 is empty, so is this one.
// Each pass runs twice, LARGE 0 then LARGE 1 (see dmrt_splat_common.glsl).
#include "int64_atomics.glsl"
#include "dmrt_splat_common.glsl"

#if defined COMPUTE_SHADER

// k layers x (height x width), row-major from the top-left pixel, layer after layer.
layout(std430, binding = B_LAYER_DEPTH) buffer LayerDepth { uint layer_depth[]; };
layout(std430, binding = B_LAYER_LABEL) buffer LayerLabel { int layer_label[]; };

#if INT64
layout(std430, binding = B_VKEY) buffer VisKey { uint64_t vkey[]; };  // h x w, this layer
#endif

uniform int u_layer;

void visit(Splat s, int label, int col, int row) {
    float z = splat_depth_at(s, vec2(col, row) + 0.5);
    if (z <= 0.0) return;
    uint npix = uint(u_size.x * u_size.y);
    uint pix = uint(row * u_size.x + col);
    uint bits = floatBitsToUint(z);
    if (u_layer > 0) {
        uint prev = uint(u_layer - 1) * npix + pix;
        uint pb = layer_depth[prev];
        if (pb == EMPTY_BITS || bits <= pb || label == layer_label[prev]) return;
    }
#if INT64
    uint64_t key = packUint2x32(uvec2(uint(label), bits));  // z bits in the high word
    if (key < vkey[pix]) atomicMin(vkey[pix], key);
#else
    uint i = uint(u_layer) * npix + pix;
#if RESOLVE
    if (bits == layer_depth[i]) atomicMin(layer_label[i], label);
#else
    if (bits < layer_depth[i])  // a plain read first skips the atomics of hidden discs
        atomicMin(layer_depth[i], bits);
#endif
#endif
}

#endif
