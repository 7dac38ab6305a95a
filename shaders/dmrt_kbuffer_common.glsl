// The k-buffer of dmrt_visibility_kbuffer.glsl and dmrt_kbuffer_resolve.glsl: h x w pixels x SLOTS
// keys, a pixel's slots contiguous, each key (float bits of camera z with the low LABEL_BITS
// cleared) | label; EMPTY_BITS = empty. Included; no #version.
#ifndef SLOTS
#define SLOTS 16
#endif
#ifndef LABEL_BITS
#define LABEL_BITS 8
#endif

layout(std430, binding = B_KBUFFER) buffer KBuffer { uint kbuf[]; };
