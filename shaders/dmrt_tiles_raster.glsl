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
//    squared radius, label, pixel box) and serves every walk; a longer one is walked BATCH discs
//    at a time, loaded again for each walk.
// 2. The first walk tests the discs whose box holds the pixel (SPARSE_WALK says how), and each
//    invocation keeps its TOP nearest hits sorted by depth in registers. The layers are the
//    peeling rule applied to the pixel's hits in that order (a hit is the next layer if it lies
//    behind the last one with another label; one that fails can never pass later, as every later
//    layer lies at or behind it), so the sorted prefix yields the pixel's first layers exactly:
//    all k of them when the rule finds k in it (most pixels: the labels of the maps that see a
//    surface interleave in depth), or all there are when the pixel has at most TOP hits; with no
//    two of equal depth among them.
// 3. Only the other pixels walk again, once per missing layer, each keeping the smallest
//    (depth bits, label) that passes the filter. The first walk also noted which of the tile's
//    first MASK_DISCS (256) discs hit the pixel (a bit mask in eight registers); these walks
//    test only those (findLSB), dropping the hits at or in front of the last layer (they can never
//    pass a filter again). Most tiles hold fewer discs (paper preset: ~180 a tile at 1280x720, ~63
//    at 3840x2160), so a pixel then visits only its own hits. The workgroup stops when none of its
//    pixels needs another walk (a shared flag per walk).
// Every layer of every pixel is written once (empty ones as EMPTY_BITS / EMPTY_LABEL), so the layer
// buffers need no clearing.
//
// Buffers (binding: layout):
//   B_PROXIES       n x 8 floats (dmrt_tiles_common.glsl)
//   B_LAYER_DEPTH   k x h x w uint: float bits of camera z, EMPTY_BITS = none (row 0 at the top)
//   B_LAYER_LABEL   k x h x w int: label, EMPTY_LABEL = none
//   B_TILE_ENTRIES  uvec2[capacity]: proxy index, box_bits in the tile; tile after tile (dmrt_tiles_bin.glsl)
//   B_TILE_OFFSETS  uint[tiles + 1] (dmrt_tiles_scan.glsl)
//   B_TILE_MASKS    h x w x 2 uvec4: the first walk's hit bits of discs 0-255, written for pixels of
//                   tiles of up to BATCH discs, the second uvec4 only for lists of more than 128
//                   (masks_second_half; HIT_MASKS: read by dmrt_tiles_labeling.glsl)
#include "dmrt_tiles_common.glsl"

#if defined COMPUTE_SHADER

#ifndef BATCH
#define BATCH 288  // discs in shared memory at once: 36 bytes each (TileVisibility's batch says why)
#endif
#define THREADS (TILE * TILE)
#ifndef TOP
#define TOP 12  // nearest hits a pixel keeps sorted during the first walk: 4, 8, 12 or 16
#endif
#if TOP != 4 && TOP != 8 && TOP != 12 && TOP != 16
#error "TOP must be 4, 8, 12 or 16 (the registers keep the nearest hits in vectors of 4)"
#endif

layout(local_size_x = TILE, local_size_y = TILE) in;

layout(std430, binding = B_LAYER_DEPTH) writeonly buffer LayerDepth { uint layer_depth[]; };
layout(std430, binding = B_LAYER_LABEL) writeonly buffer LayerLabel { int layer_label[]; };
layout(std430, binding = B_TILE_ENTRIES) readonly buffer Entries { uvec2 entries[]; };
layout(std430, binding = B_TILE_OFFSETS) readonly buffer Offsets { uint offsets[]; };
#if HIT_MASKS
layout(std430, binding = B_TILE_MASKS) writeonly buffer Masks { uvec4 masks[]; };  // 2 per pixel: g_lo, g_hi
#endif

uniform uint u_capacity;  // entries the buffer holds (a slice past it was cut short)
uniform int u_layers;     // k

