// DMRT visibility stage, raster path (paper Section 5.1.1): the proxies as GL_POINTS whose sprite
// covers the disc's pixel box, the per-fragment ray-disc and peeling tests of
// dmrt_visibility_fragment.glsl. Discs whose sprite would exceed the largest point size are left to
// dmrt_visibility_raster_large (quads from a geometry shader). See dmrt/visibility.py.
#include "splat_depth_common.glsl"

#if defined VERTEX_SHADER

in vec3 in_position;  // metres, scene-origin-relative
in float in_radius;   // metres
in vec3 in_normal;
in int in_label;

uniform float u_max_point_size;

flat out vec3 f_pc;
flat out vec3 f_nc;
flat out float f_r;
flat out int f_label;

void main() {
    Splat s = splat_to_camera(in_position, in_normal, in_radius);
    f_pc = s.pc;
    f_nc = s.nc;
    f_r = s.r;
    f_label = in_label;
    ivec4 box = splat_pixel_box(s);
    float size = float(max(box.z - box.x, box.w - box.y) + 2);
    if (box.x > box.z || box.y > box.w || size > u_max_point_size) {
        gl_Position = vec4(2.0, 2.0, 2.0, 1.0);  // outside the clip volume: no fragments
        gl_PointSize = 1.0;
        return;
    }
    vec2 centre = 0.5 * (vec2(box.xy) + vec2(box.zw + 1));
    gl_Position = vec4(2.0 * centre / vec2(u_size) - 1.0, 0.0, 1.0);
    gl_PointSize = size;
}

#elif defined FRAGMENT_SHADER

#include "dmrt_visibility_fragment.glsl"

#endif
