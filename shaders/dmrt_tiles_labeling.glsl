// DMRT labeling pass on the tile lists (dmrt/runtime/tiles.py): the geometry-aware Voronoi labels of
// dmrt_labeling.glsl - each pixel with a raytraced point q takes the label of the covering proxy
// disc nearest to q in 3D, ties to the smallest label - without splatting the proxies again and
// without a global atomic. The visibility stage's tile lists already hold, per TILE x TILE tile,
// every disc whose pixel box (splat_pixel_box, the box of every splat path) overlaps it; one
// workgroup walks its tile's list, THREADS discs at a time through shared memory, and each
// invocation keeps its pixel's nearest (distance bits, label) in registers. A disc covers a pixel
// by the same test (splat_depth_at), so the labels equal dmrt_labeling.glsl's to the bit.
// HIT_MASKS (TILE 16): in a tile whose list the raster held in shared memory (at most BATCH discs),
// the raster's first walk left each pixel the bits of which of the first 256 discs hit it, the very
// test made here; the first batch then visits only those discs (a few of the tile's tens to
// hundreds), and only discs past the 256th are tested.
//
// Long lists (TileVisibility's split_min): a tile whose list the split plan took over
// (dmrt_tiles_split.glsl) has an empty list here, so its pixels get the output of no covering disc;
// SPLIT_PASS 1, a workgroup per slice of BATCH of its discs, writes each pixel's nearest over the
// slice, then SPLIT_PASS 2, a workgroup per split tile, takes the nearest of its slices' and writes
// the output over it.
//
// Output: FINALIZE 1 -> each pixel's final label in its Hit record (dmrt_final_label.glsl: the pass
// of dmrt_label_finalize.glsl done here, without writing the labels and reading them back); else
// as dmrt_label_finalize.glsl reads it: PACKED_LABELS 1 -> Key uvec2 (label, distance bits), else
// Key uint distance bits and Label int label; EMPTY_BITS / EMPTY_LABEL where no disc covers.
#ifndef SPLIT_PASS
#define SPLIT_PASS 0
#endif
#define SPLIT_BUFFER (SPLIT_PASS != 0)
#include "dmrt_tiles_common.glsl"
#include "dmrt_frame.glsl"
#ifndef FINALIZE
#define FINALIZE 0
#endif
#if FINALIZE
#include "dmrt_photos.glsl"
#include "dmrt_final_label.glsl"
#endif

#if defined COMPUTE_SHADER

#ifndef PACKED_LABELS
#define PACKED_LABELS 0
#endif
#ifndef BATCH
#define BATCH 288  // as dmrt_tiles_raster.glsl's: tiles of up to BATCH discs have hit masks
#endif
#define THREADS (TILE * TILE)

layout(local_size_x = TILE, local_size_y = TILE) in;

layout(std430, binding = B_TILE_ENTRIES) readonly buffer Entries { uvec2 entries[]; };
layout(std430, binding = B_TILE_OFFSETS) readonly buffer Offsets { uint offsets[]; };
#if FINALIZE
#elif PACKED_LABELS
layout(std430, binding = B_KEY) writeonly buffer Key { uvec2 key[]; };
#else
layout(std430, binding = B_KEY) writeonly buffer Key { uint key[]; };
layout(std430, binding = B_VLABEL) writeonly buffer Label { int vlabel[]; };
#endif

#if HIT_MASKS
layout(std430, binding = B_TILE_MASKS) readonly buffer Masks { uvec4 masks[]; };
#endif

uniform uint u_capacity;  // entries the list holds (a slice past it was lost: see tiles.py)

// 36 bytes a disc, 9 KB a workgroup: few enough for several workgroups an SM (the raster's batch
// in dmrt/runtime/tiles.py says why that matters). A batch whose discs the hit masks name needs
// only the centres and labels.
shared vec4 s_cl[THREADS];    // camera-space centre (m), label (int bits)
shared vec4 s_nr[THREADS];    // unit normal, radius (m)
shared uint s_box[THREADS];   // pixel box in the tile (box_bits)

vec3 g_q;         // the pixel's raytraced point, camera space (m)
uint g_best;      // distance bits of the nearest covering disc so far
int g_best_label;

void consider(uint j) {
    vec4 cl = s_cl[j];
    uint bits = floatBitsToUint(distance(g_q, cl.xyz));
    int label = floatBitsToInt(cl.w);
    if (bits < g_best || (bits == g_best && label < g_best_label)) {
        g_best = bits;
        g_best_label = label;
    }
}