shared vec4 s_pr[BATCH];     // camera-space centre (m), squared radius (m^2)
shared vec4 s_nl[BATCH];     // unit normal, label (uint bits)
// How a walk finds the discs whose pixel box holds the pixel (the program is built both ways; the
// stage picks one a frame from how many discs its tiles hold, TileVisibility's walk):
// SPARSE_WALK 0: every disc in turn, its box tested (the warp's lanes on the same disc: one load
//   for all); SPARSE_WALK 1: the boxes as bit masks by word of 32 discs, s_cols[w * TILE + x]
//   with bit i set when the box of disc 32 w + i spans the tile's column x, s_rows likewise for
//   rows (from box_bits); a pixel's discs of a word are the AND of its column's and its row's
//   words, and each lane visits only its own (findLSB). H200 (reports/frame-h200, session 17):
//   with ~180 discs a tile (1280x720) the raster took 0.35 ms sparse against 0.50 in turn (the
//   box tests alone were ~0.4 of 1.68 ms at 3840x2160); with ~63 (3840x2160) 1.78 against 1.72.
#ifndef SPARSE_WALK
#define SPARSE_WALK 0
#endif
#if SPARSE_WALK
#define WORDS ((BATCH + 31) / 32)
shared uint s_cols[WORDS * TILE];
shared uint s_rows[WORDS * TILE];
#else
shared uint s_box[BATCH + 1];  // pixel box in the tile (box_bits); one more: the walk reads one ahead
#endif
shared uint s_found[3];      // "some pixel found this layer", one per walk, rotating

// per-invocation state
#if SPARSE_WALK
uint g_col, g_row;        // the pixel's column and row in the tile
#else
uint g_px;                // the pixel's bits in the tile (pixel_bits)
#endif
vec3 g_ray;               // its ray through the pixel centre (splat_ray)
float g_ray_len;          // length(g_ray)
float g_graze;            // GRAZING_COS * g_ray_len (hit_bits)
uint g_prev_d, g_prev_l;  // the last layer's depth bits and label (label ~0u before the first)
uint g_best_d, g_best_l;  // the nearest hit that passes the filter so far
uint g_count;             // discs in the tile's list
// The hit masks of discs 0-127 and 128-255, one word of 32 discs a component. Written as vectors
// filled component by component with constant indices: an array indexed by a loop counter may be
// kept in local memory (dmrt_photos.glsl's snap_try says more).
uvec4 g_lo, g_hi;
// The TOP nearest hits so far, ascending (depth bits, label); EMPTY_BITS = none. Vectors with
// constant indices, as the masks.
uvec4 g_top_d0, g_top_l0, g_top_d1, g_top_l1, g_top_d2, g_top_l2, g_top_d3, g_top_l3;
uint g_hits;   // hits of the pixel in the first walk

// Load discs [first, first + n) of the list into shared memory (call it from uniform control flow
// after a barrier that ends every read of the batch before: with SPARSE_WALK it holds one).
void load_batch(uint first, uint n) {
#if SPARSE_WALK
    for (uint i = gl_LocalInvocationIndex; i < uint(WORDS * TILE); i += uint(THREADS)) {
        s_cols[i] = 0u;
        s_rows[i] = 0u;
    }
    memoryBarrierShared();
    barrier();
#endif
    for (uint i = gl_LocalInvocationIndex; i < n; i += uint(THREADS)) {
        int label;
        uvec2 e = entries[first + i];
        Splat s = load_proxy(e.x, label);
        s_pr[i] = vec4(s.pc, s.r * s.r);
        s_nl[i] = vec4(s.nc, intBitsToFloat(label));
#if SPARSE_WALK
        uint at = (i >> 5u) * uint(TILE), bit = 1u << (i & 31u);
        for (uint cols = e.y & 0xFFFFu; cols != 0u; cols &= cols - 1u) atomicOr(s_cols[at + uint(findLSB(cols))], bit);
        for (uint rows = e.y >> 16u; rows != 0u; rows &= rows - 1u) atomicOr(s_rows[at + uint(findLSB(rows))], bit);
#else
        s_box[i] = e.y;
#endif
    }
}

