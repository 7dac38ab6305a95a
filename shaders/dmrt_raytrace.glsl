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

// The search of one layer as a state machine that stops at every depth-map lookup: the pixel pass
// runs its lanes' searches side by side one lookup at a time (see raytrace_pixel), the fill pass
// one search to its end (trace). The state is per invocation, in globals:
float g_dlen;           // length of the ray's direction (camera_ray: camera z grows by 1 a unit)
int g_l;                // the label whose depth map is searched
// The ray in photo l's camera, pc(s) = g_o + s * g_v, its intrinsics and its depth map's size,
// set once a search (search_start): a lookup then costs three FMAs for the point, and the state
// holds 12 words of the photo instead of the 18 its rows, intrinsics and size take. (The search is
// bound by the warps an SM holds, which its registers decide: H200, 3840x2160, the search took
// 1.310 ms with the photo and the world ray in the state, 1.098 ms without; session 16.)
vec3 g_o, g_v;
vec4 g_fc;              // fx, fy, cx, cy (texels)
vec2 g_size;            // the depth map's width, height (texels)
int g_layer;            // the layer searched (-1: a fill search), for the statistics
int g_iters;            // search steps so far (the paper's c_total)
// the pending lookup: what it is for (PH_*) and where (s along the ray); once advance() returns
// HIT, g_q is the hit (its test was the last lookup)
int g_phase;
float g_q;
// the search: the current point and its h, the previous ones (the secant's), the step's point, the
// step (held in g_fn's word: a step's length is not read once its point's h is known)
float g_s, g_f, g_sp, g_fp, g_sn, g_fn;
#define g_step g_fn
bool g_restart;         // the next step is the paper's (no previous sample for a secant)
int g_i, g_k, g_resumes;  // step index, halvings of this step, resumptions
// the refinement: the interval [a, b] (s and h at each end), the Illinois side kept last, the step
// index. Its ends are held in the words of the current and the previous sample, which nothing
// reads from the enclosure to the refinement's end (a search that resumes goes on from
// (g_sn, g_fn) with the paper's step): 4 words of state fewer.
#define g_sa g_s
#define g_fa g_f
#define g_sb g_sp
#define g_fb g_fp
int g_side;
#define g_b g_k  // the halvings of a step end where the refinement starts
// the hit's unit world normal (NORMALS and u_normals; else 0)
vec3 g_n;

const int PH_START = 0;       // h at the layer's splat depth
const int PH_STEP = 1;        // h at the step's point (SECANT: retried at halved steps)
const int PH_NUDGE = 2;       // h just past a converged point that failed the test (SECANT)
const int PH_REFINE = 3;      // h at the refinement's point
const int PH_TEST_POINT = 4;  // the discontinuity test of a converged point
const int PH_TEST_HIT = 5;    // the discontinuity test of a refined hit
// what advance() returns
const int PENDING = 0, HIT = 1, MISS = 2;

int lookup_at(int phase, float q) {
    g_phase = phase;
    g_q = q;
    return PENDING;
}

// The discontinuity test of the quad (i0, f, d) of depth_quad at the hit: true, with g_n the unit
// world normal facing the render camera when u_normals is set.
bool quad_valid(ivec2 i0, vec2 f, vec4 d) {
    float t = u_threshold;
    // each triangle: all three texels present and no two depths further apart than t
    bool ok0 = d.x > 0.0 && d.y > 0.0 && d.z > 0.0 &&
               abs(d.x - d.y) <= t && abs(d.x - d.z) <= t && abs(d.y - d.z) <= t;
    bool ok1 = d.y > 0.0 && d.w > 0.0 && d.z > 0.0 &&
               abs(d.y - d.w) <= t && abs(d.w - d.z) <= t && abs(d.y - d.z) <= t;
#if QUAD_TEST
    if (!(ok0 && ok1)) return false;
#else
    if (!(f.x + f.y <= 1.0 ? ok0 : ok1)) return false;
#endif
    if (NORMALS == 0 || u_normals == 0) return true;  // a frame not read back keeps no normal (write_normal)
    Photo ph = photos[g_l];
    vec3 p00 = unproject_texel(ph, i0, d.x);
    vec3 p10 = unproject_texel(ph, i0 + ivec2(1, 0), d.y);
    vec3 p01 = unproject_texel(ph, i0 + ivec2(0, 1), d.z);
    vec3 p11 = unproject_texel(ph, i0 + ivec2(1, 1), d.w);
    vec3 n1 = cross(p10 - p00, p01 - p00);
    vec3 n2 = cross(p11 - p10, p01 - p10);
    vec3 nc = (ok0 ? n1 / max(length(n1), 1e-30) : vec3(0.0)) + (ok1 ? n2 / max(length(n2), 1e-30) : vec3(0.0));
    vec3 n = photo_dir_to_world(ph, nc);
    vec3 dir = photo_dir_to_world(ph, g_v);  // the ray's direction in the world
    float len = length(n);
    n = len > 0.0 ? n / len : -dir / length(dir);
    g_n = dot(n, dir) > 0.0 ? -n : n;
    return true;
}