// The discs of a mask word (32 discs from `base`) that hit the pixel.
void visit(uint word, uint base) {
    while (word != 0u) {
        int b = findLSB(word);
        word &= word - 1u;
        consider(base + uint(b));
    }
}

void main() {
#if SPLIT_PASS
    SplitSlice slice = SPLIT_PASS == 1 ? split_slice(gl_WorkGroupID.x) : split_tile(gl_WorkGroupID.x);
    uint tile = slice.tile;
    ivec2 origin = split_tile_origin(tile);
#else
    uint tile = gl_WorkGroupID.y * uint(u_tiles.x) + gl_WorkGroupID.x;
    ivec2 origin = ivec2(gl_WorkGroupID.xy) * TILE;
#endif
    uint lid = gl_LocalInvocationIndex;
    ivec2 local = tile_local_pixel();
    ivec2 px = origin + local;
    uint bits = pixel_bits(local);
    bool inside = px.x < u_size.x && px.y < u_size.y;
    uint pix = uint(px.y * u_size.x + px.x);
    vec2 uv = vec2(px) + 0.5;
    vec3 ray = camera_ray(uv);  // splat_depth_at's, once for every disc
    float ray_len = length(ray);
    float z = inside ? hits[pix].depth : 0.0;
    g_q = z * ray;
    g_best = EMPTY_BITS;
    g_best_label = EMPTY_LABEL;
    uint start = offsets[tile];
    uint end = min(offsets[tile + 1u], u_capacity);
    // the raster's condition for holding the list in shared memory, on the same (cut) length
    uint count = min(end, u_capacity) - min(start, u_capacity);
    bool masked = bool(HIT_MASKS) && count <= uint(BATCH);
#if SPLIT_PASS == 1  // the slice's discs, in the split buffer (no hit masks)
    uvec2 range = split_slice_range(slice);
    start = range.x;
    end = range.y;
    masked = false;
#elif SPLIT_PASS == 2  // no walk: the nearest of the slices'
    end = start;
#endif
    for (uint base = start; base < end; base += uint(THREADS)) {
        bool by_masks = masked && base == start;  // the same for the whole workgroup
        if (base + lid < end) {
            int label;
#if SPLIT_PASS
            uvec2 e = split_entry(base + lid);
#else
            uvec2 e = entries[base + lid];
#endif
            Splat s = load_proxy(e.x, label);
            s_cl[lid] = vec4(s.pc, intBitsToFloat(label));
            if (!by_masks) {
                s_nr[lid] = vec4(s.nc, s.r);
                s_box[lid] = e.y;
            }
        }
        barrier();
        uint n = min(uint(THREADS), end - base);
#if HIT_MASKS
        if (z > 0.0 && by_masks) {
            uvec4 lo = masks[2u * pix];
            visit(lo.x, 0u); visit(lo.y, 32u); visit(lo.z, 64u); visit(lo.w, 96u);
            if (masks_second_half(count)) {  // else not written this frame (the raster's condition)
                uvec4 hi = masks[2u * pix + 1u];
                visit(hi.x, 128u); visit(hi.y, 160u); visit(hi.z, 192u); visit(hi.w, 224u);
            }
        } else
#endif
        if (z > 0.0) {
            for (uint j = 0u; j < n; ++j) {
                if (!in_box(bits, s_box[j])) continue;
                vec4 nr = s_nr[j];
                if (splat_depth_ray(Splat(s_cl[j].xyz, nr.xyz, nr.w), ray, ray_len) <= 0.0) continue;
                consider(j);
            }
        }
        barrier();
    }
#if SPLIT_PASS == 1
    split_write_partial(slice, lid, uvec2(g_best, uint(g_best_label)));
    return;
#elif SPLIT_PASS == 2
    uvec2 best = split_merged(slice, lid);
    g_best = best.x;
    g_best_label = best.x == EMPTY_BITS ? EMPTY_LABEL : int(best.y);
#endif
    if (!inside) return;
#if FINALIZE
    hits[pix].final_label = final_label(hits[pix], g_best_label, px);
#elif PACKED_LABELS
    key[pix] = uvec2(uint(g_best_label), g_best);
#else
    key[pix] = g_best;
    vlabel[pix] = g_best_label;
#endif
}

#endif
