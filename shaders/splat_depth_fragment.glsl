// Fragment stage shared by the raster depth-map programs. Included; no #version.
// Each fragment intersects its own pixel's ray with the disc (so discs give the exact depth of
// their plane, unlike screen-aligned splats), discards misses, and outputs camera z.

// Depth-test key: log-spaced camera z between these bounds. moderngl's depth buffers are 24-bit
// fixed point; log spacing gives every depth the same relative step (log2(1e10) / 2^24 = 1.4e-6)
// with no per-scene near/far to choose. Ties within a step are settled exactly by the MIN blend
// on the float32 colour target, so the stored z is the exact nearest one, as in the compute path.
#ifndef LOG_DEPTH_NEAR
#define LOG_DEPTH_NEAR 1e-4
#endif
#ifndef LOG_DEPTH_FAR
#define LOG_DEPTH_FAR 1e6
#endif

flat in vec3 f_pc;
flat in vec3 f_nc;
flat in float f_r;

layout(location = 0) out float out_z;

void main() {
    // gl_FragCoord.xy is the pixel centre (u, v): clip y is not flipped, so window row = image row
    float z = splat_depth_at(Splat(f_pc, f_nc, f_r), gl_FragCoord.xy);
    if (z <= 0.0) discard;
    out_z = z;
    gl_FragDepth = clamp(log2(z / LOG_DEPTH_NEAR) / log2(LOG_DEPTH_FAR / LOG_DEPTH_NEAR), 0.0, 1.0);
}
