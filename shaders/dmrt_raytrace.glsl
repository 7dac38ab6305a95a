// DMRT raytracing pass (paper Section 5.1.2): one thread per pixel. For each label layer in turn
// (front to back) the pixel's ray is intersected with the depth map D_l of the layer's label l,
// starting at the layer's splat depth; the first valid intersection wins, none = background.
//
// Surface of D_l (paper: "the four texels ... yielding two triangles in 3D"): surface_depth() of
// dmrt_photos.glsl - the quad of texel centres around a position split into two triangles, inverse
// depth interpolated linearly inside each, so each triangle is exactly the 3D triangle through its
// three unprojected texels and planar regions are reproduced exactly. Empty texels: no surface.
//
// Iterative search (paper Eq. 1, Fig. 5). With q on the ray, its photo-camera coordinates
// p = R_l q + t_l and D = the surface depth at p's projection, the surface point on the line from
// C_l through q is p * D / p.z, so the signed distance from q to the surface along that line is
//         h(q) = (D - p.z) * |p| / p.z          (> 0: q lies between C_l and the surface)
// and the next point is q' = q + h(q) * r_p, r_p the unit ray direction (for a plane seen from the
// same side by both cameras this converges, or overshoots into an enclosing pair). The search stops
// when two consecutive points enclose the surface (h changes sign) or when |h| <= 1e-5 of the camera
// z (landed on the surface, float32 precision); it fails when a point leaves the depth map, falls
// on empty texels, goes behind the camera, or after u_max_steps steps. An enclosed interval is
// refined by u_binary_steps bisection steps and a final secant step (the paper), or with ILLINOIS by
// the Illinois variant of regula falsi: each step takes the secant point of the interval, halving
// the stale end's value when the same end is kept twice, and stops when |h| <= 1e-6 of the camera z
// (float32 resolves ~1e-7) - a few fetches where bisection always takes u_binary_steps; at most
// u_binary_steps steps either way.
//
// Discontinuity test on the four texels around the hit's projection (triangles T0 = (00,10,01),
// T1 = (10,11,01)), as chosen by QUAD_TEST:
//   1 (paper): invalid if any two vertices of either triangle differ in depth by more than
//     u_threshold (or a texel is empty);
//   0: only the triangle that contains the hit is tested, so that a hit on a continuous
//     triangle next to a depth edge counts (halves the band lost along each discontinuity).
// An invalid hit sends the search to the next layer. The pixel's normal is the average of the
// unit normals of the triangles that pass the test (the paper: of both triangles).
//
// Hole filling walks a list of the holes the pixel pass leaves (HoleList), a workgroup per hole and
// a thread per neighbour (see FILL below).
//
// RAYTRACE 0 (ablation, the paper's Fig. 8a "coarse splats"): no search; the first layer's splat is
// the surface (its depth and label; the normal faces the camera).
// STATISTICS 1: every iterative step's length along the ray (metres) is accumulated per layer and
// step index into the StepStats buffer (the paper's Figs. 9 and 10).
#include "splat_depth_common.glsl"
#define NORMALS_BUFFER
#include "dmrt_frame.glsl"
#include "dmrt_photos.glsl"

#if defined COMPUTE_SHADER

#ifndef FILL
#define FILL 0
#endif

// The pixel pass: 8 x 8 pixels a workgroup; the fill pass: one hole a workgroup, its LIST_THREADS
// neighbours searched side by side
#if FILL
#define LIST_THREADS 8
layout(local_size_x = LIST_THREADS) in;
#else
#define LIST_THREADS 1
layout(local_size_x = 8, local_size_y = 8) in;
#endif

layout(std430, binding = B_LAYER_DEPTH) readonly buffer LayerDepth { uint layer_depth[]; };
layout(std430, binding = B_LAYER_LABEL) readonly buffer LayerLabel { int layer_label[]; };

uniform int u_layers;
uniform int u_max_steps;
uniform int u_binary_steps;
uniform float u_threshold;  // metres

#ifndef SECANT
#define SECANT 0
#endif

#ifndef QUAD_TEST
#define QUAD_TEST 1
#endif

#ifndef RAYTRACE
#define RAYTRACE 1
#endif

