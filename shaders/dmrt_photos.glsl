// The photographs' cameras and depth maps D_j on the GPU. Included; no #version.
// World coordinates are scene-origin-relative metres, as everywhere on the GPU.

struct Photo {
    vec4 r0, r1, r2;  // rows of [R | t]: world -> photo camera (COLMAP/OpenCV axes)
    vec4 k;           // fx, fy, cx, cy in texels of the photo's depth map
    vec4 size;        // depth-map width, height; low-resolution image width, height (pixels)
    vec4 full;        // full-resolution image width, height; unused, unused
};

layout(std430, binding = B_PHOTOS) readonly buffer Photos { Photo photos[]; };

// The depth maps, one layer per photo (R32F camera z, 0 = empty; row 0 = the photo's top row);
// a map smaller than the array only fills its top-left corner: lookups use texelFetch.
uniform sampler2DArray u_depthmaps;

// Layer = photo index, unless the scene has more photos than the arrays hold (dmrt/runtime/maps.py):
// then MAP_SLOTS maps a photo to its layer, and a photo whose map is not resident is flagged for
// the renderer, which loads it and renders the frame again. A resident map that is read is flagged
// as used, so that the cache keeps the maps a frame reads (not only those of its final labels:
// the search also reads the deeper layers' and the label check's) and evicts others first.
#ifndef MAP_SLOTS
#define MAP_SLOTS 0
#endif
#ifndef MAP_FLAGS  // 0: a missing map only reads as no surface, nothing flagged (a pass that tests every photo)
#define MAP_FLAGS 1
#endif
#if MAP_SLOTS
layout(std430, binding = B_MAP_SLOTS) readonly buffer MapSlots { int map_slots[]; };
// [0]: any map missing; [1 + l]: MAP_MISSING or MAP_USED (within a frame a photo is either resident
// or not, so every write to a word stores the same value: plain stores, no atomics)
layout(std430, binding = B_MAP_MISSING) buffer MapFlags { uint map_flags[]; };
const uint MAP_MISSING = 1u;
const uint MAP_USED = 2u;

// The layer of photo l's map and low-resolution copy; -1 (and l flagged) when not resident.
int map_layer(int l) {
    int s = map_slots[l];
    if (MAP_FLAGS != 0) {
        if (s < 0) {
            map_flags[0] = 1u;
            map_flags[1 + l] = MAP_MISSING;
        } else if (map_flags[1 + l] == 0u) {  // a read (cached) spares most of the stores
            map_flags[1 + l] = MAP_USED;
        }
    }
    return s;
}
#else
int map_layer(int l) { return l; }
#endif

vec3 to_photo(Photo ph, vec3 q) {
    return vec3(dot(ph.r0.xyz, q) + ph.r0.w, dot(ph.r1.xyz, q) + ph.r1.w, dot(ph.r2.xyz, q) + ph.r2.w);
}

// photo camera -> world direction (R^T v)
vec3 photo_dir_to_world(Photo ph, vec3 v) {
    return v.x * ph.r0.xyz + v.y * ph.r1.xyz + v.z * ph.r2.xyz;
}

// Depth-map position (texels, corner origin) of a photo-camera point with pc.z > 0.
vec2 photo_uv(Photo ph, vec3 pc) {
    return ph.k.xy * pc.xy / pc.z + ph.k.zw;
}

// The depths of texels (i0, i0 + (1,0), i0 + (0,1), i0 + (1,1)) of map l; false when the quad is not
// wholly inside the map. One textureGather at the corner the four texels share (its texel
// coordinate i0 + 1 - 0.5 lies half a texel from any rounding boundary), in place of four
// texelFetch: the same values, a quarter of the texture instructions. Gather returns (01, 11, 10, 00).
bool fetch_quad(int l, vec2 size, ivec2 i0, out vec4 d) {
    d = vec4(0.0);
    if (any(lessThan(i0, ivec2(0))) || any(greaterThanEqual(i0 + 1, ivec2(size)))) return false;
    int layer = map_layer(l);
#if MAP_SLOTS
    if (layer < 0) return false;
#endif
    vec2 corner = vec2(i0 + 1) / vec2(textureSize(u_depthmaps, 0).xy);
    d = textureGather(u_depthmaps, vec3(corner, float(layer))).wzxy;
    return true;
}

// Positions within this many texels of a row or column of texel centres may take the quad on its
// other side (see depth_quad).
const float SNAP = 0.01;

// Depth span of a quad: inf when a texel is empty.
float quad_span(vec4 d) {
    if (any(lessThanEqual(d, vec4(0.0)))) return 1e30;
    return max(max(d.x, d.y), max(d.z, d.w)) - min(min(d.x, d.y), min(d.z, d.w));
}

