// Fragment stage of the raster visibility programs (paper Section 5.1.1). Included; no #version.
// Each fragment intersects its pixel's ray with the disc (splat_depth_at, the compute path's very
// test), applies the depth-peeling test against layer u_layer-1 (read from the layer buffers), and
// outputs into a float32 target under a MIN blend:
//   u_resolve 0: the camera z (the blend keeps the exact nearest one: a z-buffer);
//   u_resolve 1: the label of fragments whose z equals the layer's stored z (the blend keeps the
//                smallest label, as the compute path's atomicMin does). Labels < 2^24 are exact.

flat in vec3 f_pc;
flat in vec3 f_nc;
flat in float f_r;
flat in int f_label;

layout(std430, binding = B_LAYER_DEPTH) readonly buffer LayerDepth { uint layer_depth[]; };
layout(std430, binding = B_LAYER_LABEL) readonly buffer LayerLabel { int layer_label[]; };

uniform int u_layer;
uniform int u_resolve;

layout(location = 0) out float out_value;

void main() {
    // gl_FragCoord.xy is the pixel centre (u, v): clip y is not flipped, so window row = image row
    float z = splat_depth_at(Splat(f_pc, f_nc, f_r), gl_FragCoord.xy);
    if (z <= 0.0) discard;
    ivec2 p = ivec2(gl_FragCoord.xy);
    uint npix = uint(u_size.x * u_size.y);
    uint pix = uint(p.y * u_size.x + p.x);
    uint bits = floatBitsToUint(z);
    if (u_layer > 0) {
        uint prev = uint(u_layer - 1) * npix + pix;
        uint pb = layer_depth[prev];
        if (pb == EMPTY_BITS || bits <= pb || f_label == layer_label[prev]) discard;
    }
    if (u_resolve != 0) {
        if (bits != layer_depth[uint(u_layer) * npix + pix]) discard;
        out_value = float(f_label);
    } else {
        out_value = z;
    }
}
