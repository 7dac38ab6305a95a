// DMRT visibility stage, k-buffer path, second pass: the label layers from each pixel's sorted list
// of its K nearest fragments (dmrt_visibility_kbuffer.glsl). Depth peeling (layer i + 1 = the
// nearest fragment behind layer i with another label) picks, in depth order, the first fragment of
// each run of equal labels; so does this pass, walking the list once. Where the list is full and
// runs out before u_layers layers are found, the deeper layers stay empty (their fragments were not
// among the K nearest): u_overflow counts those pixels.
#if defined COMPUTE_SHADER

#include "dmrt_kbuffer_common.glsl"

layout(local_size_x = 8, local_size_y = 8) in;

layout(std430, binding = B_LAYER_DEPTH) writeonly buffer LayerDepth { uint layer_depth[]; };
layout(std430, binding = B_LAYER_LABEL) writeonly buffer LayerLabel { int layer_label[]; };
layout(std430, binding = B_OVERFLOW) buffer Overflow { uint overflow; };

uniform ivec2 u_size;
uniform int u_layers;

const uint LABEL_MASK = (1u << LABEL_BITS) - 1u;

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    uint npix = uint(u_size.x * u_size.y);
    uint pix = uint(p.y * u_size.x + p.x);
    uint base = pix * uint(SLOTS);
    int n = 0;
    uint prev_depth = 0u, prev_label = 0u;
    for (int j = 0; j < SLOTS && n < u_layers; ++j) {
        uint key = kbuf[base + uint(j)];
        if (key == EMPTY_BITS) break;
        uint label = key & LABEL_MASK, depth = key & ~LABEL_MASK;
        if (n > 0 && (label == prev_label || depth <= prev_depth)) continue;
        layer_depth[uint(n) * npix + pix] = depth;
        layer_label[uint(n) * npix + pix] = int(label);
        prev_depth = depth;
        prev_label = label;
        ++n;
    }
    if (n < u_layers && kbuf[base + uint(SLOTS - 1)] != EMPTY_BITS) atomicAdd(overflow, 1u);
    for (int i = n; i < u_layers; ++i) {
        layer_depth[uint(i) * npix + pix] = EMPTY_BITS;
        layer_label[uint(i) * npix + pix] = EMPTY_LABEL;
    }
}

#endif