// depth_quad's other quads for a position within SNAP of a row (s.y != 0) and/or a column (s.x):
// k = 0 across the column, 1 across the row, 2 across both. A function of k, not a constant array
// indexed by the loop counter: the NVIDIA compiler put such an array in local memory (lmem), in
// each of the seven places the raytracing program inlines depth_quad.
ivec2 snap_try(ivec2 s, int k) {
    return k == 0 ? ivec2(s.x, 0) : (k == 1 ? ivec2(0, s.y) : s);
}

// The four texels nearest to depth-map position uv: i0 = the top-left one's (column, row), f = the
// bilinear weights, d = depths of (i0, i0 + (1,0), i0 + (0,1), i0 + (1,1)). False when the quad is
// not wholly inside the map. A position on a row or column of texel centres (within SNAP) lies in
// two (or four) quads, all giving it the same surface depth: the one floor() picks is kept when
// its texels are present and span at most max_span metres, else the first other one that does
// (else the first other complete one). At a photo's own camera every pixel ray passes through a
// texel centre, and float32 rounding would otherwise pick, along every depth edge of the map, the
// quad on the empty or discontinuous side half of the time. `size`: the map's width and height
// (Photo.size.xy).
bool depth_quad(int l, vec2 size, vec2 uv, float max_span, out ivec2 i0, out vec2 f, out vec4 d) {
    vec2 x = clamp(uv, vec2(-4.0), size + 4.0) - 0.5;  // clamp: keep int conversion defined
    vec2 fl = floor(x);
    i0 = ivec2(fl);
    f = x - fl;
    bool inside = fetch_quad(l, size, i0, d);
    float span = inside ? quad_span(d) : 1e30;
    if (span <= max_span) return true;
    ivec2 s = ivec2(f.x < SNAP ? -1 : (f.x > 1.0 - SNAP ? 1 : 0), f.y < SNAP ? -1 : (f.y > 1.0 - SNAP ? 1 : 0));
    if (s == ivec2(0)) return inside;
    // The quad kept is fetched again at the end rather than held through the tries: on this rare
    // path one more fetch costs less than the registers of two quads held live, which every
    // lookup of the raytracing program would pay (its occupancy is bound by them).
    int best = -1;
    for (int k = 0; k < 3; ++k) {
        vec4 d2;
        ivec2 o = snap_try(s, k);
        if (o == ivec2(0) || !fetch_quad(l, size, i0 + o, d2)) continue;
        float span2 = quad_span(d2);
        if (span2 < span && (span2 <= max_span || span >= 1e30)) {
            best = k;
            span = span2;
            if (span2 <= max_span) break;
        }
    }
    if (best < 0) return fetch_quad(l, size, i0, d);  // the first quad (inside as before)
    ivec2 o = snap_try(s, best);
    i0 += o;
    f = clamp(f - vec2(o), 0.0, 1.0);
    return fetch_quad(l, size, i0, d);
}

// Photo-camera point of depth-map texel (col, row) holding depth z.
vec3 unproject_texel(Photo ph, ivec2 t, float z) {
    vec2 uv = vec2(t) + 0.5;
    return z * vec3((uv - ph.k.zw) / ph.k.xy, 1.0);
}

// Depth of the surface of a quad from depth_quad (f, d): the texel centres (00, 10, 01, 11) split
// along the 10-01 diagonal into T0 = (00, 10, 01) and T1 = (10, 11, 01); inside the triangle holding
// f, inverse depth is interpolated linearly in image coordinates, which is exact for a plane (1/z is
// affine in image coordinates on a plane). ok = false where that triangle has an empty texel.
float triangle_depth(vec2 f, vec4 d, out bool ok) {
    float inv;
    ok = false;
    if (f.x + f.y <= 1.0) {  // T0
        if (d.x == 0.0 || d.y == 0.0 || d.z == 0.0) return 0.0;
        inv = 1.0 / d.x + f.x * (1.0 / d.y - 1.0 / d.x) + f.y * (1.0 / d.z - 1.0 / d.x);
    } else {                 // T1
        if (d.y == 0.0 || d.w == 0.0 || d.z == 0.0) return 0.0;
        inv = 1.0 / d.w + (1.0 - f.y) * (1.0 / d.y - 1.0 / d.w) + (1.0 - f.x) * (1.0 / d.z - 1.0 / d.w);
    }
    ok = true;
    return 1.0 / inv;
}

// Depth of D_l's surface at depth-map position uv (triangle_depth of the quad around it). ok =
// false outside the map or where the triangle has an empty texel.
float surface_depth(int l, Photo ph, vec2 uv, out bool ok) {
    ivec2 i0;
    vec2 f;
    vec4 d;
    ok = false;
    if (!depth_quad(l, ph.size.xy, uv, 1e29, i0, f, d)) return 0.0;
    return triangle_depth(f, d, ok);
}
