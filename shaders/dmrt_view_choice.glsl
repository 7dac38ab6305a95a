// View-dependent photo choice, per pixel (an addition to the paper; dmrt/runtime/view_choice.py).
// Candidates: the pixel's final label (the paper's, from the labeling pass) and the frame's
// preselected photos (dmrt_view_scores.glsl, ranked by dmrt_photo_choice.glsl into
// B_VIEW_CANDIDATES). Each candidate in front of whose camera the point lies is ranked by its
// penalty (dmrt_view_common.glsl: the angle between the view ray and the photo's ray, plus the
// resolution term); the depth maps are then fetched in ascending penalty order until BLEND + 1 see
// the point; a photo whose map does not hold it (an occluder in front of it, or no surface) is dropped.
//
// The BLEND best get the weights of unstructured lumigraph rendering: w_i = (1 - p_i / p_t) / p_i,
// with p_t the penalty of the next best visible candidate (pi when there is none), normalised; a
// photo's weight falls to 0 as it is overtaken, so the colours change smoothly as the camera moves.
// The best photo becomes the pixel's final label (the label histogram, the photo cache and the
// leveling follow it); with BLEND > 1 the others and all weights go to B_VIEW_BLEND for the
// texturing pass. Nothing visible (all candidates fail the test): the final label stays, alone.
//
// At high resolutions one choice serves a 2x2 quad of pixels where the quad is one surface (main).
#include "splat_depth_common.glsl"
#include "dmrt_frame.glsl"
#include "dmrt_photos.glsl"
#include "dmrt_view_common.glsl"

#if defined COMPUTE_SHADER

#ifndef BLEND
#define BLEND 1
#endif
#ifndef CANDIDATES  // RenderConfig.view_candidates: the list's length at most
#define CANDIDATES 16
#endif

// One invocation per 2x2 quad of pixels with u_quads, else per pixel; 8x8 a workgroup.
layout(local_size_x = 8, local_size_y = 8) in;

uniform bool u_quads;

layout(std430, binding = B_VIEW_CANDIDATES) readonly buffer Candidates {
    uint header[STATUS_HEADER_WORDS];  // header[1]: the number of candidates (dmrt_photo_choice.glsl)
    int candidates[];
};
#if BLEND > 1
// Per pixel: x, y, z = the 2nd to 4th photo (-1 = none), w = the weights of the 1st to 4th
// (packUnorm4x8, summing to ~1).
layout(std430, binding = B_VIEW_BLEND) writeonly buffer Blend { ivec4 blend[]; };
#endif

const float NONE = 1e30;

// The candidates' turn penalties: one per photo and frame, computed once a workgroup.
shared float s_turn[CANDIDATES > 0 ? CANDIDATES : 1];

// The choice at pixel p whose hit is `hit` (depth > 0, final_label >= 0): the final label, and with
// BLEND > 1 the blend record.
int choose(ivec2 p, Hit hit, int n, out ivec4 record) {
    vec3 q, dir;
    float dist;
    view_ray(p, hit.depth, q, dir, dist);

    // every candidate's penalty first (arithmetic only: index 0 = the label, i = candidates[i - 1]);
    // then the depth maps of the lowest ones, in ascending order, until BLEND + 1 see the point: about
    // BLEND + 1 fetches a pixel whatever the candidates' order. Fixed-size arrays indexed only by
    // unrolled loops with constant bounds, so that they stay in registers.
    float cpen[CANDIDATES + 1];
    for (int i = 0; i <= CANDIDATES; ++i) {
        cpen[i] = NONE;
        int l = i == 0 ? hit.final_label : (i <= n ? candidates[i - 1] : -1);
        if (l < 0 || (i > 0 && l == hit.final_label)) continue;
        Photo ph = photos[l];
        float penalty = view_penalty(ph, to_photo(ph, q), dir, dist, i == 0 ? turn_penalty(ph) : s_turn[i - 1]);
        if (penalty >= 0.0) cpen[i] = penalty;
    }
    float pen[BLEND + 1];
    int lab[BLEND + 1];
    for (int k = 0; k <= BLEND; ++k) { pen[k] = NONE; lab[k] = -1; }
    int found = 0;
    for (int tries = 0; tries <= CANDIDATES && found <= BLEND; ++tries) {
        float best = NONE;
        int bi = -1;
        for (int i = 0; i <= CANDIDATES; ++i)  // the lowest left; equal ones: the label, then list order
            if (cpen[i] < best) { best = cpen[i]; bi = i; }
        if (bi < 0) break;
        for (int i = 0; i <= CANDIDATES; ++i)
            if (i == bi) cpen[i] = NONE;
        int l = bi == 0 ? hit.final_label : candidates[bi - 1];
        Photo ph = photos[l];
        if (!view_sees(l, ph, to_photo(ph, q))) continue;
        for (int k = 0; k <= BLEND; ++k)
            if (k == found) { pen[k] = best; lab[k] = l; }
        ++found;
    }
    if (lab[0] < 0) {  // no candidate sees the point: the paper's label, alone
        lab[0] = hit.final_label;
        pen[0] = MIN_PENALTY;
    }
    record = ivec4(-1, -1, -1, 0);
#if BLEND > 1
    float threshold = lab[BLEND] >= 0 ? pen[BLEND] : 3.14159265;
    vec4 w = vec4(0.0);
    for (int k = 0; k < BLEND; ++k)
        if (lab[k] >= 0) w[k] = max(1.0 - pen[k] / threshold, 0.0) / pen[k];
    float total = w.x + w.y + w.z + w.w;
    w = total > 0.0 ? w / total : vec4(1.0, 0.0, 0.0, 0.0);
    for (int k = 1; k < BLEND; ++k) record[k - 1] = w[k] > 0.0 ? lab[k] : -1;
    record.w = int(packUnorm4x8(w));
#endif
    return lab[0];
}

