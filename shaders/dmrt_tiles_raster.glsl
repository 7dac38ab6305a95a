// Tile-binned visibility stage, raster (dmrt/runtime/tiles.py): all k label layers of one TILE x TILE
// screen tile per workgroup, one invocation per pixel, the per-pixel state in registers.
//
// Depth peeling defines layer 1 as the nearest hit at the pixel centre and layer i+1 as the nearest
// hit behind layer i with another label (ties in depth to the smallest label; the order is that of
// (depth bits, label)). Each layer is therefore a minimum over the pixel's hits under a filter set by
// the layer before, which needs no order among the discs: the workgroup walks its tile's list once
// per layer and each invocation keeps the smallest (depth bits, label) that passes, exactly what
// compute peeling's atomicMin per layer computes, with the same ray-disc test (splat_depth_at) and
// so the same bits, but in registers.
//
// The walk's cost is in the loads and the tests, so:
// 1. A list of up to BATCH discs is loaded into shared memory once (camera-space centre, normal,
//    radius, label, pixel box) and serves every layer; a longer one is walked BATCH discs at a
//    time, loaded again for each layer.
// 2. The first walk tests every disc against the pixel box and the disc; each invocation notes
//    which of the first MASK_DISCS (256) discs hit its pixel (a bit mask in eight registers), and
//    the later walks test only those (findLSB), dropping the hits at or in front of the last layer
//    (they can never pass a filter again). Most tiles hold fewer discs (paper preset: ~180 a tile
//    at 1280x720, ~63 at 3840x2160), so after the first layer a pixel visits only its own hits.
// 3. A pixel without a hit for layer i has none for the layers after it; the workgroup stops when
//    none of its pixels found a layer (a shared flag per walk).
// Every layer of every pixel is written once (empty ones as EMPTY_BITS / EMPTY_LABEL), so the layer
// buffers need no clearing.
//
// Buffers (binding: layout):
//   B_PROXIES       n x 8 floats (dmrt_tiles_common.glsl)
//   B_LAYER_DEPTH   k x h x w uint: float bits of camera z, EMPTY_BITS = none (row 0 at the top)
//   B_LAYER_LABEL   k x h x w int: label, EMPTY_LABEL = none
//   B_TILE_ENTRIES  uint[capacity]: proxy indices, tile after tile (dmrt_tiles_bin.glsl)
//   B_TILE_OFFSETS  uint[tiles + 1] (dmrt_tiles_scan.glsl)
//   B_TILE_MASKS    h x w x 2 uvec4: the first walk's hit bits of discs 0-255, written for pixels of
//                   tiles of up to BATCH discs (HIT_MASKS: read by dmrt_tiles_labeling.glsl)
#include "dmrt_tiles_common.glsl"

#if defined COMPUTE_SHADER

#ifndef BATCH
#define BATCH 512  // discs in shared memory at once: 40 bytes each
#endif
#define THREADS (TILE * TILE)

layout(local_size_x = TILE, local_size_y = TILE) in;

layout(std430, binding = B_LAYER_DEPTH) writeonly buffer LayerDepth { uint layer_depth[]; };
layout(std430, binding = B_LAYER_LABEL) writeonly buffer LayerLabel { int layer_label[]; };
layout(std430, binding = B_TILE_ENTRIES) readonly buffer Entries { uint entries[]; };
layout(std430, binding = B_TILE_OFFSETS) readonly buffer Offsets { uint offsets[]; };
#if HIT_MASKS
layout(std430, binding = B_TILE_MASKS) writeonly buffer Masks { uvec4 masks[]; };  // 2 per pixel: g_lo, g_hi
#endif

uniform uint u_capacity;  // entries the buffer holds (a slice past it was cut short)
uniform int u_layers;     // k

shared vec4 s_pr[BATCH];     // camera-space centre (m), radius (m)
shared vec4 s_nl[BATCH];     // unit normal, label (uint bits)
shared uvec2 s_box[BATCH];   // pixel box: col0 | row0 << 16, col1 | row1 << 16
shared uint s_found[3];      // "some pixel found this layer", one per walk, rotating

// per-invocation state
uvec2 g_px;               // the pixel
vec2 g_uv;                // its centre
uint g_prev_d, g_prev_l;  // the last layer's depth bits and label (label ~0u before the first)
uint g_best_d, g_best_l;  // the nearest hit that passes the filter so far
uint g_count;             // discs in the tile's list
// The hit masks of discs 0-127 and 128-255, one word of 32 discs a component. Written as vectors
// filled component by component with constant indices: an array indexed by a loop counter may be
// kept in local memory (dmrt_photos.glsl's snap_try says more).
uvec4 g_lo, g_hi;

void load_batch(uint first, uint n) {
    for (uint i = gl_LocalInvocationIndex; i < n; i += uint(THREADS)) {
        int label;
        Splat s = load_proxy(entries[first + i], label);
        ivec4 box = splat_pixel_box(s);
        s_pr[i] = vec4(s.pc, s.r);
        s_nl[i] = vec4(s.nc, intBitsToFloat(label));
        s_box[i] = uvec2(uint(box.x) | (uint(box.y) << 16), uint(box.z) | (uint(box.w) << 16));
    }
}

