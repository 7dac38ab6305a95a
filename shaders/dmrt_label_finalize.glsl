// DMRT: each pixel's final label (dmrt_final_label.glsl says which), for the visibility paths whose
// labeling pass leaves its labels in Key / Label (dmrt_label_histogram then counts them for image
// management).
#include "splat_depth_common.glsl"
#include "dmrt_frame.glsl"
#include "dmrt_photos.glsl"
#include "dmrt_final_label.glsl"

#if defined COMPUTE_SHADER

layout(local_size_x = 8, local_size_y = 8) in;

#ifndef PACKED_LABELS
#define PACKED_LABELS 0
#endif
#if PACKED_LABELS  // the labeling pass's 64-bit keys, read as (label, distance bits) pairs
layout(std430, binding = B_KEY) readonly buffer Key { uvec2 key[]; };
#else
layout(std430, binding = B_VLABEL) readonly buffer Label { int vlabel[]; };
#endif

uniform int u_use_labeling;

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    uint pix = uint(p.y * u_size.x + p.x);
    Hit hit = hits[pix];
    int v = EMPTY_LABEL;
    if (hit.depth > 0.0 && u_use_labeling != 0) {
#if PACKED_LABELS
        v = key[pix].y == EMPTY_BITS ? EMPTY_LABEL : int(key[pix].x);
#else
        v = vlabel[pix];
#endif
    }
    hits[pix].final_label = final_label(hit, v, p);
}

#endif
