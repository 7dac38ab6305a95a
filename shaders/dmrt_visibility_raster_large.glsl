// DMRT visibility stage, raster path, second program: discs too big for a point sprite (see
// dmrt_visibility_raster), drawn as one screen-space quad over the disc's pixel box emitted by a
// geometry shader; the same fragment stage.
#include "splat_depth_common.glsl"

#if defined VERTEX_SHADER

in vec3 in_position;
in float in_radius;
in vec3 in_normal;
in int in_label;

flat out vec3 v_pc;
flat out vec3 v_nc;
flat out float v_r;
flat out int v_label;

void main() {
    Splat s = splat_to_camera(in_position, in_normal, in_radius);
    v_pc = s.pc;
    v_nc = s.nc;
    v_r = s.r;
    v_label = in_label;
    gl_Position = vec4(0.0, 0.0, 0.0, 1.0);
}

#elif defined GEOMETRY_SHADER

layout(points) in;
layout(triangle_strip, max_vertices = 4) out;

uniform float u_max_point_size;

flat in vec3 v_pc[];
flat in vec3 v_nc[];
flat in float v_r[];
flat in int v_label[];

flat out vec3 f_pc;
flat out vec3 f_nc;
flat out float f_r;
flat out int f_label;

void main() {
    Splat s = Splat(v_pc[0], v_nc[0], v_r[0]);
    ivec4 box = splat_pixel_box(s);
    float size = float(max(box.z - box.x, box.w - box.y) + 2);
    // exactly the discs the sprite program dropped (same box, same arithmetic): each disc is drawn
    // once, which the label resolve's equality test does not need but costs nothing
    if (box.x > box.z || box.y > box.w || size <= u_max_point_size) return;
    vec2 lo = 2.0 * vec2(box.xy) / vec2(u_size) - 1.0;
    vec2 hi = 2.0 * vec2(box.zw + 1) / vec2(u_size) - 1.0;
    vec2 corners[4] = vec2[4](vec2(lo.x, lo.y), vec2(hi.x, lo.y), vec2(lo.x, hi.y), vec2(hi.x, hi.y));
    for (int c = 0; c < 4; ++c) {
        f_pc = s.pc;
        f_nc = s.nc;
        f_r = s.r;
        f_label = v_label[0];
        gl_Position = vec4(corners[c], 0.0, 1.0);
        EmitVertex();
    }
    EndPrimitive();
}

#elif defined FRAGMENT_SHADER

#include "dmrt_visibility_fragment.glsl"

#endif