#ifndef MAX_RESUMES
#define MAX_RESUMES 2
#endif

#ifndef STATISTICS
#define STATISTICS 0
#endif

#ifndef ILLINOIS
#define ILLINOIS 0
#endif

#if FILL
// hole filling searches no layer: nothing of it is recorded
#undef STATISTICS
#define STATISTICS 0
#endif

#if STATISTICS
// STEP_BINS, STAT_LAYERS: dmrt/gl/abi.py (RenderConfig refuses statistics with more layers)
// per (layer, step index) four words: count, sum of lengths in 10 um units (low word, high word), 0;
// step indices >= STEP_BINS - 1 share the last bin
layout(std430, binding = B_STEP_STATS) buffer StepStats { uint step_stats[]; };

// Each workgroup sums its steps in shared memory and adds the sums to StepStats once, at the end,
// instead of 2-3 global atomics per step on these few hundred words (30M steps a frame with splat
// radii x2.5 on the paper preset, where an H200's GL context stopped during this pass: the
// contention is the suspect, not yet confirmed on a GPU).
shared uint s_count[STAT_LAYERS * STEP_BINS];
shared uint s_sum_lo[STAT_LAYERS * STEP_BINS];
shared uint s_sum_hi[STAT_LAYERS * STEP_BINS];

void record_step(int layer, int i, float metres) {
    uint k = uint(layer * STEP_BINS + min(i, STEP_BINS - 1));
    atomicAdd(s_count[k], 1u);
    uint v = uint(clamp(metres, 0.0, 40000.0) * 1e5);
    uint old = atomicAdd(s_sum_lo[k], v);
    if (old + v < old) atomicAdd(s_sum_hi[k], 1u);  // carry into the high word
}

void clear_steps() {
    for (uint k = gl_LocalInvocationIndex; k < uint(STAT_LAYERS * STEP_BINS); k += gl_WorkGroupSize.x * gl_WorkGroupSize.y) {
        s_count[k] = 0u;
        s_sum_lo[k] = 0u;
        s_sum_hi[k] = 0u;
    }
    memoryBarrierShared();
    barrier();
}

void flush_steps() {
    memoryBarrierShared();
    barrier();
    for (uint k = gl_LocalInvocationIndex; k < uint(u_layers * STEP_BINS); k += gl_WorkGroupSize.x * gl_WorkGroupSize.y) {
        if (s_count[k] == 0u) continue;
        uint base = 4u * k;
        atomicAdd(step_stats[base], s_count[k]);
        uint old = atomicAdd(step_stats[base + 1u], s_sum_lo[k]);
        uint carry = s_sum_hi[k] + ((old + s_sum_lo[k] < old) ? 1u : 0u);
        if (carry != 0u) atomicAdd(step_stats[base + 2u], carry);
    }
}
#endif

const float CONVERGED = 1e-5;  // |h| / camera z below which the search has landed on the surface

// h(q) of the header; ok = false where it is undefined.
float signed_distance(int l, Photo ph, vec3 q, out bool ok) {
    vec3 pc = to_photo(ph, q);
    ok = false;
    if (pc.z <= 1e-6) return 0.0;
    float depth = surface_depth(l, ph, photo_uv(ph, pc), ok);
    return ok ? (depth - pc.z) * length(pc) / pc.z : 0.0;
}

