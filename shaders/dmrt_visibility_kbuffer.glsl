// DMRT visibility stage, single-pass k-buffer (the paper's future work, Section 5.1.1: "one pass
// with an A-buffer"): every disc hit is inserted once into a per-pixel list of the K nearest
// fragments, K = SLOTS, kept sorted by a 32-bit key
//     key = (float bits of camera z with the low LABEL_BITS cleared) | label,
// so that one atomicMin orders by depth, then label. Insertion is the lock-free atomicMin cascade:
// the key takes slot j if smaller and the value it displaces moves on to slot j + 1; every slot
// only decreases, so concurrent insertions leave the K smallest keys in order. A key not below the
// last slot is not among the K nearest and is dropped after one plain read.
// dmrt_kbuffer_resolve.glsl then reads the label layers off the list. Both passes use 32-bit
// atomics only, so the same code runs on any GL 4.3 driver (Mesa llvmpipe in CI).
#include "dmrt_splat_common.glsl"

#if defined COMPUTE_SHADER

#include "dmrt_kbuffer_common.glsl"

void visit(Splat s, int label, int col, int row) {
    float z = splat_depth_at(s, vec2(col, row) + 0.5);
    if (z <= 0.0) return;
    uint key = ((floatBitsToUint(z) >> LABEL_BITS) << LABEL_BITS) | uint(label);
    uint base = uint(row * u_size.x + col) * uint(SLOTS);
    if (key >= kbuf[base + uint(SLOTS - 1)]) return;
    for (int j = 0; j < SLOTS; ++j) {
        uint cur = kbuf[base + uint(j)];
        if (key == cur) return;  // the same depth and label again: nothing new
        if (key > cur) continue;
        uint old = atomicMin(kbuf[base + uint(j)], key);
        if (old == EMPTY_BITS || old == key) return;
        key = max(old, key);
    }
}

#endif
