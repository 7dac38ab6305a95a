// View-dependent photo choice (an addition to the paper; dmrt/runtime/view_choice.py): how well a
// photo suits the render camera at a surface point, the ranking of unstructured lumigraph
// rendering (Buehler et al. 2001) with DMRT's own visibility test. Shared by the per-frame candidate
// scores (dmrt_view_scores.glsl) and the per-pixel choice (dmrt_view_choice.glsl). Included after
// dmrt_frame.glsl and dmrt_photos.glsl; no #version.

uniform float u_distance_weight;  // radians a photo pays per octave its distance to the point differs from the view's
uniform float u_turn_weight;      // radians a photo pays per radian its optical axis turns from the view's
uniform float u_view_tol;    // metres: |D_l - z_l| beyond which photo l does not see the point

// Below this a penalty counts as this (a photo at the render camera's own pose: its weight stays finite).
const float MIN_PENALTY = 1e-3;

// The render camera's view of pixel p at camera z `depth`: world point q, unit world direction of
// the view ray, and the distance from the render camera to q (metres).
void view_ray(ivec2 p, float depth, out vec3 q, out vec3 dir, out float dist) {
    vec3 qc = depth * camera_ray(vec2(p) + 0.5);
    float len = length(qc);
    q = transpose(u_R) * (qc - u_t);
    dir = transpose(u_R) * (qc / len);
    dist = len;
}

// The penalty of photo ph for a point whose photo-camera position is pc (to_photo), seen along the
// view direction dir from distance dist: the angle between the two rays to the point
// (radians), plus u_distance_weight per octave by which the photo's distance to the point differs
// from the view's (a photo far behind on the same ray holds less detail, one far in front sees
// other occlusions), plus `turn` = turn_penalty(ph), u_turn_weight times the angle between the
// photo's optical axis and the view's: two photos taken from one place agree on every ray angle whatever their orientation, but
// the one turned like the view sees the point where the view does, away from its borders (lens
// residuals, vignetting, a registration error that grows there), and was most likely taken with
// it (real photos are taken in sequences: exposure, blur and pose drift follow the sequence). -1
// when the point is behind the photo or projects outside its map (no fetch yet: the caller tests
// visibility only for penalties worth it).
float view_penalty(Photo ph, vec3 pc, vec3 dir, float dist, float turn) {
    if (pc.z <= 1e-6) return -1.0;
    vec2 uv = photo_uv(ph, pc);
    if (any(lessThan(uv, vec2(0.0))) || any(greaterThan(uv, ph.size.xy))) return -1.0;
    float len = length(pc);
    float angle = acos(clamp(dot(dir, photo_dir_to_world(ph, pc) / len), -1.0, 1.0));
    float octaves = abs(log2(len / dist));
    return max(angle + u_distance_weight * octaves + turn, MIN_PENALTY);
}

// The turn term of view_penalty for photo ph: u_turn_weight times the angle between its optical
// axis and the view's (the third rows of the photo's and the view's rotations, world). One value
// per photo and frame.
float turn_penalty(Photo ph) {
    return u_turn_weight * acos(clamp(dot(ph.r2.xyz, vec3(u_R[0][2], u_R[1][2], u_R[2][2])), -1.0, 1.0));
}

// Whether photo l's depth map holds the point whose photo-camera position is pc (in front of it and
// inside its map): no occluder in front of it, within u_view_tol.
bool view_sees(int l, Photo ph, vec3 pc) {
    bool ok;
    float depth = surface_depth(l, ph, photo_uv(ph, pc), ok);
    return ok && abs(depth - pc.z) <= u_view_tol;
}