// The hit at s_hit on D_l passes the discontinuity test on the four texels around it: true, with
// the unit world normal n facing the render camera when u_normals is set (else n = 0).
bool valid_hit(int l, Photo ph, vec3 C, vec3 dir, float dlen, float s_hit, out vec3 n) {
    n = vec3(0.0);
    vec3 pc = to_photo(ph, C + s_hit * dir);
    if (pc.z <= 1e-6) return false;
    ivec2 i0;
    vec2 f2;
    vec4 d;
    if (!depth_quad(l, ph, photo_uv(ph, pc), u_threshold, i0, f2, d)) return false;
    float t = u_threshold;
    // each triangle: all three texels present and no two depths further apart than t
    bool ok0 = d.x > 0.0 && d.y > 0.0 && d.z > 0.0 &&
               abs(d.x - d.y) <= t && abs(d.x - d.z) <= t && abs(d.y - d.z) <= t;
    bool ok1 = d.y > 0.0 && d.w > 0.0 && d.z > 0.0 &&
               abs(d.y - d.w) <= t && abs(d.w - d.z) <= t && abs(d.y - d.z) <= t;
#if QUAD_TEST
    if (!(ok0 && ok1)) return false;
#else
    if (!(f2.x + f2.y <= 1.0 ? ok0 : ok1)) return false;
#endif
    if (NORMALS == 0 || u_normals == 0) return true;  // a frame not read back keeps no normal (write_normal)
    vec3 p00 = unproject_texel(ph, i0, d.x);
    vec3 p10 = unproject_texel(ph, i0 + ivec2(1, 0), d.y);
    vec3 p01 = unproject_texel(ph, i0 + ivec2(0, 1), d.z);
    vec3 p11 = unproject_texel(ph, i0 + ivec2(1, 1), d.w);
    vec3 n1 = cross(p10 - p00, p01 - p00);
    vec3 n2 = cross(p11 - p10, p01 - p10);
    vec3 nc = (ok0 ? n1 / max(length(n1), 1e-30) : vec3(0.0)) + (ok1 ? n2 / max(length(n2), 1e-30) : vec3(0.0));
    n = photo_dir_to_world(ph, nc);
    float len = length(n);
    n = len > 0.0 ? n / len : -dir / dlen;
    if (dot(n, dir) > 0.0) n = -n;
    return true;
}

// Refinement of the enclosing interval [sa, sb] (f changes sign): true with the intersection s_hit;
// false where a probe falls on empty texels (see the header for the two methods).
bool refine(int l, Photo ph, vec3 C, vec3 dir, float sa, float fa, float sb, float fb, out float s_hit) {
    bool ok;
    s_hit = sa;
    if (sa == sb) return true;
#if ILLINOIS
    int side = 0;
    for (int b = 0; b < u_binary_steps && fa != fb; ++b) {
        float sm = (sa * fb - sb * fa) / (fb - fa);
        float fm = signed_distance(l, ph, C + sm * dir, ok);
        if (!ok) return false;
        if (abs(fm) <= 1e-6 * sm) { s_hit = sm; return true; }
        if ((fm > 0.0) == (fb > 0.0)) {
            sb = sm; fb = fm;
            if (side == -1) fa *= 0.5;
            side = -1;
        } else {
            sa = sm; fa = fm;
            if (side == 1) fb *= 0.5;
            side = 1;
        }
    }
#else
    for (int b = 0; b < u_binary_steps; ++b) {
        float sm = 0.5 * (sa + sb);
        float fm = signed_distance(l, ph, C + sm * dir, ok);
        if (!ok) return false;
        if ((fm > 0.0) == (fa > 0.0)) { sa = sm; fa = fm; } else { sb = sm; fb = fm; }
    }
#endif
    s_hit = (fa == fb) ? 0.5 * (sa + sb) : sa + (sb - sa) * fa / (fa - fb);
    return true;
}

