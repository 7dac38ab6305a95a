// Screen-space leveling, pass 2: every textured pixel's colour times its photo's gain (solved on
// the CPU from the seam sums of dmrt_leveling_seams.glsl, dmrt.runtime.leveling).
#include "splat_depth_common.glsl"
#include "dmrt_frame.glsl"

#if defined COMPUTE_SHADER

layout(local_size_x = 64) in;

layout(std430, binding = B_COLORS) buffer Colors { uint colors[]; };
layout(std430, binding = B_GAINS) readonly buffer Gains { vec4 gains[]; };  // per photo: RGB gain, unused

uniform int u_count;

void main() {
    uint pix = gl_GlobalInvocationID.x;
    if (pix >= uint(u_count)) return;
    int l = hits[pix].final_label;
    if (l < 0 || colors[pix] == 0u) return;
    vec4 c = unpackUnorm4x8(colors[pix]);
    colors[pix] = packUnorm4x8(vec4(clamp(c.rgb * gains[l].rgb, 0.0, 1.0), 1.0));
}

#endif
