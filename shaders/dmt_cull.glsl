// DMT view-frustum culling: one thread per depth map tests its world bounding box against the
// render camera's frustum and writes the map's multi-draw-indirect command for shaders/dmt_mesh.glsl
// (count 0 = culled). A box is culled when its 8 corners all lie outside one frustum plane
// (w +- x >= 0 etc. in clip space: linear in world space, so the whole box is outside); this is
// conservative, as baselines/dmt/geometry.py's frustum_culled, which the tests compare.
#include "dmrt_photos.glsl"

#if defined COMPUTE_SHADER

layout(local_size_x = 64) in;

// per map: (min.xyz, 1 = has surface), (max.xyz, 0); origin-relative metres
layout(std430, binding = B_DMT_BOXES) readonly buffer Boxes { vec4 boxes[]; };
// DrawArraysIndirectCommand padded to moderngl's 20-byte stride
struct Command { uint count; uint instances; uint first; uint base_instance; uint pad; };
layout(std430, binding = B_DMT_COMMANDS) writeonly buffer Commands { Command commands[]; };
layout(std430, binding = B_DMT_STATS) buffer Stats { uint culled; uint triangles; };

uniform mat4 u_vp;
uniform int u_count;           // depth maps
uniform int u_maps_per_draw;   // maps per multi-draw (gl_VertexID range: 2^31)
uniform int u_verts_per_map;

void main() {
    int i = int(gl_GlobalInvocationID.x);
    if (i >= u_count) return;
    vec4 lo = boxes[2 * i], hi = boxes[2 * i + 1];
    bool cull = lo.w == 0.0;
    bvec3 all_pos = bvec3(true), all_neg = bvec3(true);  // every corner beyond +plane / -plane
    for (int k = 0; k < 8; ++k) {
        vec3 p = vec3((k & 1) != 0 ? hi.x : lo.x, (k & 2) != 0 ? hi.y : lo.y, (k & 4) != 0 ? hi.z : lo.z);
        vec4 c = u_vp * vec4(p, 1.0);
        all_pos = bvec3(all_pos.x && c.x > c.w, all_pos.y && c.y > c.w, all_pos.z && c.z > c.w);
        all_neg = bvec3(all_neg.x && c.x < -c.w, all_neg.y && c.y < -c.w, all_neg.z && c.z < -c.w);
    }
    cull = cull || any(all_pos) || any(all_neg);
    Photo ph = photos[i];
    uint verts = uint(6 * (int(ph.size.x) - 1) * (int(ph.size.y) - 1));
    Command cmd;
    cmd.count = cull ? 0u : verts;
    cmd.instances = 1u;
    cmd.first = uint((i % u_maps_per_draw) * u_verts_per_map);
    cmd.base_instance = 0u;
    cmd.pad = 0u;
    commands[i] = cmd;
    if (cull) atomicAdd(culled, 1u);
    else atomicAdd(triangles, verts / 3u);
}

#endif
