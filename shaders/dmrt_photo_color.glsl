// Colour of a photo at a world point: from the full-resolution cache when image management holds
// that photo there, else from the low-resolution copy (resident with its depth map; bilinear both), times the
// photo's photometric gain (dmrt.preprocess.photometric; all 1 when off). Included after
// dmrt_photos.glsl; no #version.

layout(std430, binding = B_SLOTS) readonly buffer Slots { int slots[]; };  // photo -> cache layer, -1
layout(std430, binding = B_PHOTO_GAINS) readonly buffer PhotoGains { vec4 photo_gains[]; };  // RGB gain, unused

uniform sampler2DArray u_low;   // low-resolution photos, layer = map_layer(photo index)
uniform sampler2DArray u_high;  // full-resolution cache, layer = slot
uniform vec2 u_low_dims;        // width, height of the arrays (photos fill the top-left corner)
uniform vec2 u_high_dims;

// RGB 0..1 of photo l at world point q as the photo records it (q must lie in front of the
// photo's camera).
vec3 photo_color_raw(int l, vec3 q) {
    Photo ph = photos[l];
    vec2 uvn = photo_uv(ph, to_photo(ph, q)) / ph.size.xy;  // 0..1 across the photo
    int slot = slots[l];
    if (slot >= 0) {
        vec2 px = clamp(uvn * ph.full.xy, vec2(0.5), ph.full.xy - 0.5);
        return textureLod(u_high, vec3(px / u_high_dims, float(slot)), 0.0).rgb;
    }
    vec2 px = clamp(uvn * ph.size.zw, vec2(0.5), ph.size.zw - 0.5);
    int layer = map_layer(l);
#if MAP_SLOTS
    if (layer < 0) return vec3(0.0);  // flagged: the frame is rendered again with it
#endif
    return textureLod(u_low, vec3(px / u_low_dims, float(layer)), 0.0).rgb;
}

// RGB of photo l at world point q after the photometric adjustment (may exceed 1: callers clamp
// when they store it). Texturing and the leveling seams both use it, so leveling measures and
// removes what the global gains left.
vec3 photo_color(int l, vec3 q) {
    return photo_color_raw(l, q) * photo_gains[l].rgb;
}

// World point of pixel p's raytraced depth (uses the render camera's uniforms).
vec3 pixel_point(ivec2 p, float depth) {
    return transpose(u_R) * (depth * camera_ray(vec2(p) + 0.5) - u_t);
}
