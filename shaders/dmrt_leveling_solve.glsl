// Screen-space leveling, pass 2 of 3: the per-photo log gains, solved on the GPU from the seam sums
// of dmrt_leveling_seams.glsl and this frame's label histogram (dmrt_label_histogram.glsl), written
// as the gains dmrt_leveling_apply.glsl multiplies by. Reading the sums back and solving in numpy
// made the CPU wait for the whole frame so far (4.6-5.3 ms a frame on an H200); here nothing leaves
// the GPU. The problem is the one of dmrt/runtime/leveling.py's module docstring, and its numpy
// twin is dmrt.runtime.leveling.solve_gains (same rules: pairs with count >= u_min_samples only,
// photos without such a pair keep gain 1, reg * deg on the diagonal, the pixel-weighted mean over
// the used photos shifted to 0, exp and clamp to [1 / u_max_gain, u_max_gain]).
//
// One workgroup of THREADS invocations; invocation t owns the photos (rows) t, t + THREADS, ...
// and keeps their vectors in registers, so only the mat-vec reads other invocations' data (the
// search direction p of a row's neighbours: shared memory when it fits, P_SHARED, else the
// scratch buffer B_LEVEL_P, as the Python side decides from GL's guaranteed 32 KiB).
//
// 1. Each row a scans pairs[a][b] (a as the smaller label) and pairs[b][a] (a as the larger one)
//    once, and lists its neighbours b with their weights w_ab in row a of B_LEVEL_EDGES (capacity
//    n - 1 per row: no prefix sum needed). The right-hand side -sum_b w_ab d_ab is an integer sum
//    of the fixed-point seam sums, scaled once.
// 2. Jacobi-preconditioned conjugate gradients on (L + reg D) x = rhs, the three channels at once
//    (one mat-vec, per-channel scalars). The preconditioned matrix D^-1 (L + reg D) = (1 + reg) I -
//    D^-1 W has its eigenvalues in [reg, 2 + reg] (those of D^-1 W lie in [-1, 1]), so its
//    condition number kappa is at most (2 + reg) / reg = 201 whatever the graph, and PCG reduces
//    the A-norm error by 2 ((sqrt(kappa) - 1) / (sqrt(kappa) + 1))^i: 1e-6 by i = 103, 1e-11 by
//    i = 190. Each channel stops when |r| <= u_tol |rhs|, which float32 reaches (a float32 numpy
//    emulation of this loop: <= 72 iterations for chains of up to 300 photos, the slowest graphs,
//    <= 20 for random ones); the cap, used photos + 16 (exact arithmetic ends after as many steps
//    as distinct eigenvalues, float32 needs a few more) and at most u_max_iters (256), never bound
//    there and only bounds a frame's time.
// 3. The pixel-weighted mean over the used photos subtracted, exp, clamp.
//
// Accumulation is float32 throughout; what that costs against numpy's float64 solve is measured
// and justified in tests/test_leveling.py.
#if defined COMPUTE_SHADER

#ifndef N_PHOTOS
#define N_PHOTOS 1
#endif
#ifndef THREADS
#define THREADS 256  // a power of two: the reductions halve it
#endif
#ifndef P_SHARED
#define P_SHARED 1
#endif
#ifndef LOG_SCALE
#define LOG_SCALE 1024.0  // fixed point of the seam sums: dmrt_leveling_seams.glsl
#endif
#ifndef SCAN_BATCH
#define SCAN_BATCH 8
#endif
#define ROWS ((N_PHOTOS + THREADS - 1) / THREADS)

layout(local_size_x = THREADS) in;

// n x n: count, then the three channels' sums of log(c_a) - log(c_b) (row = smaller label a)
layout(std430, binding = B_PAIRS) readonly buffer Pairs { ivec4 pairs[]; };
layout(std430, binding = B_COUNTS) readonly buffer Counts { uint counts[]; };  // pixels per label
layout(std430, binding = B_GAINS) writeonly buffer Gains { vec4 gains[]; };   // RGB gain, 1
// row a (n entries from a * n): neighbour b, weight w_ab as float bits; only its own invocation
// writes and reads a row, so it needs no barrier
layout(std430, binding = B_LEVEL_EDGES) buffer Edges { uvec2 edges[]; };

uniform int u_min_samples;  // >= 1
uniform float u_reg;
uniform float u_max_gain;
uniform int u_max_iters;
uniform float u_tol;

