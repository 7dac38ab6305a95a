// Tile-binned visibility stage, raster (dmrt/runtime/tiles.py): all k label layers of one TILE x TILE
// screen tile per workgroup, one invocation per pixel, the per-pixel state in registers.
//
// 1. Order. The tile's slice of Entries (dmrt_tiles_bin.glsl: (near key, proxy index) pairs, unique
//    since a disc is binned once per tile) is sorted in shared memory (bitonic, up to SORT_SIZE
//    keys). A longer slice is cut into chunks of at most SORT_SIZE (every chunks-th entry), each
//    sorted and written back, then merged on the fly: each chunk keeps a cursor, a window of
//    W = SORT_SIZE / chunks keys per chunk is read, T = the smallest key just past any window, and
//    the window keys below T are exactly the next keys of the merged order (everything past a
//    window is >= T); they are sorted in shared memory and walked, and the cursors advance. A slice
//    of more than MAX_CHUNKS chunks (or windows under 4 keys) is walked chunk after chunk instead
//    (approximate; counted in Status.long_tiles).
// 2. Raster. The sorted discs are loaded THREADS at a time into shared memory (camera-space centre,
//    normal, radius, label, pixel box); each invocation tests its pixel against the box, then runs
//    the ray-disc test of every other path (splat_depth_at: same function, same depth bits).
// 3. Layers. Depth peeling (layer i+1 = the nearest hit behind layer i with another label; equal
//    depths to the smallest label) is, over all hits at the pixel in (depth, label) order, "take a
//    hit unless its label equals the last layer's or its depth is not greater"
//    (dmrt_kbuffer_resolve.glsl walks the same rule): an automaton that needs the hits in order.
//    Discs arrive in near-key order, their hits not quite (a hit lies up to the disc's depth extent
//    behind its near key), so each invocation keeps the hits that are not final yet in a sorted
//    pending list of PENDING entries: every disc still to come has a near key >= the current one
//    (the watermark) and so hits no nearer; pending hits in front of the watermark are final and
//    go to the automaton in order, which writes each layer it takes to the layer buffers once.
//    The list fills with the hits of the discs overlapping at the pixel near the watermark (the
//    splat overlap of the nearest surfaces). When full, hits behind the k-th layer that the taken
//    layers plus the pending hits already give are dropped (exact: adding hits only adds layers or
//    moves them nearer, so nothing behind that one can become a layer), and so is every later hit
//    behind it; if the list is still full, its farthest hit is dropped (approximate: only layers
//    behind it can change). With u_redo the workgroup then lists its tile (RedoList) and the REDO
//    variant, compiled with the longest list, walks the listed tiles again in the same frame
//    (dispatch-indirect); Status.redo_tiles counts them. Status.overflow counts the pixels that
//    overflowed in the pass that wrote them last (dmrt/runtime/tiles.py).
// 4. Early exit. A pixel is done when it has k layers. After each batch of discs the workgroup
//    checks (shared flag, barrier) whether all of its pixels are done and stops walking the list.
// At the end the pending hits are flushed and the missing layers written empty, so the layer
// buffers need no clearing.
//
// Buffers (binding: layout):
//   B_PROXIES       n x 8 floats (dmrt_tiles_common.glsl)
//   B_LAYER_DEPTH   k x h x w uint: float bits of camera z, EMPTY_BITS = none (row 0 at the top)
//   B_LAYER_LABEL   k x h x w int: label, EMPTY_LABEL = none
//   B_TILE_STATUS   uint total, overflow (pixels that dropped a hit), long_tiles, redo_tiles
//   B_TILE_REDO     dispatch-indirect header (groups x, y, z, tiles), then the tiles to walk again
//   B_TILE_ENTRIES  uvec2[capacity] (dmrt_tiles_bin.glsl); chunks of long slices are sorted in place
//   B_TILE_OFFSETS  uint[tiles + 1] (dmrt_tiles_scan.glsl)
#include "dmrt_tiles_common.glsl"

