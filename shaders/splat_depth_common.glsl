// Oriented circular splats (disc of radius r centred at p with unit normal n) seen by a pinhole
// camera in COLMAP/OpenCV axes (x right, y down, z forward). Shared by every depth-map program so
// that the raster and compute paths evaluate the very same per-pixel test. Included; no #version.
//
// Pixel (row i, column j) has centre (u, v) = (j + 0.5, i + 0.5); its ray in camera space is
// d = ((u - cx) / fx, (v - cy) / fy, 1), so a point at parameter s on it has camera depth z = s.

uniform mat3 u_R;      // world -> camera rotation (column-major, as GLSL reads it)
uniform vec3 u_t;      // world -> camera translation, metres (positions are scene-origin-relative)
uniform vec4 u_K;      // fx, fy, cx, cy in pixels of the depth map
uniform ivec2 u_size;  // depth-map width, height in pixels

// Below this |cos| between the disc normal and the pixel ray the ray (almost) lies in the disc's
// plane: the ray-plane depth dot(n, p) / dot(n, d) is then ill-conditioned (a float32 rounding of n
// moves it by metres), and the true answer is a whole chord of the disc. Such rays take the depth
// of the disc's centre instead, where they pass within r of it. 1e-3 = within 0.06 degrees of the
// plane: the footprint of an exactly edge-on disc is a line one or two pixels wide, so this only
// decides depth on that line and never inflates a disc into a screen-aligned one.
#ifndef GRAZING_COS
#define GRAZING_COS 1e-3
#endif

struct Splat {
    vec3 pc;  // centre, camera space, metres
    vec3 nc;  // unit normal, camera space (either side: discs are two-sided)
    float r;  // radius, metres
};

Splat splat_to_camera(vec3 p, vec3 n, float r) {
    Splat s;
    s.pc = u_R * p + u_t;
    float len = length(n);
    // a missing (zero) normal: let the disc face the camera rather than vanish
    s.nc = len > 0.0 ? (u_R * n) / len : -normalize(s.pc);
    s.r = r;
    return s;
}

// Projected extent along one image axis of the sphere (a, z, r) (a = x or y): exact perspective
// bounds from the two planes through the camera centre tangent to the sphere. Needs z > r.
vec2 sphere_bounds(float a, float z, float r, float f, float c) {
    float den = z * z - r * r;
    float h = r * sqrt(max(a * a + den, 0.0));
    return vec2((a * z - h) / den, (a * z + h) / den) * f + c;
}

// Pixel range along one image axis of a sphere (a, z, r) that reaches the camera plane (z <= r).
// Unbounded, except where the sphere lies wholly on one side of the plane a = 0 (|a| > r): each of
// its points (a', z') in front of the camera then has |a'| / z' >= (|a| - r) / (z + r), which
// bounds the range from one side. (Without this, the discs that every wall and floor has near the
// camera plane would each test the whole map: ~0.1 % of a room scan's points, most of the time.)
// Widened towards the centre by 0.1 % + 0.01 px, like the bounded case.
vec2 plane_crossing_bounds(float a, float z, float r, float f, float c) {
    const float UNBOUNDED = 1e30;
    float edge = (abs(a) - r) / (z + r) * f * (1.0 - 1e-3) - 0.01;  // pixels from c
    if (edge <= 0.0) return vec2(-UNBOUNDED, UNBOUNDED);
    return a > 0.0 ? vec2(c + edge, UNBOUNDED) : vec2(-UNBOUNDED, c - edge);
}

// Projected extent along one image axis of the disc (centre (a, z), normal (na, nz) in that axis'
// plane, the remaining normal component nb, radius r): the image coordinates X = a'/z' of the two
// planes through the camera centre tangent to the disc. A plane with normal m meets the disc iff
// (m.c)^2 <= r^2 (|m|^2 - (m.n)^2); with m = (1, -X) that is the quadratic
//     (z^2 - r^2 (1 - nz^2)) X^2 - 2 (a z + r^2 na nz) X + (a^2 - r^2 (1 - na^2)) <= 0,
// whose discriminant, expanded so that float32 does not cancel it, is
//     r^2 (a^2 + z^2 - (z na - a nz)^2 - r^2 nb^2).
// Exact for the disc (a sphere bound is as wide as the disc's diameter even where the disc is
// seen edge-on: floors and walls at grazing angles, the most common discs in a building).
// Needs z > r sqrt(1 - nz^2): the whole disc in front of the camera.
vec2 disc_bounds(float a, float z, float na, float nz, float nb, float r, float f, float c) {
    float r2 = r * r;
    float A = z * z - r2 * (1.0 - nz * nz);
    float B = a * z + r2 * na * nz;
    float zn = z * na - a * nz;
    float h = r * sqrt(max(a * a + z * z - zn * zn - r2 * nb * nb, 0.0));
    return vec2((B - h) / A, (B + h) / A) * f + c;
}

