// The viewer's display pass (dmrt/app/viewer.py): one buffer of a rendered frame mapped to colours on a
// full-screen triangle, with the text overlay blended on top.
//
// Textures hold the frame in image order (row 0 = the top of the image, as every frame array), so
// the fragment's GL y (0 at the bottom) is flipped when fetching. Texels are fetched, not
// filtered: at the frame's own size the display is exact (the viewer's tests compare it byte for
// byte with the frame), and a window of another size shows the frame scaled with nearest pixels.
//
// MODE_* come from dmrt.app.viewer.BUFFERS (one place for the numbering).

#if defined VERTEX_SHADER

out vec2 v_uv;

void main() {
    // a triangle covering the viewport: (0,0), (2,0), (0,2) in uv; no vertex buffer needed
    vec2 p = vec2(float((gl_VertexID << 1) & 2), float(gl_VertexID & 2));
    v_uv = p;
    gl_Position = vec4(2.0 * p - 1.0, 0.0, 1.0);
}

#elif defined FRAGMENT_SHADER

in vec2 v_uv;
out vec4 f_color;

uniform int u_mode;
uniform sampler2D u_color;    // RGBA8 frame colour (alpha unused)
uniform sampler2D u_scalar;   // R32F: depth (MODE_DEPTH) or iterations (MODE_ITERATIONS)
uniform isampler2D u_index;   // R32I: labels (MODE_LABEL, MODE_SPLAT_LABEL) or layer_used (MODE_HOLES)
uniform vec2 u_range;         // depth: (near, far) of the frame's surface; iterations: (0, max)
uniform sampler2D u_overlay;  // RGBA8 text box, alpha = coverage (not premultiplied)
uniform int u_show_overlay;

// Label -> colour, mirrored by dmrt.io.frames.label_colors (numpy): hue along the golden-ratio
// sequence (neighbouring photo indices get far-apart hues; any few labels get distinct ones),
// value varied by a second low-discrepancy sequence (never below 0.7); -1 (no label) is black.
vec3 label_color(int label) {
    if (label < 0) return vec3(0.0);
    float h = fract(0.5 + float(label) * 0.6180339887);
    float v = 0.7 + 0.3 * fract(float(label) * 0.7548776662);
    vec3 rgb = clamp(abs(mod(h * 6.0 + vec3(0.0, 4.0, 2.0), 6.0) - 3.0) - 1.0, 0.0, 1.0);
    return v * mix(vec3(1.0), rgb, 0.75);
}

// black -> red -> yellow -> white
vec3 heat(float t) {
    t = clamp(t, 0.0, 1.0);
    return clamp(vec3(3.0 * t, 3.0 * t - 1.0, 3.0 * t - 2.0), 0.0, 1.0);
}

void main() {
    ivec2 size = textureSize(u_color, 0);
    vec2 st = vec2(v_uv.x, 1.0 - v_uv.y);  // image order: row 0 at the top
    ivec2 ij = clamp(ivec2(st * vec2(size)), ivec2(0), size - 1);
    vec3 rgb;
    if (u_mode == MODE_COLOR) {
        rgb = texelFetch(u_color, ij, 0).rgb;
    } else if (u_mode == MODE_DEPTH) {
        // near surfaces bright, far ones dim, background black
        float z = texelFetch(u_scalar, ij, 0).r;
        float t = (z - u_range.x) / max(u_range.y - u_range.x, 1e-6);
        rgb = z > 0.0 ? vec3(1.0 - 0.8 * clamp(t, 0.0, 1.0)) : vec3(0.0);
    } else if (u_mode == MODE_LABEL || u_mode == MODE_SPLAT_LABEL) {
        rgb = label_color(texelFetch(u_index, ij, 0).r);
    } else if (u_mode == MODE_ITERATIONS) {
        rgb = heat(texelFetch(u_scalar, ij, 0).r / max(u_range.y, 1.0));
    } else {  // MODE_HOLES: holes pure red over the colour in grey (grey is never pure red)
        vec3 c = texelFetch(u_color, ij, 0).rgb;
        float grey = 0.8 * dot(c, vec3(0.299, 0.587, 0.114));
        rgb = texelFetch(u_index, ij, 0).r < 0 ? vec3(1.0, 0.0, 0.0) : vec3(grey);
    }
    if (u_show_overlay != 0) {
        vec4 text = texelFetch(u_overlay, clamp(ivec2(st * vec2(textureSize(u_overlay, 0))), ivec2(0),
                                                textureSize(u_overlay, 0) - 1), 0);
        rgb = mix(rgb, text.rgb, text.a);
    }
    f_color = vec4(rgb, 1.0);
}

#endif