#if defined COMPUTE_SHADER

#ifndef PENDING
#define PENDING 8
#endif
#ifndef SORT_SIZE
#define SORT_SIZE 2048  // power of two; SORT_SIZE x 8 bytes of shared memory
#endif
#ifndef REDO
#define REDO 0
#endif
#ifndef MAX_CHUNKS
#define MAX_CHUNKS 256
#endif
#define THREADS (TILE * TILE)

layout(local_size_x = TILE, local_size_y = TILE) in;

layout(std430, binding = B_LAYER_DEPTH) writeonly buffer LayerDepth { uint layer_depth[]; };
layout(std430, binding = B_LAYER_LABEL) writeonly buffer LayerLabel { int layer_label[]; };
layout(std430, binding = B_TILE_STATUS) buffer Status { uint total; uint overflow; uint long_tiles; uint redo_tiles; };
layout(std430, binding = B_TILE_REDO) buffer RedoList { uint redo_x, redo_y, redo_z, redo_n; uint redo_list[]; };
layout(std430, binding = B_TILE_ENTRIES) coherent buffer Entries { uvec2 entries[]; };
layout(std430, binding = B_TILE_OFFSETS) readonly buffer Offsets { uint offsets[]; };

uniform uint u_capacity;  // entries the buffer holds (a slice past it was cut short)
uniform int u_layers;     // k
uniform int u_redo;       // 1: list the tiles with an overflowing pixel for the REDO pass (main pass)
uniform uint u_max_groups;  // GL_MAX_COMPUTE_WORK_GROUP_COUNT[0]

const uvec2 MAX_KEY = uvec2(EMPTY_BITS);  // above every (near key, index) pair

shared uvec2 s_keys[SORT_SIZE];  // sorted (near key, proxy index)
shared vec4 s_pr[THREADS];       // disc batch: camera-space centre (m), radius (m)
shared vec4 s_nl[THREADS];       //             unit normal, label (int bits)
shared uvec2 s_box[THREADS];     //             pixel box: col0 | row0 << 16, col1 | row1 << 16
shared uint s_cur[MAX_CHUNKS];   // merge: next unprocessed key of each chunk
shared uint s_cnt[MAX_CHUNKS];   // merge: keys of each chunk in this round
shared uint s_tx, s_ty, s_m;     // merge: the round's bound T and key count
shared uint s_active[3];         // "some pixel still needs layers", one per round, rotating
shared uint s_overflow;          // some pixel of the tile overflowed

// per-invocation state
uint g_pix, g_npix;       // pixel index, pixels per layer
uint g_n;                 // layers found (u_layers when done or outside the frame)
uint g_prev_d, g_prev_l;  // the last layer's depth bits and label
uint g_round;             // batches walked (uniform in the workgroup)
bool g_overflow;          // a hit that may have mattered was dropped
uint g_bound;             // hits behind this depth cannot become layers (prune)
uint pd[PENDING];         // pending hits, ascending (depth bits, label); EMPTY_BITS = free
uint pl[PENDING];

bool key_less(uvec2 a, uvec2 b) { return a.x < b.x || (a.x == b.x && a.y < b.y); }

// The peeling automaton, fed hits in (depth, label) order.
void commit(uint d, uint l) {
    if (g_n >= uint(u_layers)) return;
    if (g_n > 0u && (l == g_prev_l || d <= g_prev_d)) return;
    layer_depth[g_n * g_npix + g_pix] = d;
    layer_label[g_n * g_npix + g_pix] = int(l);
    g_prev_d = d;
    g_prev_l = l;
    ++g_n;
}

void pop_front() {
    for (int i = 0; i < PENDING - 1; ++i) {
        pd[i] = pd[i + 1];
        pl[i] = pl[i + 1];
    }
    pd[PENDING - 1] = EMPTY_BITS;
}

// Commit the pending hits nearer than the watermark: no disc still to come can hit in front of them.
void commit_below(uint watermark) {
    while (pd[0] < watermark && g_n < uint(u_layers)) {
        commit(pd[0], pl[0]);
        pop_front();
    }
}

