// Exact k nearest neighbours of every point of a bucket among the bucket's points, over a uniform
// grid that dmrt/preprocess/gpu_knn.py (GridKnn) builds on the CPU: one invocation per query point
// visits the cells in cubic rings of growing Chebyshev radius around its own, keeps its K best
// (squared distance, point) sorted by insertion, skips cells whose box is farther than its K-th
// best, and stops once the ring's boundary is farther than its K-th best (nothing outside can be
// nearer). The query point is its own first neighbour (distance 0), as KnnTree.query gives it.
//
// Buffers (binding points in dmrt/gl/abi.py):
//   B_KNN_POINTS    n vec4: xyz float32 metres from the bucket's centre, sorted by cell (column
//                   major, then z); w: the point's index in the caller's order, as float bits
//   B_KNN_COLUMNS   nx * ny + 1 uint: where column (x, y) = y * nx + x starts in B_KNN_CELLS
//   B_KNN_CELLS     cells + 1 uvec2: the cell's z index and its first point in B_KNN_POINTS; the
//                   last is (0xFFFFFFFF, n), so cells[c + 1].y always ends cell c's points
//   B_KNN_INDICES   n x K uint out: neighbours' indices in the caller's order, nearest first
//   B_KNN_DISTANCES n x K float out: their distances, metres; rows in the caller's order
// Defines: K (neighbours, <= 32). Uniforms below.
#if defined COMPUTE_SHADER

layout(local_size_x = 64) in;

layout(std430, binding = B_KNN_POINTS) readonly buffer Points { vec4 points[]; };
layout(std430, binding = B_KNN_COLUMNS) readonly buffer Columns { uint columns[]; };
layout(std430, binding = B_KNN_CELLS) readonly buffer Cells { uvec2 cells[]; };
layout(std430, binding = B_KNN_INDICES) writeonly buffer Indices { uint out_idx[]; };
layout(std430, binding = B_KNN_DISTANCES) writeonly buffer Distances { float out_dist[]; };

uniform uint u_first;   // this dispatch's first query (position in B_KNN_POINTS)
uniform uint u_count;   // its number of queries
uniform vec3 u_origin;  // the grid's lower corner, metres
uniform float u_cell;   // cell edge, metres
uniform ivec3 u_dims;   // cells along x, y, z
// metres taken off every box and ring distance before it prunes: the CPU binned the points in
// float64, this shader recomputes cell faces in float32 (a few ulps of the bucket's extent apart),
// so a pruning distance may only err short, which costs a cell visit, never a neighbour
uniform float u_slack;

float best_d[K];  // squared distances, ascending
uint best_i[K];   // positions in B_KNN_POINTS
uint found;

void consider(float d2, uint j) {
    if (found == K && d2 >= best_d[K - 1]) return;
    int s = int(min(found, uint(K - 1)));  // the slot freed: past the end, or the K-th best dropped
    if (found < K) found++;
    for (; s > 0 && best_d[s - 1] > d2; s--) {  // strict: among equals the first found stays first
        best_d[s] = best_d[s - 1];
        best_i[s] = best_i[s - 1];
    }
    best_d[s] = d2;
    best_i[s] = j;
}

float pruned(float gap) { return max(gap - u_slack, 0.0); }

// the points of column `col`'s cells with z in [z0, z1], the column's xy box at squared distance dxy2
void scan(vec3 q, uint self, int col, int z0, int z1, float dxy2) {
    uint lo = columns[col], hi = columns[col + 1];
    while (lo < hi) {  // the first cell with z >= z0
        uint mid = (lo + hi) >> 1;
        if (int(cells[mid].x) < z0) lo = mid + 1; else hi = mid;
    }
    hi = columns[col + 1];
    for (uint c = lo; c < hi; c++) {
        uvec2 cell = cells[c];
        int z = int(cell.x);
        if (z > z1) break;
        if (found == K) {
            float zlo = u_origin.z + float(z) * u_cell;
            float dz = pruned(max(max(zlo - q.z, q.z - zlo - u_cell), 0.0));
            if (dxy2 + dz * dz > best_d[K - 1]) {
                if (zlo > q.z) break;  // the cells above are farther still
                continue;
            }
        }
        uint end = cells[c + 1].y;
        for (uint p = cell.y; p < end; p++) {
            if (p == self) continue;
            vec3 d = points[p].xyz - q;
            consider(dot(d, d), p);
        }
    }
}

void main() {
    if (gl_GlobalInvocationID.x >= u_count) return;
    uint self = u_first + gl_GlobalInvocationID.x;
    vec4 pq = points[self];
    vec3 q = pq.xyz;
    ivec3 c = clamp(ivec3(floor((q - u_origin) / u_cell)), ivec3(0), u_dims - 1);
    best_d[0] = 0.0;
    best_i[0] = self;
    found = 1u;
    ivec3 far = max(c, u_dims - 1 - c);
    int rmax = max(far.x, max(far.y, far.z));  // the ring that covers the whole grid
    for (int r = 0; r <= rmax; r++) {
        for (int dy = -r; dy <= r; dy++) {
            int y = c.y + dy;
            if (y < 0 || y >= u_dims.y) continue;
            float ylo = u_origin.y + float(y) * u_cell;
            float gy = pruned(max(max(ylo - q.y, q.y - ylo - u_cell), 0.0));
            for (int dx = -r; dx <= r; dx++) {
                int x = c.x + dx;
                if (x < 0 || x >= u_dims.x) continue;
                float xlo = u_origin.x + float(x) * u_cell;
                float gx = pruned(max(max(xlo - q.x, q.x - xlo - u_cell), 0.0));
                float dxy2 = gx * gx + gy * gy;
                if (found == K && dxy2 > best_d[K - 1]) continue;
                int col = y * u_dims.x + x;
                if (max(abs(dx), abs(dy)) == r) {  // a column on the ring's side: all its ring's cells
                    scan(q, self, col, c.z - r, c.z + r, dxy2);
                } else {  // inside the ring: its top and bottom cells only
                    scan(q, self, col, c.z - r, c.z - r, dxy2);
                    scan(q, self, col, c.z + r, c.z + r, dxy2);
                }
            }
        }
        // nothing unvisited is nearer than the block's faces that have cells beyond them
        float bound = 3.0e38;
        vec3 lo = u_origin + vec3(c - r) * u_cell, hi = u_origin + vec3(c + r + 1) * u_cell;
        for (int a = 0; a < 3; a++) {
            if (c[a] - r > 0) bound = min(bound, q[a] - lo[a]);
            if (c[a] + r < u_dims[a] - 1) bound = min(bound, hi[a] - q[a]);
        }
        bound = pruned(bound);
        if (found == K && best_d[K - 1] <= bound * bound) break;
    }
    uint row = floatBitsToUint(pq.w);
    for (int s = 0; s < K; s++) {
        out_idx[row * uint(K) + uint(s)] = floatBitsToUint(points[best_i[s]].w);
        out_dist[row * uint(K) + uint(s)] = sqrt(best_d[s]);
    }
}

#endif
