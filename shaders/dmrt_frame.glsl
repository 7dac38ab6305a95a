// Per-pixel results of the DMRT passes, shared by the raytracing, labeling, finalize and texturing
// programs. Included; no #version. Pixels are row-major from the top-left (image order).
#include "splat_depth_common.glsl"  // the render camera (u_K) and its pixel rays (splat_ray)

// 16 bytes: every pass after raytracing reads a pixel's record (labeling, finalize, histogram,
// texturing, leveling), so its size is their memory traffic. The normal, read only with the frame,
// goes to its own buffer (Normals below) and only when the frame is read back.
struct Hit {
    float depth;       // camera z of the render camera, metres; 0 = no valid hit (background)
    int label;         // label of the layer whose depth map gave the hit; -1 = none
    int final_label;   // per-pixel label after the labeling pass; -1 = none
    uint layer_iters;  // bits 0-7: 0-based index of that layer + 1 (0 = none); bits 8-31: the
                       // iterative-search steps over every layer tried (the paper's c_total)
};

layout(std430, binding = B_HITS) buffer Hits { Hit hits[]; };

uint layer_iters(int layer, int iters) { return uint(layer + 1) | (uint(iters) << 8); }
int hit_layer(Hit h) { return int(h.layer_iters & 0xFFu) - 1; }
int hit_iters(Hit h) { return int(h.layer_iters >> 8); }

#ifdef NORMALS_BUFFER
// The unit world-space normal facing the render camera, 3 floats a pixel (0 = background), written
// by the passes that find the surface when u_normals is set (a frame that is read back) in a
// program built with NORMALS 1 (the default; NORMALS 0 leaves their code out: fewer registers).
#ifndef NORMALS
#define NORMALS 1
#endif
layout(std430, binding = B_NORMALS) writeonly buffer Normals { float normals[]; };
uniform int u_normals;

void write_normal(uint pix, vec3 n) {
    if (NORMALS == 0 || u_normals == 0) return;
    normals[3u * pix] = n.x;
    normals[3u * pix + 1u] = n.y;
    normals[3u * pix + 2u] = n.z;
}
#endif

// The ray of the render camera through pixel centre uv (pixels, corner origin) in camera space,
// scaled so that the point at parameter s has camera z = s: the splat passes' own
// (splat_depth_common.glsl), so a surface point and a splat hit at one pixel share the ray.
vec3 camera_ray(vec2 uv) {
    return splat_ray(uv);
}