// Adding hits to a pixel only adds layers or moves them nearer (in depth order a hit splits a run of
// equal labels, heads one, or joins one), so once the layers taken so far plus the pending hits
// walked in order reach k layers, nothing behind that k-th layer can become one: drop those pending
// hits, and every later hit behind it (g_bound). Exact; walked only when the pending list is full.
void prune() {
    uint n = g_n, prev_d = g_prev_d, prev_l = g_prev_l;
    for (int i = 0; i < PENDING; ++i) {
        if (n >= uint(u_layers)) {
            pd[i] = EMPTY_BITS;
        } else if (n == 0u || (pl[i] != prev_l && pd[i] > prev_d)) {
            prev_d = pd[i];
            prev_l = pl[i];
            if (++n == uint(u_layers)) g_bound = min(g_bound, prev_d);
        }
    }
}

void insert(uint d, uint l, uint watermark) {
    if (d > g_bound) return;
    if (pd[PENDING - 1] != EMPTY_BITS) {
        commit_below(watermark);
        if (pd[PENDING - 1] != EMPTY_BITS) prune();
    }
    for (int i = 0; i < PENDING; ++i) {  // insertion by compare-and-swap: constant indices, registers
        if (d < pd[i] || (d == pd[i] && l < pl[i])) {
            uint td = pd[i], tl = pl[i];
            pd[i] = d;
            pl[i] = l;
            d = td;
            l = tl;
        }
    }
    if (d != EMPTY_BITS) g_overflow = true;  // the list was full: the farthest of PENDING + 1 hits dropped
}

// Bitonic sort of s_keys[0..n), n a power of two; ends with a barrier.
void sort_keys(uint n) {
    uint lid = gl_LocalInvocationIndex;
    for (uint k = 2u; k <= n; k <<= 1u) {
        for (uint j = k >> 1u; j > 0u; j >>= 1u) {
            for (uint q = lid; q < n / 2u; q += uint(THREADS)) {
                uint i = 2u * q - (q & (j - 1u));  // i has bit j clear; its partner is i + j
                uvec2 a = s_keys[i], b = s_keys[i + j];
                if (key_less(b, a) == ((i & k) == 0u)) {
                    s_keys[i] = b;
                    s_keys[i + j] = a;
                }
            }
            memoryBarrierShared();
            barrier();
        }
    }
}

// Load Entries[base + i * stride] for i < m (m <= SORT_SIZE) into s_keys and sort them.
void load_sorted(uint base, uint stride, uint m) {
    uint n = 2u;
    while (n < m) n <<= 1u;
    memoryBarrierShared();
    barrier();  // s_keys may still be read by the previous batch
    for (uint i = gl_LocalInvocationIndex; i < n; i += uint(THREADS))
        s_keys[i] = i < m ? entries[base + i * stride] : MAX_KEY;
    memoryBarrierShared();
    barrier();
    sort_keys(n);
}

