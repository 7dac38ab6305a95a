// DMRT: a pixel's final label, for dmrt_label_finalize.glsl and the tile labeling pass that
// finishes the labels itself (dmrt_tiles_labeling.glsl, FINALIZE). Included after dmrt_frame.glsl
// and dmrt_photos.glsl; no #version.
//
// The final label is the labeling pass's (the nearest covering proxy's, paper 5.2.1) where it found
// one, else the raytraced layer's. With u_label_check (an addition to the paper), a labeling-pass
// label whose depth map does not see the pixel's surface point - |D_l - z_l| > u_visibility_tol at
// its projection, or outside / empty - is replaced by the raytraced layer's label, whose depth map
// holds the point by construction: the nearest proxy can lie on the same surface yet its photo be
// occluded at this point (next to an occluder's silhouette), which would texture the point with
// the occluder's colour.

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

// The final label of pixel p (-1: background); hit: its record, v: the labeling pass's label there
// (EMPTY_LABEL: none, or no labeling pass).
int final_label(Hit hit, int v, ivec2 p) {
    if (hit.depth <= 0.0) return -1;
    int label = hit.label;
    if (v != EMPTY_LABEL && v != label) {
        vec3 q = transpose(u_R) * (hit.depth * camera_ray(vec2(p) + 0.5) - u_t);
        if (u_label_check == 0 || sees(v, q)) label = v;
    }
    return label;
}
