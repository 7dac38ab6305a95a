// Screen-space leveling, pass 3 of 3: every textured pixel's colour times its photo's gain (solved
// on the GPU by dmrt_leveling_solve.glsl from the seam sums of dmrt_leveling_seams.glsl).
#include "splat_depth_common.glsl"
#include "dmrt_frame.glsl"

#if defined COMPUTE_SHADER

layout(local_size_x = 64) in;

layout(std430, binding = B_COLORS) buffer Colors { uint colors[]; };
layout(std430, binding = B_GAINS) readonly buffer Gains { vec4 gains[]; };  // per photo: RGB gain, 1

uniform int u_count;

void main() {
    // strided: GL guarantees 65535 workgroups, fewer than a 4K frame's pixels / 64
    for (uint pix = gl_GlobalInvocationID.x; pix < uint(u_count); pix += gl_NumWorkGroups.x * 64u) {
        int l = hits[pix].final_label;
        if (l < 0 || colors[pix] == 0u) continue;
        vec4 c = unpackUnorm4x8(colors[pix]);
        colors[pix] = packUnorm4x8(vec4(clamp(c.rgb * gains[l].rgb, 0.0, 1.0), 1.0));
    }
}

#endif