// The pending lookup at s = g_q in D_l. The search's phases: h(q) of the header (ok = false where it
// is undefined). The test phases: ok = the point passes the discontinuity test (quad_valid). Both
// read the quad of texels around the point's projection: the lanes of a warp fetch side by side
// whatever phase each is in.
float lookup(out bool ok) {
    ok = false;
    vec3 pc = g_o + g_q * g_v;
    if (pc.z <= 1e-6) return 0.0;
    bool test = g_phase >= PH_TEST_POINT;
    ivec2 i0;
    vec2 f;
    vec4 d;
    vec2 uv = g_fc.xy * pc.xy / pc.z + g_fc.zw;  // photo_uv
    if (!depth_quad(g_l, g_size, uv, test ? u_threshold : 1e29, i0, f, d)) return 0.0;
    if (test) {
        ok = quad_valid(i0, f, d);
        return 0.0;
    }
    float depth = triangle_depth(f, d, ok);
    return ok ? (depth - pc.z) * length(pc) / pc.z : 0.0;
}

// The head of the search's loop: on the surface, test the point; else step (the paper's step: h
// metres along the unit ray; with SECANT after the first step the secant through the last two
// samples: h is measured along the line to the photo's centre, which converges slowly, or jumps off
// the surface, when that line and the pixel ray differ by a large angle).
int search_top() {
    if (g_i >= u_max_steps) return MISS;
    g_iters++;
    if (abs(g_f) <= CONVERGED * g_s) {  // on the surface: no interval to refine
        return lookup_at(PH_TEST_POINT, g_s);
    }
    float step = g_f / g_dlen;
#if SECANT
    if (!g_restart && g_fp != g_f) step = -g_f * (g_s - g_sp) / (g_f - g_fp);
#endif
    g_restart = false;
    g_step = step;
    g_sn = g_s + step;
    if (g_sn <= 0.0) return MISS;
    g_k = 0;
    return lookup_at(PH_STEP, g_sn);
}

// The search goes on from the step's point.
int search_next() {
    g_sp = g_s;
    g_fp = g_f;
    g_s = g_sn;
    g_f = g_fn;
    ++g_i;
    return search_top();
}

// The refinement's next point (see the header for the two methods), or its hit to test.
int refine_top() {
#if ILLINOIS
    if (g_b < u_binary_steps && g_fa != g_fb) return lookup_at(PH_REFINE, (g_sa * g_fb - g_sb * g_fa) / (g_fb - g_fa));
#else
    if (g_b < u_binary_steps) return lookup_at(PH_REFINE, 0.5 * (g_sa + g_sb));
#endif
    return lookup_at(PH_TEST_HIT, (g_fa == g_fb) ? 0.5 * (g_sa + g_sb) : g_sa + (g_sb - g_sa) * g_fa / (g_fa - g_fb));
}

// An enclosed interval gave no valid hit: the paper's search ends; with SECANT (a sign change
// across a depth edge of D_l, not a surface, or a hit that fails the discontinuity test) it resumes
// beyond the interval, at most MAX_RESUMES times (a pixel that no depth-map surface covers would
// otherwise spend every step of the budget).
int interval_failed() {
#if SECANT
    if (++g_resumes > MAX_RESUMES) return MISS;
    g_restart = true;
    return search_next();
#else
    return MISS;
#endif
}

// Starts the search of D_l along the render camera's ray C + s * dir (world) from s = s0.
void search_start(int l, vec3 C, vec3 dir, float s0) {
    Photo ph = photos[l];
    g_l = l;
    g_o = to_photo(ph, C);
    g_v = vec3(dot(ph.r0.xyz, dir), dot(ph.r1.xyz, dir), dot(ph.r2.xyz, dir));
    g_fc = ph.k;
    g_size = ph.size.xy;
    g_dlen = length(dir);
    g_s = s0;
    lookup_at(PH_START, s0);
}