// the reductions' partial sums: slot 0 for the first reduction of an iteration (and the mean),
// slots 1 and 2 for the second, so that no invocation overwrites a slot before every invocation
// has read the last sum from it (a reduction on other slots, with its barriers, lies between)
shared vec4 s_red[3][THREADS];
shared uint s_used;

#if P_SHARED
shared float s_p[3 * N_PHOTOS];  // channel-major: 12 bytes a photo

vec3 load_p(uint b) { return vec3(s_p[b], s_p[N_PHOTOS + b], s_p[2 * N_PHOTOS + b]); }
void store_p(uint a, vec3 v) { s_p[a] = v.x; s_p[N_PHOTOS + a] = v.y; s_p[2 * N_PHOTOS + a] = v.z; }
void sync_p() { memoryBarrierShared(); barrier(); }
#else
// coherent: other invocations of the workgroup read what one wrote (after sync_p)
layout(std430, binding = B_LEVEL_P) coherent buffer Direction { vec4 p_buf[]; };

vec3 load_p(uint b) { return p_buf[b].xyz; }
void store_p(uint a, vec3 v) { p_buf[a] = vec4(v, 0.0); }
void sync_p() { memoryBarrierBuffer(); barrier(); }
#endif

// Sums a and b over the workgroup (slots sa != sb of s_red); every invocation gets the sums.
// Called in uniform control flow only.
void reduce2(int sa, int sb, inout vec4 a, inout vec4 b) {
    uint lid = gl_LocalInvocationIndex;
    s_red[sa][lid] = a;
    s_red[sb][lid] = b;
    for (uint s = uint(THREADS) / 2u; s > 0u; s >>= 1) {
        memoryBarrierShared();
        barrier();
        if (lid < s) {
            s_red[sa][lid] += s_red[sa][lid + s];
            s_red[sb][lid] += s_red[sb][lid + s];
        }
    }
    memoryBarrierShared();
    barrier();
    a = s_red[sa][0];
    b = s_red[sb][0];
}

// Sums v over the workgroup (slot 0 of s_red), as reduce2.
vec4 reduce1(vec4 v) {
    uint lid = gl_LocalInvocationIndex;
    s_red[0][lid] = v;
    for (uint s = uint(THREADS) / 2u; s > 0u; s >>= 1) {
        memoryBarrierShared();
        barrier();
        if (lid < s) s_red[0][lid] += s_red[0][lid + s];
    }
    memoryBarrierShared();
    barrier();
    return s_red[0][0];
}

