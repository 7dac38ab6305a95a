// Screen-space leveling, pass 1 (paper Section 5.2.3, last step): measure the colour offsets
// between photos along the seams of the frame. One thread per pixel p with a surface point q and
// final label a: for its right and lower neighbour, if that one carries another label b and lies
// on the same surface (depths within u_threshold), and photo b sees q too (its depth map agrees
// within u_visibility_tol), then log(colour of q in photo min(a,b)) - log(colour in photo max(a,b))
// per channel is added to that pair's sums. Channels outside [u_min_value, u_max_value] (black,
// clipped) carry no exposure information and make the sample be skipped.
//
// Pairs buffer: n x n entries (row = smaller label) of four ints: count, then the three channel
// sums in fixed point (1/LOG_SCALE).
#include "splat_depth_common.glsl"
#include "dmrt_frame.glsl"
#include "dmrt_photos.glsl"
#include "dmrt_photo_color.glsl"

#if defined COMPUTE_SHADER

layout(local_size_x = 8, local_size_y = 8) in;

layout(std430, binding = B_PAIRS) buffer Pairs { int pairs[]; };

uniform int u_photos;
uniform float u_threshold;       // metres: neighbours further apart in depth are another surface
uniform float u_visibility_tol;  // metres: photo b's depth map must agree with q this well
uniform float u_min_value;
uniform float u_max_value;

const float LOG_SCALE = 1024.0;

bool usable(vec3 c) {
    return all(greaterThanEqual(c, vec3(u_min_value))) && all(lessThanEqual(c, vec3(u_max_value)));
}

void seam(ivec2 p, Hit hit, ivec2 nb) {
    if (nb.x >= u_size.x || nb.y >= u_size.y) return;
    Hit other = hits[uint(nb.y * u_size.x + nb.x)];
    int a = hit.final_label, b = other.final_label;
    if (b < 0 || b == a || other.depth <= 0.0 || abs(other.depth - hit.depth) > u_threshold) return;
    vec3 q = pixel_point(p, hit.depth);
    Photo pb = photos[b];
    vec3 pc = to_photo(pb, q);
    if (pc.z <= 1e-6) return;
    bool ok;
    float d = surface_depth(b, pb, photo_uv(pb, pc), ok);
    if (!ok || abs(d - pc.z) > u_visibility_tol) return;
    vec3 ca = photo_color(a, q), cb = photo_color(b, q);
    if (!usable(ca) || !usable(cb)) return;
    vec3 diff = a < b ? log(ca) - log(cb) : log(cb) - log(ca);
    ivec3 fixed_diff = ivec3(round(diff * LOG_SCALE));
    uint base = 4u * uint(min(a, b) * u_photos + max(a, b));
    atomicAdd(pairs[base], 1);
    atomicAdd(pairs[base + 1u], fixed_diff.x);
    atomicAdd(pairs[base + 2u], fixed_diff.y);
    atomicAdd(pairs[base + 3u], fixed_diff.z);
}

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    Hit hit = hits[uint(p.y * u_size.x + p.x)];
    if (hit.depth <= 0.0 || hit.final_label < 0) return;
    seam(p, hit, p + ivec2(1, 0));
    seam(p, hit, p + ivec2(0, 1));
}

#endif
