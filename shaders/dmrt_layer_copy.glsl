// DMRT raster visibility path: copy a float32 render target into label layer u_layer of the layer
// buffers (dmrt/runtime/visibility.py): u_resolve 0 = camera z -> float bits (clear value -> empty),
// u_resolve 1 = label (stored as float, exact below 2^24) -> int (clear value -> empty).
#if defined COMPUTE_SHADER

layout(local_size_x = 8, local_size_y = 8) in;

layout(std430, binding = B_LAYER_DEPTH) buffer LayerDepth { uint layer_depth[]; };
layout(std430, binding = B_LAYER_LABEL) buffer LayerLabel { int layer_label[]; };

uniform sampler2D u_src;
uniform ivec2 u_size;
uniform int u_layer;
uniform int u_resolve;


void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    uint i = uint(u_layer) * uint(u_size.x * u_size.y) + uint(p.y * u_size.x + p.x);
    float v = texelFetch(u_src, p, 0).r;
    if (u_resolve != 0)
        layer_label[i] = v >= EMPTY_Z ? EMPTY_LABEL : int(v);
    else
        layer_depth[i] = v >= EMPTY_Z ? EMPTY_BITS : floatBitsToUint(v);
}

#endif
