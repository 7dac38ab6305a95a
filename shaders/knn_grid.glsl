// Exact k nearest neighbours of every point of a bucket among the bucket's points, over a uniform
// grid that dmrt/preprocess/gpu_knn.py (GridKnn) builds on the CPU: one invocation per query point
// visits the grid's (x, y) columns in square rings of growing radius around its own, scanning each
// along z; it keeps its K best (squared distance, point) sorted by insertion, skips columns and
// cells whose box is farther than its K-th best, and stops once the ring's sides are farther than
// its K-th best (nothing outside can be nearer). The query point is its own first neighbour
// (distance 0), as KnnTree.query gives it. Mesa llvmpipe ends a shader's loops after 65,535
// iterations in all (LP_MAX_TGSI_LOOP_ITERATIONS), silently: tests keep the rings few.
//
// Buffers (binding points in dmrt/gl/abi.py):
//   B_KNN_POINTS    n Point: float32 metres from the bucket's centre, sorted by cell (by column,
//                   then z), and the point's index in the caller's order
//   B_KNN_COLUMNS   nx * ny + 1 uint: where column (x, y) = y * nx + x starts in B_KNN_CELLS
//   B_KNN_CELLS     cells + 1 uvec2: the cell's z index and its first point in B_KNN_POINTS; the
//                   last is (0xFFFFFFFF, n), so cells[c + 1].y always ends cell c's points
//   B_KNN_INDICES   n x K uint out: neighbours' indices in the caller's order, nearest first
//   B_KNN_DISTANCES n x K float out: their distances, metres; rows in the caller's order
// Defines: K (neighbours, <= 32). Uniforms below.
#if defined COMPUTE_SHADER

layout(local_size_x = 64) in;

// 16 bytes; the index is no float's bits: a denormal may be flushed to zero on its way
struct Point { float x, y, z; uint id; };
layout(std430, binding = B_KNN_POINTS) readonly buffer Points { Point points[]; };
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
    uint s = found < uint(K) ? found++ : uint(K - 1);  // the slot freed: past the end, or the K-th best dropped
    for (; s > 0u && best_d[s - 1u] > d2; s--) {  // strict: among equals the first found stays first
        best_d[s] = best_d[s - 1u];
        best_i[s] = best_i[s - 1u];
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
            Point o = points[p];
            vec3 d = vec3(o.x, o.y, o.z) - q;
            consider(dot(d, d), p);
        }
    }
}

// the column (x, y): its cells that may hold a point nearer than the K-th best (all of them until
// K points are known)
void column(vec3 q, uint self, int x, int y) {
    float xlo = u_origin.x + float(x) * u_cell, ylo = u_origin.y + float(y) * u_cell;
    float gx = pruned(max(max(xlo - q.x, q.x - xlo - u_cell), 0.0));
    float gy = pruned(max(max(ylo - q.y, q.y - ylo - u_cell), 0.0));
    float dxy2 = gx * gx + gy * gy;
    int z0 = -1, z1 = u_dims.z;
    if (found == K) {
        if (dxy2 > best_d[K - 1]) return;
        // one cell more each way: the cells' faces are float32 here and float64 in the binning
        float w = sqrt(best_d[K - 1] - dxy2) + u_slack;
        z0 = int(floor((q.z - w - u_origin.z) / u_cell)) - 1;
        z1 = int(floor((q.z + w - u_origin.z) / u_cell)) + 1;
    }
    scan(q, self, y * u_dims.x + x, z0, z1, dxy2);
}

void main() {
    if (gl_GlobalInvocationID.x >= u_count) return;
    uint self = u_first + gl_GlobalInvocationID.x;
    Point pq = points[self];
    vec3 q = vec3(pq.x, pq.y, pq.z);
    ivec2 c = clamp(ivec2(floor((q.xy - u_origin.xy) / u_cell)), ivec2(0), u_dims.xy - 1);
    best_d[0] = 0.0;
    best_i[0] = self;
    found = 1u;
    ivec2 far = max(c, u_dims.xy - 1 - c);
    int rmax = max(far.x, far.y);  // the ring that covers the whole grid
    // square rings of columns, each scanned along z: a ring costs its 8 r columns (cubic shells
    // would cost ~24 r^2 cells, most of them empty around a surface)
    for (int r = 0; r <= rmax; r++) {
        int x0 = max(c.x - r, 0), x1 = min(c.x + r, u_dims.x - 1);
        int y0 = max(c.y - r + 1, 0), y1 = min(c.y + r - 1, u_dims.y - 1);
        if (c.y - r >= 0) for (int x = x0; x <= x1; x++) column(q, self, x, c.y - r);
        if (r > 0 && c.y + r < u_dims.y) for (int x = x0; x <= x1; x++) column(q, self, x, c.y + r);
        if (r > 0 && c.x - r >= 0) for (int y = y0; y <= y1; y++) column(q, self, c.x - r, y);
        if (r > 0 && c.x + r < u_dims.x) for (int y = y0; y <= y1; y++) column(q, self, c.x + r, y);
        // nothing unvisited is nearer than the ring's sides that have columns beyond them
        float bound = 3.0e38;
        vec2 lo = u_origin.xy + vec2(c - r) * u_cell, hi = u_origin.xy + vec2(c + r + 1) * u_cell;
        for (int a = 0; a < 2; a++) {
            if (c[a] - r > 0) bound = min(bound, q[a] - lo[a]);
            if (c[a] + r < u_dims[a] - 1) bound = min(bound, hi[a] - q[a]);
        }
        bound = pruned(bound);
        if (found == K && best_d[K - 1] <= bound * bound) break;
    }
    for (int s = 0; s < K; s++) {
        out_idx[pq.id * uint(K) + uint(s)] = points[best_i[s]].id;
        out_dist[pq.id * uint(K) + uint(s)] = sqrt(best_d[s]);
    }
}

#endif