void main() {
    uint lid = gl_LocalInvocationIndex;
    if (lid == 0u) s_used = 0u;
    memoryBarrierShared();
    barrier();

    // 1. the rows' neighbour lists, diagonals, right-hand sides; x0 = 0, r0 = rhs, p0 = z0 = r0 / diag
    vec3 x[ROWS], r[ROWS], p[ROWS], q[ROWS];
    float diag[ROWS];
    uint nnz[ROWS];
    vec4 rz = vec4(0.0), bb = vec4(0.0);
    uint used_here = 0u;
    for (int k = 0; k < ROWS; ++k) {
        uint a = lid + uint(k * THREADS);
        x[k] = r[k] = p[k] = q[k] = vec3(0.0);
        diag[k] = 1.0;
        nnz[k] = 0u;
        if (a >= uint(N_PHOTOS)) continue;
        float deg = 0.0;
        vec3 rhs = vec3(0.0);
        uint m = 0u;
        // SCAN_BATCH entries loaded before any is used: one load at a time left the scan bound by
        // memory latency (H200, 1000 photos: 1.05 ms a solve, 0.65 ms with batches of 8, 1.2 ms
        // with 16)
        for (uint b0 = 0u; b0 < uint(N_PHOTOS); b0 += uint(SCAN_BATCH)) {
            ivec4 ab[SCAN_BATCH], ba[SCAN_BATCH];
            for (int j = 0; j < SCAN_BATCH; ++j) {
                uint b = min(b0 + uint(j), uint(N_PHOTOS - 1));  // in bounds; the tail is skipped below
                ab[j] = pairs[a * uint(N_PHOTOS) + b];
                ba[j] = pairs[b * uint(N_PHOTOS) + a];
            }
            for (int j = 0; j < SCAN_BATCH; ++j) {
                uint b = b0 + uint(j);
                if (b >= uint(N_PHOTOS) || b == a) continue;  // the seam pass never pairs a photo with itself
                float w = 0.0;
                // term w (d + x_a - x_b)^2 with a the row: rhs_a -= w d = sum / LOG_SCALE; as the column, +=
                if (ab[j].x >= u_min_samples) { w += float(ab[j].x); rhs -= vec3(ab[j].yzw); }
                if (ba[j].x >= u_min_samples) { w += float(ba[j].x); rhs += vec3(ba[j].yzw); }
                if (w > 0.0) {
                    edges[a * uint(N_PHOTOS) + m] = uvec2(b, floatBitsToUint(w));
                    ++m;
                    deg += w;
                }
            }
        }
        nnz[k] = m;
        if (m > 0u) {
            ++used_here;
            diag[k] = (1.0 + u_reg) * deg;
            r[k] = rhs / LOG_SCALE;
            p[k] = r[k] / diag[k];
            rz.xyz += r[k] * p[k];
            bb.xyz += r[k] * r[k];
        }
        store_p(a, p[k]);  // 0 for unused photos: no used photo has them as neighbours anyway
    }
    if (used_here > 0u) atomicAdd(s_used, used_here);
#if !P_SHARED
    memoryBarrierBuffer();  // p0 before the reduction's barriers
#endif
    reduce2(1, 2, rz, bb);
    int cap = min(int(s_used) + 16, u_max_iters);
    float tol2 = u_tol * u_tol;
    vec3 live = vec3(greaterThan(bb.xyz, vec3(0.0)));  // 1 while a channel iterates

    // 2. PCG; every invocation sees the same reductions, so the loop's control flow is uniform
    for (int it = 0; it < cap && any(greaterThan(live, vec3(0.0))); ++it) {
        vec4 pq = vec4(0.0);
        for (int k = 0; k < ROWS; ++k) {
            if (nnz[k] == 0u) continue;
            uint base = (lid + uint(k * THREADS)) * uint(N_PHOTOS);
            // y_a = sum_b w_ab (p_a - p_b) + reg deg_a p_a
            vec3 s = diag[k] * p[k];
            for (uint e = 0u; e < nnz[k]; ++e) {
                uvec2 nb = edges[base + e];
                s -= uintBitsToFloat(nb.y) * load_p(nb.x);
            }
            q[k] = s;
            pq.xyz += p[k] * s;
        }
        pq = reduce1(pq);
        // live channels have pq > 0 (A is positive definite on the used photos, p != 0 while r != 0)
        vec3 alpha = mix(vec3(0.0), rz.xyz / pq.xyz, bvec3(live * vec3(greaterThan(pq.xyz, vec3(0.0)))));
        vec4 rz_new = vec4(0.0), rr = vec4(0.0);
        for (int k = 0; k < ROWS; ++k) {
            if (nnz[k] == 0u) continue;
            x[k] += alpha * p[k];
            r[k] -= alpha * q[k];
            rz_new.xyz += r[k] * r[k] / diag[k];
            rr.xyz += r[k] * r[k];
        }
        reduce2(1, 2, rz_new, rr);
        vec3 beta = mix(vec3(0.0), rz_new.xyz / rz.xyz, bvec3(live * vec3(greaterThan(rz.xyz, vec3(0.0)))));
        live *= vec3(greaterThan(rr.xyz, tol2 * bb.xyz));
        rz = rz_new;
        for (int k = 0; k < ROWS; ++k) {
            if (nnz[k] == 0u) continue;
            p[k] = r[k] / diag[k] + beta * p[k];
            store_p(lid + uint(k * THREADS), p[k]);
        }
        sync_p();  // the next mat-vec reads the neighbours' p
    }

    // 3. keep the frame's mean log brightness over the used photos, then gains
    vec4 mean = vec4(0.0);
    for (int k = 0; k < ROWS; ++k) {
        if (nnz[k] == 0u) continue;
        float px = float(counts[lid + uint(k * THREADS)]);
        mean += vec4(px * x[k], px);
    }
    mean = reduce1(mean);
    vec3 shift = mean.w > 0.0 ? mean.xyz / mean.w : vec3(0.0);
    for (int k = 0; k < ROWS; ++k) {
        uint a = lid + uint(k * THREADS);
        if (a >= uint(N_PHOTOS)) continue;
        vec3 g = nnz[k] > 0u ? clamp(exp(x[k] - shift), vec3(1.0 / u_max_gain), vec3(u_max_gain)) : vec3(1.0);
        gains[a] = vec4(g, 1.0);
    }
}

#endif