void write_choice(ivec2 p, int label, ivec4 record) {
    uint pix = uint(p.y * u_size.x + p.x);
    if (label >= 0) hits[pix].final_label = label;
#if BLEND > 1
    blend[pix] = record;
#endif
}

// Pixel k (0..3: row-major) of the quad whose top-left pixel is p0.
ivec2 quad_pixel(ivec2 p0, int k) { return p0 + ivec2(k & 1, k >> 1); }

void main() {
    int n = min(int(header[1]), CANDIDATES);
    uint li = gl_LocalInvocationIndex;
    if (li < uint(n)) s_turn[li] = turn_penalty(photos[candidates[li]]);
    barrier();

    // With u_quads, one choice for a whole 2x2 quad, at its top-left pixel's point, where the quad is
    // one surface: four hits with one label and depths within the visibility tolerance. The caller
    // sets it where two pixels are at most a texel of the finest depth map (at 3840x2160 with the
    // paper's maps, a pixel is about half a texel): the maps cannot tell the quad's pixels apart, and
    // per-pixel choices would fetch the same texels four times. Elsewhere each pixel chooses alone
    // (without u_quads: one invocation a pixel).
    ivec2 p0 = (u_quads ? 2 : 1) * ivec2(gl_GlobalInvocationID.xy);
    if (p0.x >= u_size.x || p0.y >= u_size.y) return;
    Hit h0 = hits[p0.y * u_size.x + p0.x];
    bool agree = u_quads && p0.x + 1 < u_size.x && p0.y + 1 < u_size.y && h0.depth > 0.0 && h0.final_label >= 0;
    float zmin = h0.depth, zmax = h0.depth;
    for (int k = 1; k < 4 && agree; ++k) {
        ivec2 p = quad_pixel(p0, k);
        Hit hk = hits[p.y * u_size.x + p.x];
        agree = hk.depth > 0.0 && hk.final_label == h0.final_label;
        zmin = min(zmin, hk.depth);
        zmax = max(zmax, hk.depth);
    }
    agree = agree && zmax - zmin <= u_view_tol;
    for (int k = 0; k < (u_quads && !agree ? 4 : 1); ++k) {
        ivec2 p = quad_pixel(p0, k);
        if (p.x >= u_size.x || p.y >= u_size.y) continue;
        Hit hit = k == 0 ? h0 : hits[p.y * u_size.x + p.x];
        int label = -1;
        ivec4 record = ivec4(-1, -1, -1, 0);  // background (texturing writes it)
        if (hit.depth > 0.0 && hit.final_label >= 0) label = choose(p, hit, n, record);
        if (agree)
            for (int j = 0; j < 4; ++j) write_choice(quad_pixel(p0, j), label, record);
        else
            write_choice(p, label, record);
    }
}

#endif
