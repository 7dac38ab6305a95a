// DMT: the stitching pass's render targets into the per-pixel Hit records of dmrt_frame.glsl, so
// that DMRT's image-management histogram (dmrt_label_histogram) and texturing pass
// (dmrt_texturing) run unchanged on DMT frames. Hit.label = the winning depth map, Hit.layer = 0,
// Hit.final_label = the label of that map's texel; background: depth 0, labels -1.
#include "splat_depth_common.glsl"
#include "dmrt_frame.glsl"

#if defined COMPUTE_SHADER

layout(local_size_x = 8, local_size_y = 8) in;

uniform sampler2D u_surface;  // camera z (0 = background), world normal
uniform sampler2D u_ids;      // depth map, label

void main() {
    ivec2 p = ivec2(gl_GlobalInvocationID.xy);
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    vec4 s = texelFetch(u_surface, p, 0);
    vec4 ids = texelFetch(u_ids, p, 0);
    Hit hit;
    bool surface = s.x > 0.0;
    hit.depth = surface ? s.x : 0.0;
    hit.label = surface ? int(ids.x) : -1;
    hit.layer = surface ? 0 : -1;
    hit.iters = 0;
    vec3 n = surface ? s.yzw : vec3(0.0);
    hit.nx = n.x;
    hit.ny = n.y;
    hit.nz = n.z;
    hit.final_label = surface ? int(ids.y) : -1;
    hits[p.y * u_size.x + p.x] = hit;
}

#endif
