// DMRT visibility stage, 64-bit path: split this layer's 64-bit keys (label in the low word, float
// bits of z in the high word; all ones = empty) into label layer u_layer of the layer buffers, and
// reset the keys for the next layer. Read as uvec2 pairs: no 64-bit types needed here.
#if defined COMPUTE_SHADER

layout(local_size_x = 8, local_size_y = 8) in;

layout(std430, binding = 1) writeonly buffer LayerDepth { uint layer_depth[]; };
layout(std430, binding = 2) writeonly buffer LayerLabel { int layer_label[]; };
layout(std430, binding = 4) buffer VisKey { uvec2 vkey[]; };

uniform ivec2 u_size;
uniform int u_layer;

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    uint pix = uint(p.y * u_size.x + p.x);
    uint i = uint(u_layer) * uint(u_size.x * u_size.y) + pix;
    uvec2 v = vkey[pix];
    bool empty = v.y == 0xFFFFFFFFu;
    layer_depth[i] = empty ? 0xFFFFFFFFu : v.y;
    layer_label[i] = empty ? 0x7FFFFFFF : int(v.x);
    vkey[pix] = uvec2(0xFFFFFFFFu);
}

#endif
