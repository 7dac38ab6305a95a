// Tile-binned visibility stage, long lists split over workgroups (dmrt/runtime/tiles.py, split_min).
// A tile holds one workgroup, so a tile with thousands of discs (distant sub-pixel discs piling up
// where a street or a block recedes to its vanishing point) kept the whole frame waiting while the
// other tiles were long done: split into slices of BATCH discs it runs on as many SMs as it has
// slices. Three steps (STEP), the plan once a frame, the others once per layer:
//
// STEP 0, the plan, one thread per tile, between the count and the scan: a tile whose list is
//   longer than u_split_min, where the split buffer has room for its discs and slices, is taken out
//   of the tile lists (its count set to 0: the scan gives it an empty slice of Entries, which the
//   raster and labeling passes walk as any empty list, writing empty layers) and its discs go to the
//   split buffer (the scatter's SPLIT 1); its slices and the tile are listed for STEP 1 and 2 with
//   their dispatch-indirect headers (the host resets them to no workgroups before).
// STEP 1, a workgroup per slice: layer i (u_layer) of a pixel is the smallest (depth bits, label)
//   among its hits behind layer i - 1 with another label (dmrt_tiles_raster.glsl's rule), so it is
//   the smallest of the slices' own smallest; each slice writes its own per pixel (its partial).
// STEP 2, a workgroup per split tile: the smallest of its slices' partials is layer i, written over
//   the raster's empty one (EMPTY_BITS / EMPTY_LABEL where no hit passes).
// The test is compute peeling's (splat_depth_ray on splat_ray, as splat_depth_at), so the layers
// equal peeling's to the bit.
//
// Buffers (binding: layout):
//   B_TILE_COUNTS   STEP 0: uint[tiles], the discs each tile counted (set to 0 for a split tile)
//   B_LAYER_DEPTH, B_LAYER_LABEL  STEP 1, 2: as dmrt_tiles_raster.glsl's (layer i - 1 read, layer i written)
//   B_TILE_SPLIT    the slices, the split tiles, their discs and partials (dmrt_tiles_common.glsl,
//                   dmrt/gl/abi.py)
#ifndef STEP
#define STEP 1
#endif
#define SPLIT_BUFFER 1
#include "dmrt_tiles_common.glsl"

#if defined COMPUTE_SHADER

#if STEP == 0

layout(local_size_x = 64) in;

layout(std430, binding = B_TILE_COUNTS) buffer Counts { uint counts[]; };

uniform uint u_split_min;  // lists longer than this are split (where they fit)

void main() {
    uint tile = gl_GlobalInvocationID.x;
    if (tile >= split_tiles()) return;
    uint count = counts[tile];
    uint base = EMPTY_BITS;
    if (count > u_split_min) {
        // the discs first, then the slices: a tile whose slices do not fit leaves a gap among the
        // discs (unused), never among the slices, so the slice pass's workgroups are all listed
        // (once one reservation runs past the room, every later one does too)
        uint e = atomicAdd(split[7], count);
        if (e + count <= u_split_entries) {
            uint n = (count + uint(BATCH) - 1u) / uint(BATCH);
            uint at = atomicAdd(split[3], n);
            if (at + n <= u_slots) {
                base = e;
                atomicMax(split[0], at + n);  // the slice pass's workgroups
                uint o = split_tile_items_at() + 4u * atomicAdd(split[4], 1u);  // the merge pass's
                split[o] = tile;
                split[o + 1u] = at;
                split[o + 2u] = n;
                for (uint s = 0u; s < n; ++s) {
                    uint q = 8u + 4u * (at + s);
                    split[q] = tile;
                    split[q + 1u] = at;
                    split[q + 2u] = n;
                    split[q + 3u] = s;
                }
                split[split_count_at() + tile] = count;
                split[split_left_at() + tile] = count;
                counts[tile] = 0u;
            }
        }
    }
    split[split_base_at() + tile] = base;
}

#else

layout(local_size_x = TILE, local_size_y = TILE) in;

layout(std430, binding = B_LAYER_DEPTH) buffer LayerDepth { uint layer_depth[]; };
layout(std430, binding = B_LAYER_LABEL) buffer LayerLabel { int layer_label[]; };

uniform int u_layer;  // i, 0-based

#if STEP == 1
shared vec4 s_pr[BATCH];  // camera-space centre (m), radius (m)
shared vec4 s_nl[BATCH];  // unit normal, label (int bits)
shared uint s_box[BATCH]; // pixel box in the tile (box_bits)
shared uint s_live;       // some pixel of the tile still has layers to find
#endif

void main() {
    uint lid = gl_LocalInvocationIndex;
    ivec2 local = tile_local_pixel();
#if STEP == 2
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
        uvec2 range = split_slice_range(slice);
        uint n = range.y - range.x;
        for (uint i = lid; i < n; i += uint(TILE * TILE)) {
            int label;
            uvec2 e = split_entry(range.x + i);
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
#endif