// Inclusive pixel box (col0, row0, col1, row1) holding every pixel centre whose ray can meet the
// disc; empty (col0 > col1) if none. It bounds the disc's projection (disc_bounds), widened by
// 0.01 px plus 0.1 % of its size, far above the float32 error of the bounds, so that rounding never
// loses a pixel the per-pixel test would accept (a whole pixel of margin would quadruple the pixels
// tested for a 1-px disc). Two cases take the disc's bounding sphere instead:
// * a disc that may take the grazing-ray rule of splat_depth_at: that rule accepts rays nearly
//   parallel to the disc's plane that pass within r of its centre, which need not be inside the
//   disc's projection. Rays through the sphere's box make an angle of at most asin(r / |c|) with
//   the centre's direction, so only discs within that angle (+ GRAZING_COS) of edge-on can;
// * a disc reaching the camera plane has no bounded projection: its bounding sphere's box is
//   bounded only on the sides of the image that plane_crossing_bounds can rule out.
ivec4 splat_pixel_box(Splat s) {
    if (s.pc.z + s.r <= 0.0 || s.r <= 0.0) return ivec4(1, 1, 0, 0);  // behind the camera / no disc
    vec2 bu, bv, margin;
    float dist = length(s.pc);
    bool grazing = abs(dot(s.nc, s.pc)) <= dist * (asin(min(s.r / dist, 1.0)) + 2.0 * GRAZING_COS);
    float depth_extent = s.r * sqrt(max(1.0 - s.nc.z * s.nc.z, 0.0));  // the disc's half-extent in z
    if (s.pc.z <= (grazing ? s.r : depth_extent) * 1.0001 + 1e-6) {
        bu = plane_crossing_bounds(s.pc.x, s.pc.z, s.r, u_K.x, u_K.z);
        bv = plane_crossing_bounds(s.pc.y, s.pc.z, s.r, u_K.y, u_K.w);
        margin = vec2(0.0);  // already widened
    } else {
        if (grazing) {
            bu = sphere_bounds(s.pc.x, s.pc.z, s.r, u_K.x, u_K.z);
            bv = sphere_bounds(s.pc.y, s.pc.z, s.r, u_K.y, u_K.w);
        } else {
            bu = disc_bounds(s.pc.x, s.pc.z, s.nc.x, s.nc.z, s.nc.y, s.r, u_K.x, u_K.z);
            bv = disc_bounds(s.pc.y, s.pc.z, s.nc.y, s.nc.z, s.nc.x, s.r, u_K.y, u_K.w);
        }
        margin = 0.01 + 1e-3 * vec2(bu.y - bu.x, bv.y - bv.x);
    }
    // clamp in float first: an almost-grazing disc can project to beyond the int range
    vec4 lim = vec4(-2.0, -2.0, vec2(u_size) + 2.0);
    vec4 b = vec4(bu.x, bv.x, bu.y, bv.y) + vec4(-margin, margin);
    b = clamp(b, lim.xyxy, lim.zwzw);
    ivec4 box = ivec4(ceil(b.xy - 0.5), floor(b.zw - 0.5));
    return ivec4(max(box.xy, ivec2(0)), min(box.zw, u_size - 1));
}

// The ray of the pixel centred at uv (camera space, z = 1).
vec3 splat_ray(vec2 uv) {
    return vec3((uv.x - u_K.z) / u_K.x, (uv.y - u_K.w) / u_K.y, 1.0);
}

// Camera z where the pixel ray d = splat_ray(uv), of length dlen = length(d), meets the disc; 0.0
// if it misses. A pass that tests many discs at one pixel computes d and dlen once. The tile
// raster's hit_bits (dmrt_tiles_raster.glsl) is this test written out: keep the two equal (the
// tiles tests compare its layers with compute peeling's, bit for bit).
float splat_depth_ray(Splat s, vec3 d, float dlen) {
    float nd = dot(s.nc, d);
    if (abs(nd) > GRAZING_COS * dlen) {
        float z = dot(s.nc, s.pc) / nd;
        vec3 q = z * d - s.pc;
        return (z > 0.0 && dot(q, q) <= s.r * s.r) ? z : 0.0;
    }
    vec3 dh = normalize(d);
    vec3 q = dot(s.pc, dh) * dh - s.pc;
    return (s.pc.z > 0.0 && dot(q, q) <= s.r * s.r) ? s.pc.z : 0.0;
}

// Camera z where the ray of the pixel centred at uv meets the disc; 0.0 if it misses.
float splat_depth_at(Splat s, vec2 uv) {
    vec3 d = splat_ray(uv);
    return splat_depth_ray(s, d, length(d));
}
