// DMT: the stitching pass's render targets into the per-pixel Hit records of dmrt_frame.glsl, so
// that DMRT's image-management histogram (dmrt_label_histogram) and texturing pass
// (dmrt_texturing) run unchanged on DMT frames. Hit.label = the winning depth map, layer 0,
// Hit.final_label = the label of that map's texel; background: depth 0, labels -1.
#include "splat_depth_common.glsl"
#define NORMALS_BUFFER
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
    bool surface = s.x > 0.0;
    Hit hit = Hit(surface ? s.x : 0.0, surface ? int(ids.x) : -1, surface ? int(ids.y) : -1,
                  layer_iters(surface ? 0 : -1, 0));
    write_normal(uint(p.y * u_size.x + p.x), surface ? s.yzw : vec3(0.0));
    hits[p.y * u_size.x + p.x] = hit;
}

#endif