// Search D_l along the ray C + s * dir (s = camera z) from s0. True with s_hit and the unit world
// normal n on a valid intersection. The paper's search ends at the first enclosed interval; with
// SECANT an interval that fails (a sign change across a depth edge of D_l, not a surface, or a
// hit that fails the discontinuity test) resumes the search beyond it, at most MAX_RESUMES times
// (a pixel that no depth-map surface covers would otherwise spend every step of the budget).
bool trace(int layer, int l, vec3 C, vec3 dir, float dlen, float s0, inout int iters, out float s_hit,
           out vec3 n) {
    s_hit = 0.0;
    n = vec3(0.0);
    bool ok;
    // read once: the search's steps all project into D_l (96 bytes a step otherwise, which the
    // compiler does not hoist out of the loop)
    Photo ph = photos[l];
    float s = s0;
    float f = signed_distance(l, ph, C + s * dir, ok);
    if (!ok) return false;
    float sp = s, fp = f;
    bool restart = true;  // the next step is the paper's (no previous sample for a secant)
    int resumes = 0;
    for (int i = 0; i < u_max_steps; ++i) {
        iters++;
        if (abs(f) <= CONVERGED * s) {  // on the surface: no interval to refine
            s_hit = s;
            if (valid_hit(l, ph, C, dir, dlen, s_hit, n)) return true;
#if SECANT
            if (++resumes > MAX_RESUMES) return false;
            // nudge past the edge point: a texel beyond it along the ray
            float sn = s * (1.0 + 1e-3);
            f = signed_distance(l, ph, C + sn * dir, ok);
            if (!ok) return false;
            s = sn;
            restart = true;
            continue;
#else
            return false;
#endif
        }
        float step = f / dlen;  // the paper's step: h metres along the unit ray
#if SECANT
        // after the first step, the secant through the last two samples: h is measured along the
        // line to the photo's centre, which converges slowly (or jumps off the surface) when that
        // line and the pixel ray differ by a large angle
        if (!restart && fp != f) step = -f * (s - sp) / (f - fp);
#endif
        restart = false;
        float sn = s + step;
        if (sn <= 0.0) return false;
        float fn = signed_distance(l, ph, C + sn * dir, ok);
#if SECANT
        // a step that lands on an empty or outside texel is halved (a few times) before giving up
        for (int k = 0; k < 4 && !ok; ++k) {
            step *= 0.5;
            sn = s + step;
            fn = signed_distance(l, ph, C + sn * dir, ok);
        }
#endif
#if STATISTICS
        if (layer >= 0) record_step(layer, i, abs(sn - s) * dlen);
#endif
        if (!ok) return false;
        if ((fn > 0.0) != (f > 0.0)) {  // enclosed
            if (refine(l, ph, C, dir, s, f, sn, fn, s_hit) && valid_hit(l, ph, C, dir, dlen, s_hit, n)) return true;
#if SECANT
            if (++resumes > MAX_RESUMES) return false;
            restart = true;  // resume beyond the interval
#else
            return false;
#endif
        }
        sp = s; fp = f;
        s = sn;
        f = fn;
    }
    return false;
}

// Work lists (dmrt/runtime/renderer.py): cmd is the dispatch-indirect command of the pass that
// walks the list, one workgroup per item: cmd.x = min(items, u_max_groups), cmd.w = items; a
// workgroup takes items gl_WorkGroupID.x, + gl_NumWorkGroups.x, ...
struct ListHeader { uint x, y, z, n; };
// Pixels that a splat covers but no layer gave a surface (FILL pass u_pass walks HoleList, appends
// the pixels it leaves to NextHoles)
layout(std430, binding = B_HOLES) buffer HoleList { ListHeader hole_cmd; uint hole_items[]; };
layout(std430, binding = B_HOLES_NEXT) buffer NextHoles { ListHeader next_cmd; uint next_items[]; };
uniform uint u_max_groups;  // GL_MAX_COMPUTE_WORK_GROUP_COUNT[0]
uniform int u_fill;         // 1: list the holes left for a fill pass (fill_passes > 0; the last fill pass: 0)

void push_hole(uint pix) {
    uint i = atomicAdd(next_cmd.n, 1u);
    next_items[i] = pix;
    if (i < u_max_groups) atomicMax(next_cmd.x, i + 1u);
}

// One hole per workgroup: the thread that finds the first success (smallest index j) writes the
// pixel; iters counts the steps of the neighbours up to that one, as a loop over them in order would.
const uint NONE = uint(LIST_THREADS);  // s_best when no candidate succeeded
shared uint s_best;
shared int s_iters[LIST_THREADS];

int iters_through(uint best, int iters) {
    for (uint j = 0u; j < uint(LIST_THREADS) && j <= best; ++j) iters += s_iters[j];
    return iters;
}

#if FILL
// Hole filling (an addition to the paper; RenderConfig.fill_passes): a pixel that a splat covers
// but whose layers gave no surface searches the depth maps of its 8 neighbours' hits, starting
// at their depths, and takes a hit within u_threshold of that neighbour's depth (the same
// surface: a hit further away is another surface the neighbour's photo sees, often wrongly): the
// first neighbour in row order that gives one. Pass u_pass reads only hits found before it (layer
// < u_layers + u_pass), so the result does not depend on the order in which threads run; a pixel
// filled here gets the layer index u_layers + u_pass. One workgroup per hole, one thread per
// neighbour: the pass takes as long as one neighbour's search, not eight in a row.
uniform int u_pass;