// The render camera's centre (world) and the ray direction of pixel p: the search's ray C + s * dir.
vec3 camera_centre() {
    return -(transpose(u_R) * u_t);
}

vec3 pixel_dir(ivec2 p) {
    return transpose(u_R) * camera_ray(vec2(p) + 0.5);
}

// Takes the pending lookup's result (lookup()): PENDING with the next lookup set, or the search's end
// (HIT: at g_q, normal g_n; MISS).
int advance(float h, bool ok) {
    if (g_phase == PH_START) {
        if (!ok) return MISS;
        g_f = h;
        g_sp = g_s;
        g_fp = h;
        g_restart = true;
        g_resumes = 0;
        g_i = 0;
        return search_top();
    }
    if (g_phase == PH_STEP) {
#if SECANT
        // a step that lands on an empty or outside texel is halved (a few times) before giving up
        if (!ok && g_k < 4) {
            g_step *= 0.5;
            g_sn = g_s + g_step;
            ++g_k;
            return lookup_at(PH_STEP, g_sn);
        }
#endif
#if STATISTICS
        if (g_layer >= 0) record_step(g_layer, g_i, abs(g_sn - g_s) * g_dlen);
#endif
        if (!ok) return MISS;
        g_fn = h;
        if ((h > 0.0) == (g_f > 0.0)) return search_next();
        // enclosed: refine [s, sn]
        g_sb = g_sn; g_fb = h;  // a: (g_s, g_f) already
        g_side = 0;
        g_b = 0;
        return g_sa == g_sb ? lookup_at(PH_TEST_HIT, g_sa) : refine_top();
    }
    if (g_phase == PH_REFINE) {
        if (!ok) return interval_failed();  // a probe on empty texels
        float sm = g_q, fm = h;
#if ILLINOIS
        if (abs(fm) <= 1e-6 * sm) return lookup_at(PH_TEST_HIT, sm);
        if ((fm > 0.0) == (g_fb > 0.0)) {
            g_sb = sm; g_fb = fm;
            if (g_side == -1) g_fa *= 0.5;
            g_side = -1;
        } else {
            g_sa = sm; g_fa = fm;
            if (g_side == 1) g_fb *= 0.5;
            g_side = 1;
        }
#else
        if ((fm > 0.0) == (g_fa > 0.0)) { g_sa = sm; g_fa = fm; } else { g_sb = sm; g_fb = fm; }
#endif
        ++g_b;
        return refine_top();
    }
    if (g_phase == PH_TEST_HIT) return ok ? HIT : interval_failed();
    if (g_phase == PH_TEST_POINT) {
        if (ok) return HIT;
#if SECANT
        if (++g_resumes > MAX_RESUMES) return MISS;
        // nudge past the edge point: a texel beyond it along the ray
        g_sn = g_s * (1.0 + 1e-3);
        return lookup_at(PH_NUDGE, g_sn);
#else
        return MISS;
#endif
    }
    // PH_NUDGE
    if (!ok) return MISS;
    g_s = g_sn;
    g_f = h;
    g_restart = true;
    ++g_i;
    return search_top();
}