// Depth bits of disc j's hit at the pixel, 0 for none; its label. splat_depth_ray's test to the
// bit (and so compute peeling's), written out for what the walks' cost is: the instructions they
// issue (H200, reports/frame-h200 session 21: raising the workgroups an SM holds from 4 to 5 made
// them slower; these few instructions less a test took 5.5 % off the raster at 3840x2160). The
// squared radius comes from shared memory, the grazing bound is the pixel's, the normal's load
// brings the label, and the bits come straight from the test: splat_depth_ray's float result
// tested again for z > 0 kept only 0.04 of the 0.09 ms.
uint hit_bits(uint j, out uint label) {
    vec4 pr = s_pr[j];
    vec4 nl = s_nl[j];
    vec3 nc = nl.xyz;
    label = floatBitsToUint(nl.w);
    float nd = dot(nc, g_ray);
    if (abs(nd) > g_graze) {
        float z = dot(nc, pr.xyz) / nd;
        vec3 q = z * g_ray - pr.xyz;
        return (z > 0.0 && dot(q, q) <= pr.w) ? floatBitsToUint(z) : 0u;
    }
    vec3 dh = normalize(g_ray);
    vec3 q = dot(pr.xyz, dh) * dh - pr.xyz;
    return (pr.z > 0.0 && dot(q, q) <= pr.w) ? floatBitsToUint(pr.z) : 0u;
}

// The peeling filter and the minimum: a hit behind the last layer with another label.
void consider(uint d, uint l) {
    if (d > g_prev_d && l != g_prev_l && (d < g_best_d || (d == g_best_d && l < g_best_l))) {
        g_best_d = d;
        g_best_l = l;
    }
}

// The nearest hits are kept in order of depth bits alone (one compare a step instead of three for
// (depth bits, label)), the label carried along. Hits of equal depth then keep the order they came
// in, not the label's, so a pixel whose kept hits hold two of equal depth (or that dropped one equal
// to the farthest kept) takes no layer from them and walks again for every layer (g_tie): exact,
// and two discs with bit-equal depths at a pixel centre are rare. (4 % off this pass at 3840x2160
// on the H100, nothing at 1280x720: reports/frame-h200, session 13.)
bool g_tie;

// One compare-exchange of the insertion: the entry keeps the nearer of itself and d (label
// alongside), which carries the farther on.
#define SORT_STEP(D, L) if (d < D) { uint t = D; D = d; d = t; t = L; L = l; l = t; }

// Insert a hit into the sorted nearest hits (dropping the farthest when they are full). A block of
// four that lies wholly in front of the carried hit keeps its entries: it is skipped (the hit
// carried on only grows, so every block before the insertion point is skipped, and a carried
// empty entry matches no block).
#define SORT_STEPS(D, L) if (d < D.w) { \
    SORT_STEP(D.x, L.x) SORT_STEP(D.y, L.y) SORT_STEP(D.z, L.z) SORT_STEP(D.w, L.w) }
#define FARTHEST_D (TOP > 12 ? g_top_d3.w : TOP > 8 ? g_top_d2.w : TOP > 4 ? g_top_d1.w : g_top_d0.w)

void keep_nearest(uint d, uint l) {
    ++g_hits;
    if (d >= FARTHEST_D) {
        g_tie = g_tie || d == FARTHEST_D;  // the list is full (an empty entry matches no hit)
        return;
    }
    SORT_STEPS(g_top_d0, g_top_l0)
#if TOP > 4
    SORT_STEPS(g_top_d1, g_top_l1)
#endif
#if TOP > 8
    SORT_STEPS(g_top_d2, g_top_l2)
#endif
#if TOP > 12
    SORT_STEPS(g_top_d3, g_top_l3)
#endif
    g_tie = g_tie || (d == FARTHEST_D && d != EMPTY_BITS);  // d: the hit dropped off the end
}

// Two neighbouring kept hits of equal depth (empty entries, all at the end, are not hits).
#define TIE(a, b) (a == b && b != EMPTY_BITS)
#define TIES4(D) (TIE(D.x, D.y) || TIE(D.y, D.z) || TIE(D.z, D.w))
bool ties_in_nearest() {
    bool t = TIES4(g_top_d0);
#if TOP > 4
    t = t || TIE(g_top_d0.w, g_top_d1.x) || TIES4(g_top_d1);
#endif
#if TOP > 8
    t = t || TIE(g_top_d1.w, g_top_d2.x) || TIES4(g_top_d2);
#endif
#if TOP > 12
    t = t || TIE(g_top_d2.w, g_top_d3.x) || TIES4(g_top_d3);
#endif
    return t;
}

