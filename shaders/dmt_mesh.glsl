// DMT runtime (Arikan et al. 2014): every depth map drawn as a grid mesh of triangles, generated
// from gl_VertexID and the depth-map texture (no vertex buffers). One multi-draw-indirect command
// per depth map (shaders/dmt_cull.glsl writes them, count 0 = culled); map m's vertices are the
// range [slot * u_verts_per_map, ...) with slot = m - u_map_base, 6 per quad of texels:
//   quad (c, r) = texels (c, r) .. (c + 1, r + 1); T0 = (00, 10, 01), T1 = (10, 11, 01)
// (the split of DMRT's surface_depth, and of baselines/dmt/geometry.py's grid_triangles).
// Each vertex fetches its triangle's three texels: a triangle with an empty texel or whose depths
// span more than u_threshold (a depth discontinuity) is dropped - its three vertices all go to
// the same point outside the clip volume.
//
// PASS 1: nearest surface. z-buffered; writes the camera z (1 / gl_FragCoord.w: clip w = camera z)
//   of the nearest fragment to an R32F target.
// PASS 2: stitching. Fragments farther than u_epsilon behind pass 1's z are discarded (a different
//   surface); among the rest - the same surface, seen by several depth maps - the depth test keeps
//   the smallest quality key, the log2 texel footprint of the fragment's depth map there,
//   z_j / (f_j |cos theta_j|) metres per texel (the better-resolved depth map wins). Writes camera z,
//   the triangle's world normal (facing the viewer), the depth map and the label of that map's
//   texel holding the fragment's surface point.
#include "dmrt_photos.glsl"

#ifndef PASS
#define PASS 1
#endif

#if defined VERTEX_SHADER

uniform mat4 u_vp;           // scene-origin-relative world -> clip (Camera.gl_view_projection)
uniform vec3 u_eye;          // render camera centre, origin-relative metres
uniform int u_map_base;      // depth map of vertex range 0 of this draw
uniform int u_verts_per_map; // vertices reserved per depth map: 6 (W - 1)(H - 1) of the largest map
uniform float u_threshold;   // discontinuity threshold, metres
uniform float u_min_cos;     // clamp of |cos theta| in the quality key (grazing views)

invariant gl_Position;
flat out int v_map;
out vec3 v_pos;              // the surface point, origin-relative world metres
flat out vec3 v_normal;      // world normal of the triangle, facing the render camera
out float v_key;             // log2 texel footprint, metres

const ivec2 CORNERS[6] = ivec2[6](ivec2(0, 0), ivec2(1, 0), ivec2(0, 1), ivec2(1, 0), ivec2(1, 1), ivec2(0, 1));

vec3 texel_world(Photo ph, ivec2 t, float z) {
    vec3 pc = unproject_texel(ph, t, z);
    return photo_dir_to_world(ph, pc - vec3(ph.r0.w, ph.r1.w, ph.r2.w));  // R^T (pc - t)
}

void main() {
    int slot = gl_VertexID / u_verts_per_map;
    int local = gl_VertexID - slot * u_verts_per_map;
    int map = u_map_base + slot;
    Photo ph = photos[map];
    int w = int(ph.size.x);
    int quad = local / 6;
    int corner = local - quad * 6;
    int first = corner < 3 ? 0 : 3;
    ivec2 q0 = ivec2(quad % (w - 1), quad / (w - 1));
    ivec2 ta = q0 + CORNERS[first], tb = q0 + CORNERS[first + 1], tc = q0 + CORNERS[first + 2];
    float za = texelFetch(u_depthmaps, ivec3(ta, map), 0).r;
    float zb = texelFetch(u_depthmaps, ivec3(tb, map), 0).r;
    float zc = texelFetch(u_depthmaps, ivec3(tc, map), 0).r;
    bool ok = za > 0.0 && zb > 0.0 && zc > 0.0
              && max(za, max(zb, zc)) - min(za, min(zb, zc)) <= u_threshold;
    v_map = map;
    v_pos = vec3(0.0);
    v_normal = vec3(0.0);
    v_key = 0.0;
    if (!ok) {
        gl_Position = vec4(2.0, 2.0, 2.0, 1.0);  // all three vertices here: outside, clipped
        return;
    }
    vec3 a = texel_world(ph, ta, za), b = texel_world(ph, tb, zb), c = texel_world(ph, tc, zc);
    vec3 n = normalize(cross(b - a, c - a));
    if (dot(n, a - u_eye) > 0.0) n = -n;
    int own = corner - first;
    vec3 p = own == 0 ? a : (own == 1 ? b : c);
    float z = own == 0 ? za : (own == 1 ? zb : zc);
    gl_Position = u_vp * vec4(p, 1.0);
    v_pos = p;
    v_normal = n;
    vec3 eye_j = -photo_dir_to_world(ph, vec3(ph.r0.w, ph.r1.w, ph.r2.w));  // C_j = -R^T t
    float cos_j = abs(dot(n, normalize(eye_j - p)));
    v_key = log2(z / (sqrt(ph.k.x * ph.k.y) * max(cos_j, u_min_cos)));
}

#elif defined FRAGMENT_SHADER

flat in int v_map;
in vec3 v_pos;
flat in vec3 v_normal;
in float v_key;

#if PASS == 1

layout(location = 0) out float f_z;

void main() {
    f_z = 1.0 / gl_FragCoord.w;
}

#else

uniform sampler2D u_front;         // pass 1: camera z of the nearest surface, 0 = none
uniform isampler2DArray u_labels;  // per-texel labels of every depth map, -1 = none
uniform float u_epsilon;           // stitching threshold, metres

layout(location = 0) out vec4 f_surface;  // camera z, world normal
layout(location = 1) out vec4 f_ids;      // depth map, label (exact small integers as floats)

void main() {
    float z = 1.0 / gl_FragCoord.w;
    float front = texelFetch(u_front, ivec2(gl_FragCoord.xy), 0).r;
    if (z > front + u_epsilon) discard;
    // the label of the map's texel that holds the point's projection (perspective-correct v_pos
    // is the exact point on the triangle)
    Photo ph = photos[v_map];
    vec2 uv = photo_uv(ph, to_photo(ph, v_pos));
    ivec2 t = clamp(ivec2(floor(uv)), ivec2(0), ivec2(ph.size.xy) - 1);
    int label = texelFetch(u_labels, ivec3(t, v_map), 0).r;
    f_surface = vec4(z, v_normal);
    f_ids = vec4(float(v_map), float(label), 0.0, 1.0);
    // key (log2 metres, about -12..5) into the depth range, below the clear value 1.0
    gl_FragDepth = clamp(0.5 + v_key / 64.0, 0.0, 0.999);
}

#endif
#endif
