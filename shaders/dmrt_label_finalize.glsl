// DMRT: each pixel's final label (dmrt_label_histogram then counts them for image management).
//
// The final label is the labeling pass's (the nearest covering proxy's, paper 5.2.1) where it found
// one, else the raytraced layer's. With u_label_check (an addition to the paper), a labeling-pass
// label whose depth map does not see the pixel's surface point - |D_l - z_l| > u_visibility_tol at
// its projection, or outside / empty - is replaced by the raytraced layer's label, whose depth map
// holds the point by construction: the nearest proxy can lie on the same surface yet its photo be
// occluded at this point (next to an occluder's silhouette), which would texture the point with
// the occluder's colour.
#include "splat_depth_common.glsl"
#include "dmrt_frame.glsl"
#include "dmrt_photos.glsl"

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
uniform int u_label_check;
uniform float u_visibility_tol;  // metres


bool sees(int l, vec3 q) {
    Photo ph = photos[l];
    vec3 pc = to_photo(ph, q);
    if (pc.z <= 1e-6) return false;
    bool ok;
    float depth = surface_depth(l, ph, photo_uv(ph, pc), ok);
    return ok && abs(depth - pc.z) <= u_visibility_tol;
}

void finalize(ivec2 p);

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x < u_size.x && p.y < u_size.y) finalize(p);
}

void finalize(ivec2 p) {
    uint pix = uint(p.y * u_size.x + p.x);
    Hit hit = hits[pix];
    int label = -1;
    if (hit.depth > 0.0) {
        label = hit.label;
#if PACKED_LABELS
        int v = key[pix].y == EMPTY_BITS ? EMPTY_LABEL : int(key[pix].x);
#else
        int v = vlabel[pix];
#endif
        if (u_use_labeling != 0 && v != EMPTY_LABEL && v != label) {
            vec3 q = transpose(u_R) * (hit.depth * camera_ray(vec2(p) + 0.5) - u_t);
            if (u_label_check == 0 || sees(v, q)) label = v;
        }
    }
    hits[pix].final_label = label;
}

#endif
