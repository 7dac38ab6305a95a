// Depth map from oriented circular splats, raster path (paper Section 4.1): GL_POINTS whose
// point sprite covers the disc's pixel box, a per-fragment ray-disc test, z-buffering.
// The sprite is centred on the box clipped to the depth map, not on the projected centre: a point
// whose centre leaves the view volume is clipped whole, which would drop discs at the border.
// Discs whose sprite would exceed the implementation's largest point size (255 px on llvmpipe) are
// left to splat_depth_raster_large (quads from a geometry shader).
// WITH_LABEL 1: the DMRT visibility stage's raster path (dmrt/runtime/visibility.py): each disc carries its
// label, and the fragment stage is dmrt_visibility_fragment.glsl (ray-disc and peeling tests).
#include "splat_depth_common.glsl"

#ifndef WITH_LABEL
#define WITH_LABEL 0
#endif

#if defined VERTEX_SHADER

in vec3 in_position;  // metres, scene-origin-relative
in vec3 in_normal;
in float in_radius;   // metres

uniform float u_max_point_size;

flat out vec3 f_pc;
flat out vec3 f_nc;
flat out float f_r;
#if WITH_LABEL
in int in_label;
flat out int f_label;
#endif

void main() {
    Splat s = splat_to_camera(in_position, in_normal, in_radius);
    f_pc = s.pc;
    f_nc = s.nc;
    f_r = s.r;
#if WITH_LABEL
    f_label = in_label;
#endif
    ivec4 box = splat_pixel_box(s);
    // +1: a sprite edge may fall exactly on a pixel centre; one more pixel is tested and discarded
    float size = float(max(box.z - box.x, box.w - box.y) + 2);
    if (box.x > box.z || box.y > box.w || size > u_max_point_size) {
        gl_Position = vec4(2.0, 2.0, 2.0, 1.0);  // outside the clip volume: no fragments
        gl_PointSize = 1.0;
        return;
    }
    vec2 centre = 0.5 * (vec2(box.xy) + vec2(box.zw + 1));  // window (= pixel) coordinates
    gl_Position = vec4(2.0 * centre / vec2(u_size) - 1.0, 0.0, 1.0);
    gl_PointSize = size;
}

#elif defined FRAGMENT_SHADER

#if WITH_LABEL
#include "dmrt_visibility_fragment.glsl"
#else
#include "splat_depth_fragment.glsl"
#endif

#endif
