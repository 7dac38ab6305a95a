// DMRT visibility stage, 64-bit path: split this layer's 64-bit keys (label in the low word, float
// bits of z in the high word; all ones = empty) into label layer u_layer of the layer buffers, and
// reset the keys for the next layer. Read as uvec2 pairs: no 64-bit types needed here.
#if defined COMPUTE_SHADER

layout(local_size_x = 8, local_size_y = 8) in;

layout(std430, binding = B_LAYER_DEPTH) writeonly buffer LayerDepth { uint layer_depth[]; };
layout(std430, binding = B_LAYER_LABEL) writeonly buffer LayerLabel { int layer_label[]; };
layout(std430, binding = B_VKEY) buffer VisKey { uvec2 vkey[]; };

uniform ivec2 u_size;
uniform int u_layer;

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    uint pix = uint(p.y * u_size.x + p.x);
    uint i = uint(u_layer) * uint(u_size.x * u_size.y) + pix;
    uvec2 v = vkey[pix];
    bool empty = v.y == EMPTY_BITS;
    layer_depth[i] = empty ? EMPTY_BITS : v.y;
    layer_label[i] = empty ? EMPTY_LABEL : int(v.x);
    vkey[pix] = uvec2(EMPTY_BITS);
}

#endif