// Depth bits of disc j's hit at the pixel, 0 for none.
uint hit_bits(uint j) {
    Splat s;
    s.pc = s_pr[j].xyz;
    s.r = s_pr[j].w;
    s.nc = s_nl[j].xyz;
    float z = splat_depth_at(s, g_uv);
    return z > 0.0 ? floatBitsToUint(z) : 0u;
}

// The peeling filter and the minimum: a hit behind the last layer with another label.
void consider(uint d, uint j) {
    uint l = floatBitsToUint(s_nl[j].w);
    if (d > g_prev_d && l != g_prev_l && (d < g_best_d || (d == g_best_d && l < g_best_l))) {
        g_best_d = d;
        g_best_l = l;
    }
}

// Test discs [from, to) of the batch in shared memory; the bits of the hits, from bit 0 for disc
// `from` (meaningful for up to 32 discs).
uint walk(uint from, uint to) {
    uint mask = 0u;
    for (uint j = from; j < to; ++j) {
        uvec2 b = s_box[j];
        if (g_px.x < (b.x & 0xFFFFu) || g_px.x > (b.y & 0xFFFFu) || g_px.y < (b.x >> 16) || g_px.y > (b.y >> 16))
            continue;
        uint d = hit_bits(j);
        if (d == 0u) continue;
        mask |= 1u << ((j - from) & 31u);
        consider(d, j);
    }
    return mask;
}

// The first walk over the 32 discs from `base`: their hit mask.
uint first_word(uint base) {
    return base < g_count ? walk(base, min(g_count, base + 32u)) : 0u;
}

// A later walk over the remembered hits of a word; those at or in front of the last layer leave
// the mask for good.
uint again(uint word, uint base) {
    uint m = word;
    while (m != 0u) {
        int b = findLSB(m);
        m &= m - 1u;
        uint j = base + uint(b);
        uint d = hit_bits(j);
        if (d <= g_prev_d) word &= ~(1u << uint(b));
        else consider(d, j);
    }
    return word;
}

void main() {
    uint lid = gl_LocalInvocationIndex;
    uint tile = gl_WorkGroupID.y * uint(u_tiles.x) + gl_WorkGroupID.x;
    ivec2 p = ivec2(gl_WorkGroupID.xy) * TILE + ivec2(gl_LocalInvocationID.xy);
    bool searching = p.x < u_size.x && p.y < u_size.y;  // still finding layers
    uint npix = uint(u_size.x * u_size.y), pix = searching ? uint(p.y * u_size.x + p.x) : 0u;
    g_px = uvec2(p);
    g_uv = vec2(p) + 0.5;  // the pixel centre, as in every splat path
    g_prev_d = 0u;
    g_prev_l = ~0u;
    uint found = 0u;

    uint off = offsets[tile];
    uint count = offsets[tile + 1u] - off;
    count = min(count, u_capacity - min(off, u_capacity));  // entries past the buffer were dropped
    g_count = count;
    bool cached = count <= uint(BATCH);
    if (lid < 3u) s_found[lid] = 0u;
    if (cached) load_batch(off, count);
    memoryBarrierShared();
    barrier();

    for (uint layer = 0u; layer < uint(u_layers); ++layer) {
        g_best_d = EMPTY_BITS;
        g_best_l = EMPTY_BITS;
        if (cached) {
            if (searching && layer == 0u) {
                g_lo = uvec4(first_word(0u), first_word(32u), first_word(64u), first_word(96u));
                g_hi = uvec4(first_word(128u), first_word(160u), first_word(192u), first_word(224u));
#if HIT_MASKS
                masks[2u * pix] = g_lo;  // for the labeling pass (dmrt_tiles_labeling.glsl)
                masks[2u * pix + 1u] = g_hi;
#endif
            } else if (searching) {
                g_lo = uvec4(again(g_lo.x, 0u), again(g_lo.y, 32u), again(g_lo.z, 64u), again(g_lo.w, 96u));
                g_hi = uvec4(again(g_hi.x, 128u), again(g_hi.y, 160u), again(g_hi.z, 192u), again(g_hi.w, 224u));
            }
            if (searching) walk(min(count, uint(MASK_DISCS)), count);
        } else {
            for (uint sb = 0u; sb < count; sb += uint(BATCH)) {
                uint nb = min(uint(BATCH), count - sb);
                memoryBarrierShared();
                barrier();  // the batch before is no longer read
                load_batch(off + sb, nb);
                memoryBarrierShared();
                barrier();
                if (searching) walk(0u, nb);
            }
        }
        // the flag reset here was last read two walks ago, before a barrier every invocation has
        // passed since
        uint slot = layer % 3u;
        if (lid == 0u) s_found[(layer + 1u) % 3u] = 0u;
        if (searching && g_best_d != EMPTY_BITS) {
            layer_depth[layer * npix + pix] = g_best_d;
            layer_label[layer * npix + pix] = int(g_best_l);
            g_prev_d = g_best_d;
            g_prev_l = g_best_l;
            found = layer + 1u;
            s_found[slot] = 1u;
        } else {
            searching = false;
        }
        memoryBarrierShared();
        barrier();
        if (s_found[slot] == 0u) break;
    }

    if (p.x < u_size.x && p.y < u_size.y) {
        for (uint i = found; i < uint(u_layers); ++i) {
            layer_depth[i * npix + pix] = EMPTY_BITS;
            layer_label[i * npix + pix] = EMPTY_LABEL;
        }
    }
}

#endif