void main() {
    uint lid = gl_LocalInvocationIndex;
    mat3 Rt = transpose(u_R);
    vec3 C = -(Rt * u_t);
    for (uint e = gl_WorkGroupID.x; e < hole_cmd.n; e += gl_NumWorkGroups.x) {
        uint pix = hole_items[e];
        ivec2 p = ivec2(int(pix % uint(u_size.x)), int(pix / uint(u_size.x)));
        vec3 dir = Rt * camera_ray(vec2(p) + 0.5);
        float dlen = length(dir);
        if (lid == 0u) s_best = NONE;
        memoryBarrierShared();
        barrier();
        int k = int(lid < 4u ? lid : lid + 1u);  // the 3 x 3 neighbourhood in row order, centre skipped
        ivec2 q = p + ivec2(k % 3 - 1, k / 3 - 1);
        int iters = 0;
        float s_hit = 0.0;
        vec3 n = vec3(0.0);
        Hit nb = Hit(0.0, -1, -1, 0u);
        bool found = false;
        if (all(greaterThanEqual(q, ivec2(0))) && all(lessThan(q, u_size))) {
            nb = hits[uint(q.y * u_size.x + q.x)];
            if (hit_layer(nb) >= 0 && hit_layer(nb) < u_layers + u_pass && nb.depth > 0.0) {
                // only the neighbour's own surface: within the discontinuity threshold of its depth
                found = trace(-1, nb.label, C, dir, dlen, nb.depth, iters, s_hit, n) &&
                        abs(s_hit - nb.depth) <= u_threshold;
            }
        }
        s_iters[lid] = iters;
        if (found) atomicMin(s_best, lid);
        memoryBarrierShared();
        barrier();
        uint best = s_best;
        if (best == lid) {
            hits[pix] = Hit(s_hit, nb.label, -1, layer_iters(u_layers + u_pass, iters_through(best, hit_iters(hits[pix]))));
            write_normal(pix, n);
        } else if (best == NONE && lid == 0u) {
            hits[pix].layer_iters = layer_iters(-1, iters_through(best, hit_iters(hits[pix])));
            if (u_fill != 0) push_hole(pix);
        }
        memoryBarrierShared();
        barrier();  // s_best and s_iters are reset for the next item
    }
}
#else
void raytrace_pixel() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    uint npix = uint(u_size.x * u_size.y);
    uint pix = uint(p.y * u_size.x + p.x);

    mat3 Rt = transpose(u_R);  // camera -> world
    vec3 C = -(Rt * u_t);
    vec3 dir = Rt * camera_ray(vec2(p) + 0.5);
    float dlen = length(dir);

    Hit hit = Hit(0.0, -1, -1, layer_iters(-1, 0));
    vec3 n = vec3(0.0);
#if !RAYTRACE
    uint bits0 = layer_depth[pix];
    if (bits0 != EMPTY_BITS) {
        n = -dir / dlen;
        hit = Hit(uintBitsToFloat(bits0), layer_label[pix], -1, layer_iters(0, 0));
    }
    hits[pix] = hit;
    write_normal(pix, n);
    return;
#endif
    int iters = 0, found_layer = -1;
    for (int layer = 0; layer < u_layers; ++layer) {
        uint bits = layer_depth[uint(layer) * npix + pix];
        if (bits == EMPTY_BITS) break;  // peeling: every later layer is empty too
        int l = layer_label[uint(layer) * npix + pix];
        float s_hit;
        vec3 n_hit;
        if (trace(layer, l, C, dir, dlen, uintBitsToFloat(bits), iters, s_hit, n_hit)) {
            hit.depth = s_hit;
            hit.label = l;
            found_layer = layer;
            n = n_hit;
            break;
        }
    }
    hit.layer_iters = layer_iters(found_layer, iters);
    hits[pix] = hit;
    write_normal(pix, n);
    if (u_fill != 0 && hit.depth <= 0.0 && layer_depth[pix] != EMPTY_BITS) push_hole(pix);
}

void main() {
#if STATISTICS
    clear_steps();
#endif
    raytrace_pixel();
#if STATISTICS
    flush_steps();
#endif
}
#endif

#endif
