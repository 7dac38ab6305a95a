// The synthetic scenes' matte photographs on the GPU (bench/scenes/glphoto.py): the twin of
// bench.scenes.synthetic.Studio.photograph with specular 0. The rasterizer only picks each pixel's
// triangle (gl_PrimitiveID = face index); the fragment stage intersects the pixel-centre ray with the
// triangle's plane, as Embree's ray does, writes that camera z as a linear depth (a DEPTH_COMPONENT32F
// buffer keeps float32's relative precision at every distance) and returns the unrounded colour
// albedo x shade, float32, which numpy box-filters, scales by the gain and rounds as Studio does.
// Per-face values that numpy computes in float64 (the dominant axis, the shade of each side) come
// precomputed, so that the only float32-vs-float64 differences are the hit point's.

#if defined VERTEX_SHADER

in vec3 in_position;  // scene-local metres
uniform mat4 u_view_projection;

void main() {
    gl_Position = u_view_projection * vec4(in_position, 1.0);
}

#elif defined FRAGMENT_SHADER

struct Face {
    vec4 plane;         // unit normal (face_normals), n . v0: the plane n . p = w, scene-local metres
    int material;       // layer of u_textures
    int axis;           // argmax |n| (first max): 0 maps (y, z), 1 (x, z), 2 (x, y)
    float shade_front;  // shade(n): the camera on the normal's side
    float shade_back;   // shade(-n)
};

layout(std430, binding = B_SYNTH_FACES) readonly buffer Faces { Face faces[]; };

uniform sampler2DArray u_textures;              // every material's albedo, RGB float 0..1, from texel (0, 0)
uniform ivec2 u_texture_size[N_MATERIALS];      // each layer's used width, height
uniform float u_texels_per_metre[N_MATERIALS];  // max(h, w) / tile
uniform mat3 u_camera_to_world;                 // R^T
uniform vec3 u_center;                          // scene-local metres
uniform vec4 u_intrinsics;                      // fx, fy, cx, cy at the rendered size, pixels
uniform float u_far;                            // camera z of the farthest scene point, metres

out vec4 f_color;

// x mod m in 0..m-1 for any sign of x (GLSL's % is undefined for negative operands)
int positive_mod(int x, int m) {
    int r = x - m * int(floor(float(x) / float(m)));
    return r < 0 ? r + m : (r >= m ? r - m : r);
}

void main() {
    Face f = faces[gl_PrimitiveID];
    // Camera.pixel_rays: gl_FragCoord.xy is the pixel centre (j + 0.5, i + 0.5), image row 0 at y = 0
    vec2 xy = (gl_FragCoord.xy - u_intrinsics.zw) / u_intrinsics.xy;
    vec3 dir = u_camera_to_world * vec3(xy, 1.0);  // a point at s along it has camera z = s
    float nd = dot(f.plane.xyz, dir);
    float s = (f.plane.w - dot(f.plane.xyz, u_center)) / nd;
    if (!(s > 0.0 && s < u_far)) {
        s = 1.0 / gl_FragCoord.w;  // grazing: the interpolated camera z
    }
    gl_FragDepth = clamp(s / u_far, 0.0, 1.0);
    vec3 p = u_center + s * dir;
    vec2 uv = f.axis == 0 ? p.yz : (f.axis == 1 ? p.xz : p.xy);
    ivec2 size = u_texture_size[f.material];
    float scale = u_texels_per_metre[f.material];
    int col = positive_mod(int(floor(uv.x * scale)), size.x);
    int row = positive_mod(-int(floor(uv.y * scale)) - 1, size.y);  // image up = world up
    vec3 albedo = texelFetch(u_textures, ivec3(col, row, f.material), 0).rgb;
    // Studio flips the normal to face the camera when n . dir > 0
    f_color = vec4(albedo * (nd > 0.0 ? f.shade_back : f.shade_front), 1.0);
}

#endif
