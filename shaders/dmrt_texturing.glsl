// DMRT texturing pass (paper Section 5.2.3): each pixel's surface point is projected into the photo
// of its final label and coloured from it, times that photo's photometric gain (dmrt_photo_color.glsl:
// the gains buffer B_PHOTO_GAINS, bundle.json photo_gains; all 1 with RenderConfig.photometric off).
// Output: one packed RGBA8 word per pixel (R in the lowest byte), 0 = background. With BLEND > 1
// (the view-dependent photo choice, dmrt_view_choice.glsl) the colour is the weighted mean of the
// pixel's BLEND best photos (B_VIEW_BLEND), each times its own gain.
#include "splat_depth_common.glsl"
#include "dmrt_frame.glsl"
#include "dmrt_photos.glsl"
#include "dmrt_photo_color.glsl"

#if defined COMPUTE_SHADER

layout(local_size_x = 8, local_size_y = 8) in;

layout(std430, binding = B_COLORS) writeonly buffer Colors { uint colors[]; };

#ifndef BLEND
#define BLEND 1
#endif
#if BLEND > 1
layout(std430, binding = B_VIEW_BLEND) readonly buffer Blend { ivec4 blend[]; };
#endif

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    uint pix = uint(p.y * u_size.x + p.x);
    Hit hit = hits[pix];
    if (hit.depth <= 0.0 || hit.final_label < 0) {
        colors[pix] = 0u;
        return;
    }
    vec3 q = pixel_point(p, hit.depth);
    vec3 c = photo_color(hit.final_label, q);  // x the photo's gain
#if BLEND > 1
    ivec4 b = blend[pix];
    vec4 w = unpackUnorm4x8(uint(b.w));
    c *= w.x;
    for (int k = 1; k < BLEND; ++k)
        if (b[k - 1] >= 0 && w[k] > 0.0) c += w[k] * photo_color(b[k - 1], q);
    c /= max(w.x + w.y + w.z + w.w, 1e-6);  // the 8-bit weights' own sum
#endif
    colors[pix] = packUnorm4x8(vec4(clamp(c, 0.0, 1.0), 1.0));
}

#endif
