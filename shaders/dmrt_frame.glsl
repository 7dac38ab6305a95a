// Per-pixel results of the DMRT passes, shared by the raytracing, labeling, finalize and texturing
// programs. Included; no #version. Pixels are row-major from the top-left (image order).

struct Hit {
    float depth;       // camera z of the render camera, metres; 0 = no valid hit (background)
    int label;         // label of the layer whose depth map gave the hit; -1 = none
    int layer;         // 0-based index of that layer; -1 = none
    int iters;         // iterative-search steps over every layer tried (the paper's c_total)
    float nx, ny, nz;  // unit world-space normal facing the render camera (0 = background)
    int final_label;   // per-pixel label after the labeling pass; -1 = none
};

layout(std430, binding = B_HITS) buffer Hits { Hit hits[]; };

// The ray of the render camera through pixel centre uv (pixels, corner origin) in camera space,
// scaled so that the point at parameter s has camera z = s (uses u_K of splat_depth_common.glsl).
vec3 camera_ray(vec2 uv) {
    return vec3((uv.x - u_K.z) / u_K.x, (uv.y - u_K.w) / u_K.y, 1.0);
}