// Walk the sorted discs s_keys[0..m): every later disc has near key >= final_watermark. True when
// every pixel of the tile has its k layers (uniform).
bool process_run(uint m, uint final_watermark, ivec2 p, vec2 uv) {
    uint lid = gl_LocalInvocationIndex;
    for (uint sb = 0u; sb < m; sb += uint(THREADS)) {
        uint nb = min(uint(THREADS), m - sb);
        if (lid < nb) {
            int label;
            Splat s = load_proxy(s_keys[sb + lid].y, label);
            ivec4 box = splat_pixel_box(s);
            s_pr[lid] = vec4(s.pc, s.r);
            s_nl[lid] = vec4(s.nc, intBitsToFloat(label));
            s_box[lid] = uvec2(uint(box.x) | (uint(box.y) << 16), uint(box.z) | (uint(box.w) << 16));
        }
        // three flags in rotation: the one reset here was last read two batches ago, before the
        // barrier every invocation has passed since
        uint slot = g_round % 3u;
        if (lid == 0u) s_active[(g_round + 1u) % 3u] = 0u;
        memoryBarrierShared();
        barrier();
        if (g_n < uint(u_layers)) {
            uvec2 px = uvec2(p);
            for (uint j = 0u; j < nb && g_n < uint(u_layers); ++j) {
                uvec2 b = s_box[j];
                if (px.x < (b.x & 0xFFFFu) || px.x > (b.y & 0xFFFFu) || px.y < (b.x >> 16) || px.y > (b.y >> 16))
                    continue;
                vec4 pr = s_pr[j], nl = s_nl[j];
                Splat s;
                s.pc = pr.xyz;
                s.r = pr.w;
                s.nc = nl.xyz;
                float z = splat_depth_at(s, uv);
                if (z > 0.0) insert(floatBitsToUint(z), floatBitsToUint(nl.w), s_keys[sb + j].x);
            }
            commit_below(sb + nb < m ? s_keys[sb + nb].x : final_watermark);
        }
        if (g_n < uint(u_layers)) s_active[slot] = 1u;
        memoryBarrierShared();
        barrier();
        bool done = s_active[slot] == 0u;
        ++g_round;
        if (done) return true;
    }
    return false;
}

