// DMRT texturing pass (paper Section 5.2.3): each pixel's surface point is projected into the photo
// of its final label and coloured from it, bilinearly: from the full-resolution cache when image
// management holds that photo there, else from the always-resident low-resolution copy.
// Output: one packed RGBA8 word per pixel (R in the lowest byte), 0 = background.
#include "splat_depth_common.glsl"
#include "dmrt_frame.glsl"
#include "dmrt_photos.glsl"

#if defined COMPUTE_SHADER

layout(local_size_x = 8, local_size_y = 8) in;

layout(std430, binding = 6) readonly buffer Slots { int slots[]; };  // photo -> cache layer, -1
layout(std430, binding = 7) writeonly buffer Colors { uint colors[]; };

uniform sampler2DArray u_low;   // low-resolution photos, layer = photo index
uniform sampler2DArray u_high;  // full-resolution cache, layer = slot
uniform vec2 u_low_dims;        // width, height of the arrays (photos fill the top-left corner)
uniform vec2 u_high_dims;

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    uint pix = uint(p.y * u_size.x + p.x);
    Hit hit = hits[pix];
    int l = hit.final_label;
    if (hit.depth <= 0.0 || l < 0) {
        colors[pix] = 0u;
        return;
    }
    mat3 Rt = transpose(u_R);
    vec3 q = Rt * (hit.depth * camera_ray(vec2(p) + 0.5) - u_t);
    Photo ph = photos[l];
    vec3 pc = to_photo(ph, q);
    vec2 uvn = photo_uv(ph, pc) / ph.size.xy;  // 0..1 across the photo
    int slot = slots[l];
    vec4 c;
    if (slot >= 0) {
        vec2 px = clamp(uvn * ph.full.xy, vec2(0.5), ph.full.xy - 0.5);
        c = textureLod(u_high, vec3(px / u_high_dims, float(slot)), 0.0);
    } else {
        vec2 px = clamp(uvn * ph.size.zw, vec2(0.5), ph.size.zw - 0.5);
        c = textureLod(u_low, vec3(px / u_low_dims, float(l)), 0.0);
    }
    colors[pix] = packUnorm4x8(vec4(c.rgb, 1.0));
}

#endif
