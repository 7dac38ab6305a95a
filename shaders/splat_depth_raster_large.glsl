// Depth map from oriented circular splats, raster path, second program: the discs too big for a
// point sprite (see splat_depth_raster), drawn as one screen-space quad over the disc's pixel box
// emitted by a geometry shader. Same fragment stage, so the same per-pixel test; WITH_LABEL as there.
#include "splat_depth_common.glsl"

#ifndef WITH_LABEL
#define WITH_LABEL 0
#endif

#if defined VERTEX_SHADER

in vec3 in_position;
in vec3 in_normal;
in float in_radius;

flat out vec3 v_pc;
flat out vec3 v_nc;
flat out float v_r;
#if WITH_LABEL
in int in_label;
flat out int v_label;
#endif

void main() {
    Splat s = splat_to_camera(in_position, in_normal, in_radius);
    v_pc = s.pc;
    v_nc = s.nc;
    v_r = s.r;
#if WITH_LABEL
    v_label = in_label;
#endif
    gl_Position = vec4(0.0, 0.0, 0.0, 1.0);
}

#elif defined GEOMETRY_SHADER

layout(points) in;
layout(triangle_strip, max_vertices = 4) out;

uniform float u_max_point_size;

flat in vec3 v_pc[];
flat in vec3 v_nc[];
flat in float v_r[];

flat out vec3 f_pc;
flat out vec3 f_nc;
flat out float f_r;
#if WITH_LABEL
flat in int v_label[];
flat out int f_label;
#endif

void main() {
    Splat s = Splat(v_pc[0], v_nc[0], v_r[0]);
    ivec4 box = splat_pixel_box(s);
    float size = float(max(box.z - box.x, box.w - box.y) + 2);
    // a 2-pixel overlap with the sprite program's test: rounding differences between the two
    // programs may draw a disc twice (harmless under the z-buffer and the MIN blend) but never drop it
    if (box.x > box.z || box.y > box.w || size <= u_max_point_size - 2.0) return;
    vec2 lo = 2.0 * vec2(box.xy) / vec2(u_size) - 1.0;
    vec2 hi = 2.0 * vec2(box.zw + 1) / vec2(u_size) - 1.0;
    vec2 corners[4] = vec2[4](vec2(lo.x, lo.y), vec2(hi.x, lo.y), vec2(lo.x, hi.y), vec2(hi.x, hi.y));
    for (int c = 0; c < 4; ++c) {
        f_pc = s.pc;
        f_nc = s.nc;
        f_r = s.r;
#if WITH_LABEL
        f_label = v_label[0];
#endif
        gl_Position = vec4(corners[c], 0.0, 1.0);
        EmitVertex();
    }
    EndPrimitive();
}

#elif defined FRAGMENT_SHADER

#if WITH_LABEL
#include "dmrt_visibility_fragment.glsl"
#else
#include "splat_depth_fragment.glsl"
#endif

#endif
