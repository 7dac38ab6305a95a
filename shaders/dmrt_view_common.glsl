// View-dependent photo choice (an addition to the paper; dmrt/runtime/view_choice.py): how well a
// photo suits the render camera at a surface point, the ranking of unstructured lumigraph
// rendering (Buehler et al. 2001) with DMRT's own visibility test. Shared by the per-frame candidate
// scores (dmrt_view_scores.glsl) and the per-pixel choice (dmrt_view_choice.glsl). Included after
// dmrt_frame.glsl and dmrt_photos.glsl; no #version.

uniform float u_res_weight;  // radians a photo pays per octave its texel at the point is coarser than the frame's pixel
uniform float u_view_tol;    // metres: |D_l - z_l| beyond which photo l does not see the point

// Below this a penalty counts as this (a photo at the render camera's own pose: its weight stays finite).
const float MIN_PENALTY = 1e-3;

// The render camera's view of pixel p at camera z `depth`: world point q, unit world direction of
// the view ray, and the frame's pixel footprint at q (metres a pixel, along the ray).
void view_ray(ivec2 p, float depth, out vec3 q, out vec3 dir, out float footprint) {
    vec3 qc = depth * camera_ray(vec2(p) + 0.5);
    float len = length(qc);
    q = transpose(u_R) * (qc - u_t);
    dir = transpose(u_R) * (qc / len);
    footprint = len / u_K.x;
}

// The penalty of photo ph for a point whose photo-camera position is pc (to_photo), seen along the
// view direction dir with the frame's footprint: the angle between the two rays to the point
// (radians) plus u_res_weight per octave by which the photo's texel there is coarser than the
// frame's pixel. -1 when the point is behind the photo or projects outside its map (no fetch yet:
// the caller tests visibility only for penalties worth it).
float view_penalty(Photo ph, vec3 pc, vec3 dir, float footprint) {
    if (pc.z <= 1e-6) return -1.0;
    vec2 uv = photo_uv(ph, pc);
    if (any(lessThan(uv, vec2(0.0))) || any(greaterThan(uv, ph.size.xy))) return -1.0;
    float len = length(pc);
    float angle = acos(clamp(dot(dir, photo_dir_to_world(ph, pc) / len), -1.0, 1.0));
    // ph.k.x is in depth-map texels: the photo's own pixels are ph.full.x / ph.size.x as many
    float texel = len / (ph.k.x * ph.full.x / ph.size.x);
    return max(angle + u_res_weight * max(log2(texel / footprint), 0.0), MIN_PENALTY);
}

// Whether photo l's depth map holds the point whose photo-camera position is pc (in front of it and
// inside its map): no occluder in front of it, within u_view_tol.
bool view_sees(int l, Photo ph, vec3 pc) {
    bool ok;
    float depth = surface_depth(l, ph, photo_uv(ph, pc), ok);
    return ok && abs(depth - pc.z) <= u_view_tol;
}
