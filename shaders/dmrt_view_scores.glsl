// View-dependent photo choice, per frame: which photos are worth testing at every pixel. A grid of
// the frame's pixels (u_samples of them, u_stride apart) is scored against every photo: a photo that
// sees a sample's raytraced point adds 1 / penalty (dmrt_view_common.glsl), so the photos seen from
// close to the view's own rays over much of the frame rank first. dmrt_photo_choice.glsl then keeps
// the best (dmrt/runtime/view_choice.py). Cost: samples x photos tests, independent of the frame
// size; one global atomic per workgroup.
//
// Which photos: workgroup row r scores photo u_photo0 + r (every photo of the scene, the paper
// path: every map resident), or with PHOTO_LIST 1 photo list[u_photo0 + r] (a partial map cache:
// the renderer's short list of the photos that can matter, so the cost follows the list, not the
// scene). Either way the score lands in scores[photo]: the ranking over every photo is the same.
//
// Buffers: B_HITS (read), B_PHOTOS, B_VIEW_SCORES uint[n_photos] (added to; cleared by the caller),
// with PHOTO_LIST B_VIEW_LIST int[] (photo indices, no repeats: a repeat would count twice).
#include "splat_depth_common.glsl"
#include "dmrt_frame.glsl"
#include "dmrt_photos.glsl"
#include "dmrt_view_common.glsl"

#if defined COMPUTE_SHADER

layout(local_size_x = 64) in;

layout(std430, binding = B_VIEW_SCORES) buffer Scores { uint scores[]; };

uniform ivec2 u_samples;  // sample grid columns, rows
uniform int u_stride;     // pixels between samples
uniform int u_photo0;     // photo (or list entry) of workgroup row 0 (dispatches hold at most 65535 rows)

#ifndef PHOTO_LIST
#define PHOTO_LIST 0
#endif
#if PHOTO_LIST
layout(std430, binding = B_VIEW_LIST) readonly buffer List { int list[]; };
#endif

// 1 / penalty in units of 1/64: a photo seen head-on (penalty MIN_PENALTY) adds 64000 a sample, so
// 4096 samples stay below 2^32
const float SCORE_SCALE = 64.0;

shared uint group_score;

void main() {
#if PHOTO_LIST
    int l = list[u_photo0 + int(gl_WorkGroupID.y)];
#else
    int l = u_photo0 + int(gl_WorkGroupID.y);
#endif
#if MAP_SLOTS
    if (map_layer(l) < 0) return;  // not resident (the whole workgroup): no candidate, nothing flagged
#endif
    if (gl_LocalInvocationIndex == 0u) group_score = 0u;
    barrier();
    int s = int(gl_GlobalInvocationID.x);
    if (s < u_samples.x * u_samples.y) {
        ivec2 p = min(ivec2(s % u_samples.x, s / u_samples.x) * u_stride + u_stride / 2, u_size - 1);
        float depth = hits[p.y * u_size.x + p.x].depth;
        if (depth > 0.0) {
            vec3 q, dir;
            float dist;
            view_ray(p, depth, q, dir, dist);
            Photo ph = photos[l];
            vec3 pc = to_photo(ph, q);
            float penalty = view_penalty(ph, pc, dir, dist, turn_penalty(ph));
            if (penalty > 0.0 && view_sees(l, ph, pc)) atomicAdd(group_score, uint(SCORE_SCALE / penalty));
        }
    }
    barrier();
    if (gl_LocalInvocationIndex == 0u && group_score > 0u) atomicAdd(scores[l], group_score);
}

#endif