// One search of D_l along the ray C + s * dir from s0 to its end: true with g_q on a valid
// intersection.
bool trace(int l, vec3 C, vec3 dir, float s0) {
    g_n = vec3(0.0);
    search_start(l, C, dir, s0);
    int r = PENDING;
    while (r == PENDING) {
        bool ok;
        float h = lookup(ok);
        r = advance(h, ok);
    }
    return r == HIT;
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
    vec3 C = camera_centre();
    g_layer = -1;
    for (uint e = gl_WorkGroupID.x; e < hole_cmd.n; e += gl_NumWorkGroups.x) {
        uint pix = hole_items[e];
        ivec2 p = ivec2(int(pix % uint(u_size.x)), int(pix / uint(u_size.x)));
        if (lid == 0u) s_best = NONE;
        memoryBarrierShared();
        barrier();
        int k = int(lid < 4u ? lid : lid + 1u);  // the 3 x 3 neighbourhood in row order, centre skipped
        ivec2 q = p + ivec2(k % 3 - 1, k / 3 - 1);
        g_iters = 0;
        Hit nb = Hit(0.0, -1, -1, 0u);
        bool found = false;
        if (all(greaterThanEqual(q, ivec2(0))) && all(lessThan(q, u_size))) {
            nb = hits[uint(q.y * u_size.x + q.x)];
            if (hit_layer(nb) >= 0 && hit_layer(nb) < u_layers + u_pass && nb.depth > 0.0) {
                // only the neighbour's own surface: within the discontinuity threshold of its depth
                found = trace(nb.label, C, pixel_dir(p), nb.depth) && abs(g_q - nb.depth) <= u_threshold;
            }
        }
        s_iters[lid] = g_iters;
        if (found) atomicMin(s_best, lid);
        memoryBarrierShared();
        barrier();
        uint best = s_best;
        if (best == lid) {
            hits[pix] = Hit(g_q, nb.label, -1, layer_iters(u_layers + u_pass, iters_through(best, hit_iters(hits[pix]))));
            write_normal(pix, g_n);
        } else if (best == NONE && lid == 0u) {
            hits[pix].layer_iters = layer_iters(-1, iters_through(best, hit_iters(hits[pix])));
            if (u_fill != 0) push_hole(pix);
        }
        memoryBarrierShared();
        barrier();  // s_best and s_iters are reset for the next item
    }
}
#else
// The pixel pass: one pixel an invocation, its layers' searches one after the other in one loop
// whose every turn does one lookup (advance() takes its result), so the lanes of a warp fetch side
// by side whatever search or phase each is in. Written as nested loops (layers, steps, refinement)
// with a lookup in each place, the search was ~20 % slower on an H200 (reports/frame-h200, session
// 15). Lanes that take further pixels of a block once theirs is done were slower still; handing the
// searches still running after 8-32 turns to a second pass gained nothing at 3840x2160 and lost
// 0.1 ms at 1280x720, where that pass's chains of lookups came after the first pass (session 16).

// This invocation's pixel, its index (a function, not a word of state: see g_o)
ivec2 this_pixel() {
    return ivec2(gl_GlobalInvocationID.xy);
}

uint pixel_index() {
    return uint(gl_GlobalInvocationID.y) * uint(u_size.x) + uint(gl_GlobalInvocationID.x);
}

// Starts the search of layer g_layer; false when the pixel has no such layer (peeling: every later
// layer is empty too).
bool begin_layer() {
    if (g_layer >= u_layers) return false;
    uint at = uint(g_layer) * uint(u_size.x * u_size.y) + pixel_index();
    uint bits = layer_depth[at];
    if (bits == EMPTY_BITS) return false;
    int l = layer_label[at];
    search_start(l, camera_centre(), pixel_dir(this_pixel()), uintBitsToFloat(bits));
    return true;
}

void raytrace_pixel() {
    ivec2 p = this_pixel();
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    g_iters = 0;
    g_n = vec3(0.0);
    int found = -1;  // the layer that gave the hit
#if RAYTRACE
    g_layer = 0;
    bool busy = begin_layer();
    while (busy) {
        bool ok;
        float h = lookup(ok);
        int r = advance(h, ok);
        if (r == HIT) found = g_layer;
        if (r == MISS) {
            ++g_layer;
            busy = begin_layer();
        }
        busy = busy && r != HIT;
    }
    Hit hit = found >= 0 ? Hit(g_q, g_l, -1, layer_iters(found, g_iters)) : Hit(0.0, -1, -1, layer_iters(-1, g_iters));
    uint pix = pixel_index();
#else
    // the ablation: the first layer's splat is the surface
    uint pix = pixel_index();
    uint bits0 = layer_depth[pix];
    if (bits0 != EMPTY_BITS) {
        found = 0;
        vec3 dir = pixel_dir(p);
        g_n = -dir / length(dir);
    }
    Hit hit = found >= 0 ? Hit(uintBitsToFloat(bits0), layer_label[pix], -1, layer_iters(0, 0)) : Hit(0.0, -1, -1, layer_iters(-1, 0));
#endif
    hits[pix] = hit;
    write_normal(pix, found >= 0 ? g_n : vec3(0.0));
    if (RAYTRACE != 0 && u_fill != 0 && hit.depth <= 0.0 && layer_depth[pix] != EMPTY_BITS) push_hole(pix);
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