void raster_tile(uint tile) {
    uint lid = gl_LocalInvocationIndex;
    uvec2 tile_xy = uvec2(tile % uint(u_tiles.x), tile / uint(u_tiles.x));
    ivec2 p = ivec2(tile_xy * uint(TILE) + gl_LocalInvocationID.xy);
    bool inside = p.x < u_size.x && p.y < u_size.y;
    vec2 uv = vec2(p) + 0.5;  // the pixel centre, as in every splat path
    g_npix = uint(u_size.x * u_size.y);
    g_pix = inside ? uint(p.y * u_size.x + p.x) : 0u;
    g_n = inside ? 0u : uint(u_layers);
    g_prev_d = 0u;
    g_prev_l = 0u;
    g_round = 0u;
    g_overflow = false;
    g_bound = EMPTY_BITS;
    for (int i = 0; i < PENDING; ++i) {
        pd[i] = EMPTY_BITS;
        pl[i] = 0u;
    }
    if (lid < 3u) s_active[lid] = 0u;
    if (lid == 0u) s_overflow = 0u;

    uint off = offsets[tile];
    uint count = offsets[tile + 1u] - off;
    count = min(count, u_capacity - min(off, u_capacity));  // entries past the buffer were dropped
    uint chunks = (count + uint(SORT_SIZE) - 1u) / uint(SORT_SIZE);

    if (chunks <= 1u || chunks > min(uint(MAX_CHUNKS), uint(SORT_SIZE) / 4u)) {
        // one sorted run (or, past MAX_CHUNKS, each chunk sorted on its own: approximate)
        if (chunks > 1u && lid == 0u && REDO == 0) atomicAdd(long_tiles, 1u);  // once a tile
        for (uint c = 0u; c < chunks; ++c) {
            uint m = min(uint(SORT_SIZE), count - c * uint(SORT_SIZE));
            load_sorted(off + c * uint(SORT_SIZE), 1u, m);
            if (process_run(m, c + 1u == chunks ? EMPTY_BITS : s_keys[m - 1u].x, p, uv)) break;
        }
    } else {
        // sort the chunks in place, then merge them round by round. Chunk c is every chunks-th entry
        // from the c-th: the scatter pass leaves a slice roughly in proxy (Morton, so depth-coherent)
        // order, and contiguous chunks would cover disjoint depth ranges, each round then taking
        // keys from one chunk's window only; strided ones each sample the whole range.
        for (uint c = 0u; c < chunks; ++c) {
            uint m = (count - c + chunks - 1u) / chunks;
            load_sorted(off + c, chunks, m);
            for (uint i = lid; i < m; i += uint(THREADS)) entries[off + c + i * chunks] = s_keys[i];
            memoryBarrierBuffer();
            barrier();
        }
        uint w = uint(SORT_SIZE) / chunks;
        for (uint c = lid; c < chunks; c += uint(THREADS)) {
            s_cur[c] = 0u;
            s_cnt[c] = 0u;
        }
        while (true) {
            if (lid == 0u) {
                s_tx = EMPTY_BITS;
                s_ty = EMPTY_BITS;
                s_m = 0u;
            }
            memoryBarrierShared();
            barrier();
            // T = the smallest key just past a window (64-bit minimum in two 32-bit steps)
            for (uint c = lid; c < chunks; c += uint(THREADS)) {
                uint i = s_cur[c] + w;
                if (i < (count - c + chunks - 1u) / chunks) atomicMin(s_tx, entries[off + c + i * chunks].x);
            }
            memoryBarrierShared();
            barrier();
            for (uint c = lid; c < chunks; c += uint(THREADS)) {
                uint i = s_cur[c] + w;
                if (i < (count - c + chunks - 1u) / chunks) {
                    uvec2 k = entries[off + c + i * chunks];
                    if (k.x == s_tx) atomicMin(s_ty, k.y);
                }
            }
            memoryBarrierShared();
            barrier();
            uvec2 bound = uvec2(s_tx, s_ty);
            // the window keys below T, the rest of s_keys MAX_KEY; sorted, they lead
            for (uint q = lid; q < uint(SORT_SIZE); q += uint(THREADS)) {
                uint c = q / w, i = s_cur[min(c, uint(MAX_CHUNKS) - 1u)] + (q - c * w);
                uvec2 v = MAX_KEY;
                if (c < chunks && i < (count - c + chunks - 1u) / chunks) {
                    uvec2 k = entries[off + c + i * chunks];
                    if (key_less(k, bound)) {
                        v = k;
                        atomicAdd(s_cnt[c], 1u);
                    }
                }
                s_keys[q] = v;
            }
            memoryBarrierShared();
            barrier();
            sort_keys(uint(SORT_SIZE));
            for (uint c = lid; c < chunks; c += uint(THREADS)) {
                atomicAdd(s_m, s_cnt[c]);
                s_cur[c] += s_cnt[c];
                s_cnt[c] = 0u;
            }
            memoryBarrierShared();
            barrier();
            uint m = s_m;
            if (m == 0u) break;
            if (process_run(m, bound.x, p, uv)) break;
        }
    }

    // the rest of the pending hits, in order; then the layers not found are empty
    while (pd[0] != EMPTY_BITS && g_n < uint(u_layers)) {
        commit(pd[0], pl[0]);
        pop_front();
    }
    if (inside) {
        for (uint i = g_n; i < uint(u_layers); ++i) {
            layer_depth[i * g_npix + g_pix] = EMPTY_BITS;
            layer_label[i * g_npix + g_pix] = EMPTY_LABEL;
        }
    }
#if REDO
    if (g_overflow) atomicAdd(overflow, 1u);
#else
    if (u_redo == 0) {
        if (g_overflow) atomicAdd(overflow, 1u);
        return;
    }
    memoryBarrierShared();
    barrier();  // s_overflow's reset above is done
    if (g_overflow) s_overflow = 1u;
    memoryBarrierShared();
    barrier();
    if (lid == 0u && s_overflow != 0u) {
        uint i = atomicAdd(redo_n, 1u);
        redo_list[i] = tile;
        if (i < u_max_groups) atomicMax(redo_x, i + 1u);
        atomicAdd(redo_tiles, 1u);
    }
#endif
}

void main() {
#if REDO
    // the listed tiles, a workgroup taking every gl_NumWorkGroups.x-th
    for (uint e = gl_WorkGroupID.x; e < redo_n; e += gl_NumWorkGroups.x) {
        memoryBarrierShared();
        barrier();  // the last tile's walk has left the shared arrays
        raster_tile(redo_list[e]);
    }
#else
    raster_tile(gl_WorkGroupID.y * uint(u_tiles.x) + gl_WorkGroupID.x);
#endif
}

#endif