// Test discs [from, to) of the batch in shared memory; the bits of the hits, from bit 0 for disc
// `from` (meaningful for up to 32 discs).
uint walk(uint from, uint to, const bool first) {
    uint mask = 0u;
#if SPARSE_WALK
    for (uint w = from >> 5u; w << 5u < to; ++w) {
        uint m = s_cols[w * uint(TILE) + g_col] & s_rows[w * uint(TILE) + g_row];
        uint lo = max(from, w << 5u) - (w << 5u), hi = min(to - (w << 5u), 32u);
        m &= (hi >= 32u ? ~0u : (1u << hi) - 1u) & ~((1u << lo) - 1u);
        while (m != 0u) {
            uint j = (w << 5u) + uint(findLSB(m));
            m &= m - 1u;
            uint l, d = hit_bits(j, l);
            if (d == 0u) continue;
            mask |= 1u << (j & 31u);
            if (first) keep_nearest(d, l);
            else consider(d, l);
        }
    }
#else
    // each disc's pixel box is read one iteration ahead: the load's latency overlaps the tests (H100:
    // 2-5 % off this pass, reports/frame-h200, session 13)
    uint next = s_box[from];
    for (uint j = from; j < to; ++j) {
        uint b = next;
        next = s_box[j + 1u];
        if (!in_box(g_px, b)) continue;
        uint l, d = hit_bits(j, l);
        if (d == 0u) continue;
        mask |= 1u << (j & 31u);
        if (first) keep_nearest(d, l);
        else consider(d, l);
    }
#endif
    return mask;
}

// The first walk over the 32 discs from `base`: their hit mask.
uint first_word(uint base) {
    return base < g_count ? walk(base, min(g_count, base + 32u), true) : 0u;
}

// A later walk over the remembered hits of a word; those at or in front of the last layer leave
// the mask for good.
uint again(uint word, uint base) {
    uint m = word;
    while (m != 0u) {
        int b = findLSB(m);
        m &= m - 1u;
        uint j = base + uint(b);
        uint l, d = hit_bits(j, l);
        if (d <= g_prev_d) word &= ~(1u << uint(b));
        else consider(d, l);
    }
    return word;
}

uint g_pix, g_found;  // the pixel's index, its layers written

void write_layer(uint d, uint l) {
    uint at = g_found * uint(u_size.x * u_size.y) + g_pix;
    layer_depth[at] = d;
    layer_label[at] = int(l);
    g_prev_d = d;
    g_prev_l = l;
    ++g_found;
}

// The peeling rule over the sorted nearest hits, in order (see the top of the file).
#define TAKE(D, L) if (g_found < uint(u_layers) && D != EMPTY_BITS && D > g_prev_d && L != g_prev_l) write_layer(D, L);

#define TAKES(D, L) TAKE(D.x, L.x) TAKE(D.y, L.y) TAKE(D.z, L.z) TAKE(D.w, L.w)

void layers_from_nearest() {
    TAKES(g_top_d0, g_top_l0)
#if TOP > 4
    TAKES(g_top_d1, g_top_l1)
#endif
#if TOP > 8
    TAKES(g_top_d2, g_top_l2)
#endif
#if TOP > 12
    TAKES(g_top_d3, g_top_l3)
#endif
}

// A list longer than BATCH: walked BATCH discs at a time, each batch loaded into shared memory by
// the whole workgroup (call it from uniform control flow: it holds barriers); `walking`: this
// invocation tests the discs.
void walk_batches(uint off, uint count, bool walking, const bool first) {
    for (uint sb = 0u; sb < count; sb += uint(BATCH)) {
        uint nb = min(uint(BATCH), count - sb);
        memoryBarrierShared();
        barrier();  // the batch before is no longer read
        load_batch(off + sb, nb);
        memoryBarrierShared();
        barrier();
        if (walking) walk(0u, nb, first);
    }
}

