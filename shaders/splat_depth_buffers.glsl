// Storage buffers of the compute depth-map programs. Included; no #version.

// n splats x 7 floats: position xyz (metres, scene-origin-relative), normal xyz, radius (metres).
// Plain floats, not vec3: std430 would pad a vec3 array to 16 bytes per element.
layout(std430, binding = B_SPLATS) readonly buffer Splats { float splats[]; };

// One uint per pixel, row-major from the top-left: the bits of the nearest camera z. Positive IEEE
// floats order like their bit patterns read as uints, so atomicMin on the bits is a z-buffer;
// 0xFFFFFFFF (a NaN pattern, above every finite float) marks an empty pixel.
layout(std430, binding = B_DEPTH_BITS) buffer Depth { uint depth_bits[]; };

// Splats too big for one thread, deferred to splat_depth_compute_large: its indirect dispatch
// (groups_x = min(count, LARGE_GROUPS), 1, 1: no workgroups at all when no disc is large, which
// llvmpipe would otherwise spend ~10 ms per map starting), the count, then the splat indices (in
// the batch, of every run splatted into the batch since the list was reset).
layout(std430, binding = B_DEPTH_LARGE) buffer Large { uint groups_x; uint groups_y; uint groups_z; uint n_large; uint large[]; };

#ifndef LARGE_GROUPS
#define LARGE_GROUPS 1024u
#endif

#ifndef CHECK_BEFORE_ATOMIC
#define CHECK_BEFORE_ATOMIC 1
#endif

uniform uint u_count;  // number of splats in this batch (splat_depth_compute: in this run of it)

Splat load_splat(uint k) {
    uint o = 7u * k;
    return splat_to_camera(vec3(splats[o], splats[o + 1u], splats[o + 2u]),
                           vec3(splats[o + 3u], splats[o + 4u], splats[o + 5u]), splats[o + 6u]);
}

void splat_pixel(Splat s, int col, int row) {
    float z = splat_depth_at(s, vec2(col, row) + 0.5);
    if (z > 0.0) {
        uint i = uint(row * u_size.x + col);
        uint bits = floatBitsToUint(z);
#if CHECK_BEFORE_ATOMIC
        if (bits < depth_bits[i])  // a plain read first skips the atomics of hidden discs
#endif
            atomicMin(depth_bits[i], bits);
    }
}
