// The proxy discs P_LD on the GPU and their loader, shared by every screen-space splat path (the
// compute passes of dmrt_splat_common.glsl and the tiles of dmrt_tiles_common.glsl), so that every
// path evaluates the same disc. Included; no #version.
#include "splat_depth_common.glsl"

// n proxies x PROXY_FLOATS floats: position xyz (metres, scene-origin-relative), radius (metres),
// normal xyz, label (int bits); plain floats: std430 would pad vec3 arrays
// (dmrt.runtime.visibility.pack_proxies writes them).
layout(std430, binding = B_PROXIES) readonly buffer Proxies { float proxies[]; };

Splat load_proxy(uint k, out int label) {
    uint o = uint(PROXY_FLOATS) * k;
    label = floatBitsToInt(proxies[o + 7u]);
    return splat_to_camera(vec3(proxies[o], proxies[o + 1u], proxies[o + 2u]),
                           vec3(proxies[o + 4u], proxies[o + 5u], proxies[o + 6u]), proxies[o + 3u]);
}