void main() {
    uint lid = gl_LocalInvocationIndex;
    uint tile = gl_WorkGroupID.y * uint(u_tiles.x) + gl_WorkGroupID.x;
    ivec2 local = tile_local_pixel();
    ivec2 p = ivec2(gl_WorkGroupID.xy) * TILE + local;
    bool inside = p.x < u_size.x && p.y < u_size.y;
    g_pix = inside ? uint(p.y * u_size.x + p.x) : 0u;
#if SPARSE_WALK
    g_col = uint(local.x);
    g_row = uint(local.y);
#else
    g_px = pixel_bits(local);
#endif
    g_ray = splat_ray(vec2(p) + 0.5);  // the pixel centre, as in every splat path
    g_ray_len = length(g_ray);
    g_graze = GRAZING_COS * g_ray_len;
    g_prev_d = 0u;
    g_prev_l = ~0u;
    g_found = 0u;
    g_hits = 0u;
    g_tie = false;
    g_top_d0 = g_top_l0 = g_top_d1 = g_top_l1 = uvec4(EMPTY_BITS);
    g_top_d2 = g_top_l2 = g_top_d3 = g_top_l3 = uvec4(EMPTY_BITS);

    uint off = offsets[tile];
    uint count = offsets[tile + 1u] - off;
    count = min(count, u_capacity - min(off, u_capacity));  // entries past the buffer were dropped
    g_count = count;
    bool cached = count <= uint(BATCH);
    if (lid < 3u) s_found[lid] = 0u;
    if (cached) load_batch(off, count);
    memoryBarrierShared();
    barrier();

    // the first walk: every disc, the pixel's nearest hits kept sorted
    if (cached) {
        if (inside) {
            g_lo = uvec4(first_word(0u), first_word(32u), first_word(64u), first_word(96u));
            g_hi = uvec4(first_word(128u), first_word(160u), first_word(192u), first_word(224u));
#if HIT_MASKS
            masks[2u * g_pix] = g_lo;  // for the labeling pass (dmrt_tiles_labeling.glsl)
            if (masks_second_half(count)) masks[2u * g_pix + 1u] = g_hi;
#endif
            walk(min(count, uint(MASK_DISCS)), count, true);
        }
    } else {
        walk_batches(off, count, inside, true);
    }
    g_tie = g_tie || ties_in_nearest();
    if (inside && !g_tie) layers_from_nearest();
    // a pixel whose hits did not all fit in the sorted prefix and which lacks layers walks again,
    // and one with equal depths among its nearest hits for every layer
    bool searching = inside && g_found < uint(u_layers) && (g_hits > uint(TOP) || g_tie);

    // then a walk per missing layer, over the pixels that need one, while any does; flag slot
    // i % 3 says "some pixel needs walk i + 1". A slot is reset (by invocation 0, before the
    // barrier of walk i) two walks after it was last read, before barriers every invocation has
    // passed since, and set again only after that barrier.
    uint slot = 0u;
    if (searching) s_found[0] = 1u;
    memoryBarrierShared();
    barrier();
    for (uint i = 1u; s_found[slot] != 0u; ++i) {
        g_best_d = EMPTY_BITS;
        g_best_l = EMPTY_BITS;
        if (cached) {
            if (searching) {
                g_lo = uvec4(again(g_lo.x, 0u), again(g_lo.y, 32u), again(g_lo.z, 64u), again(g_lo.w, 96u));
                g_hi = uvec4(again(g_hi.x, 128u), again(g_hi.y, 160u), again(g_hi.z, 192u), again(g_hi.w, 224u));
                walk(min(count, uint(MASK_DISCS)), count, false);
            }
        } else {
            walk_batches(off, count, searching, false);
        }
        if (searching && g_best_d != EMPTY_BITS) write_layer(g_best_d, g_best_l);
        searching = searching && g_best_d != EMPTY_BITS && g_found < uint(u_layers);
        slot = i % 3u;
        if (searching) s_found[slot] = 1u;
        if (lid == 0u) s_found[(i + 1u) % 3u] = 0u;
        memoryBarrierShared();
        barrier();
    }

    if (inside) {
        for (uint i = g_found; i < uint(u_layers); ++i) {
            uint at = i * uint(u_size.x * u_size.y) + g_pix;
            layer_depth[at] = EMPTY_BITS;
            layer_label[at] = EMPTY_LABEL;
        }
    }
}

#endif
