// Tile-binned visibility stage, a long list split over workgroups (dmrt/runtime/tiles.py, split_min):
// one label layer of the tiles whose lists the raster (dmrt_tiles_raster.glsl, SPLIT 1) handed over.
// A tile holds one workgroup, so a tile with thousands of discs (distant sub-pixel discs piling up
// where a street or a block recedes to its vanishing point) kept the whole frame waiting while the
// other tiles were long done: split into slices it runs on as many SMs as it has slices.
//
// Layer i (u_layer) of a pixel is the smallest (depth bits, label) among its hits behind layer i - 1
// with another label (dmrt_tiles_raster.glsl's rule), so it is the smallest of the slices' own
// smallest. MERGE 0: a workgroup per slice of BATCH discs writes its slice's per pixel (its
// partial); MERGE 1, the next dispatch: a workgroup per split tile takes the smallest of its
// slices' partials and writes the layer, EMPTY_BITS / EMPTY_LABEL where no hit passes (every layer
// of every pixel is written once). The test is compute peeling's (splat_depth_ray on splat_ray, as
// splat_depth_at), so the layers equal peeling's to the bit. The stage runs both once per layer.
//
// Buffers (binding: layout):
//   B_LAYER_DEPTH, B_LAYER_LABEL  as dmrt_tiles_raster.glsl's (layer i - 1 read, layer i written)
//   B_TILE_ENTRIES, B_TILE_OFFSETS  the tile lists (dmrt_tiles_bin.glsl, dmrt_tiles_scan.glsl)
//   B_TILE_SPLIT  the slices, the split tiles and the partials (dmrt_tiles_common.glsl, dmrt/gl/abi.py)
#ifndef MERGE
#define MERGE 0
#endif
#define SPLIT_BUFFER 1
#include "dmrt_tiles_common.glsl"

#if defined COMPUTE_SHADER

#ifndef BATCH
#define BATCH 288  // discs a slice: the raster's batch (TileVisibility.batch)
#endif

layout(local_size_x = TILE, local_size_y = TILE) in;

layout(std430, binding = B_LAYER_DEPTH) buffer LayerDepth { uint layer_depth[]; };
layout(std430, binding = B_LAYER_LABEL) buffer LayerLabel { int layer_label[]; };
layout(std430, binding = B_TILE_ENTRIES) readonly buffer Entries { uvec2 entries[]; };
layout(std430, binding = B_TILE_OFFSETS) readonly buffer Offsets { uint offsets[]; };

uniform uint u_capacity;  // entries the list buffer holds (a list past it was cut short)
uniform int u_layer;      // i, 0-based

shared vec4 s_pr[BATCH];  // camera-space centre (m), radius (m)
shared vec4 s_nl[BATCH];  // unit normal, label (int bits)
shared uint s_box[BATCH]; // pixel box in the tile (box_bits)
shared uint s_live;       // some pixel of the tile still has layers to find

void main() {
    uint lid = gl_LocalInvocationIndex;
    ivec2 local = tile_local_pixel();
#if MERGE
    SplitSlice tile = split_tile(gl_WorkGroupID.x);
    ivec2 p = split_tile_origin(tile.tile) + local;
    if (p.x >= u_size.x || p.y >= u_size.y) return;
    uvec2 best = split_merged(tile, lid);
    uint at = uint(u_layer) * uint(u_size.x * u_size.y) + uint(p.y * u_size.x + p.x);
    layer_depth[at] = best.x;
    layer_label[at] = best.x == EMPTY_BITS ? EMPTY_LABEL : int(best.y);
#else
    SplitSlice slice = split_slice(gl_WorkGroupID.x);
    ivec2 p = split_tile_origin(slice.tile) + local;
    bool inside = p.x < u_size.x && p.y < u_size.y;
    uint pix = inside ? uint(p.y * u_size.x + p.x) : 0u;
    uint plane = uint(u_size.x * u_size.y);

    // the layer before (none before the first); a pixel whose layer before is empty has no more
    uint prev_d = 0u, prev_l = ~0u;
    if (inside && u_layer > 0) {
        prev_d = layer_depth[uint(u_layer - 1) * plane + pix];
        prev_l = uint(layer_label[uint(u_layer - 1) * plane + pix]);
    }
    bool live = inside && prev_d != EMPTY_BITS;
    if (lid == 0u) s_live = 0u;
    memoryBarrierShared();
    barrier();
    if (live) s_live = 1u;
    memoryBarrierShared();
    barrier();

    uint best_d = EMPTY_BITS, best_l = EMPTY_BITS;
    if (s_live != 0u) {  // the same for the whole workgroup
        uint off = offsets[slice.tile];
        uint count = min(offsets[slice.tile + 1u] - off, u_capacity - min(off, u_capacity));
        uint from = off + slice.index * uint(BATCH);
        uint n = min(uint(BATCH), count - slice.index * uint(BATCH));
        for (uint i = lid; i < n; i += uint(TILE * TILE)) {
            int label;
            uvec2 e = entries[from + i];
            Splat s = load_proxy(e.x, label);
            s_pr[i] = vec4(s.pc, s.r);
            s_nl[i] = vec4(s.nc, intBitsToFloat(label));
            s_box[i] = e.y;
        }
        memoryBarrierShared();
        barrier();
        if (live) {
            vec3 ray = splat_ray(vec2(p) + 0.5);  // the pixel centre, as in every splat path
            float ray_len = length(ray);
            uint px = pixel_bits(local);
            for (uint j = 0u; j < n; ++j) {
                if (!in_box(px, s_box[j])) continue;
                vec4 pr = s_pr[j], nl = s_nl[j];
                float z = splat_depth_ray(Splat(pr.xyz, nl.xyz, pr.w), ray, ray_len);
                if (z <= 0.0) continue;
                uint d = floatBitsToUint(z), l = floatBitsToUint(nl.w);
                if (d > prev_d && l != prev_l && (d < best_d || (d == best_d && l < best_l))) {
                    best_d = d;
                    best_l = l;
                }
            }
        }
    }
    split_write_partial(slice, lid, uvec2(best_d, best_l));
#endif
}

#endif
