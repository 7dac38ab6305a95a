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

layout(local_size_x = 8, local_size_y = 8) in;

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

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    uint pix = uint(p.y * u_size.x + p.x);
    Hit hit = hits[pix];
    if (hit.depth <= 0.0 || hit.final_label < 0) {  // background (texturing writes it)
#if BLEND > 1
        blend[pix] = ivec4(-1, -1, -1, 0);
#endif
        return;
    }
    vec3 q, dir;
    float dist;
    view_ray(p, hit.depth, q, dir, dist);

    // every candidate's penalty first (arithmetic only: index 0 = the label, i = candidates[i - 1]);
    // then the depth maps of the lowest ones, in ascending order, until BLEND + 1 see the point: about
    // BLEND + 1 fetches a pixel whatever the candidates' order. Fixed-size arrays indexed only by
    // unrolled loops with constant bounds, so that they stay in registers.
    float cpen[CANDIDATES + 1];
    int n = min(int(header[1]), CANDIDATES);
    for (int i = 0; i <= CANDIDATES; ++i) {
        cpen[i] = NONE;
        int l = i == 0 ? hit.final_label : (i <= n ? candidates[i - 1] : -1);
        if (l < 0 || (i > 0 && l == hit.final_label)) continue;
        Photo ph = photos[l];
        float penalty = view_penalty(ph, to_photo(ph, q), dir, dist);
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
    hits[pix].final_label = lab[0];
#if BLEND > 1
    float threshold = lab[BLEND] >= 0 ? pen[BLEND] : 3.14159265;
    vec4 w = vec4(0.0);
    for (int k = 0; k < BLEND; ++k)
        if (lab[k] >= 0) w[k] = max(1.0 - pen[k] / threshold, 0.0) / pen[k];
    float total = w.x + w.y + w.z + w.w;
    w = total > 0.0 ? w / total : vec4(1.0, 0.0, 0.0, 0.0);
    ivec4 others = ivec4(-1);
    for (int k = 1; k < BLEND; ++k) others[k - 1] = w[k] > 0.0 ? lab[k] : -1;
    others.w = int(packUnorm4x8(w));
    blend[pix] = others;
#endif
}

#endif
