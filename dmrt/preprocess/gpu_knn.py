"""Exact k-nearest-neighbour search of a bucket's points among themselves on the GPU, for #40: the
kNN query is three quarters of the CPU kernel (:mod:`dmrt.preprocess.knn`, whose module doc says
why pykdtree stops there).

* :class:`GridKnn`: the points binned into a uniform grid on the CPU (one sort by cell), then one
  GPU invocation per point searches the cells ring by ring (``shaders/knn_grid.glsl``), giving the
  same neighbours as :meth:`dmrt.preprocess.knn.KnnTree.query` of the points themselves, to float32
  rounding.
* :func:`grid_neighbourhoods`: :func:`dmrt.preprocess.knn.neighbourhoods`'s results (PCA normals,
  the radius neighbour's distance) from that search.

The cell edge sets the work per query: cells much smaller than the k-th neighbour distance make
the search walk many empty cells, much larger ones scan many far points. It is chosen so that an
occupied cell holds ``cell_points`` points on average (about k / 2: a surface crosses ~9-15 cells
of the 3 x 3 x 3 block around a point, whose k nearest then mostly lie within that block).
"""

from __future__ import annotations

import math

import moderngl
import numpy as np

from dmrt.gl import abi, get_context, load_program, set_uniforms
from dmrt.gl.kernels import max_groups
from dmrt.preprocess.knn import PCA_RUN, on_threads, pca_normals

__all__ = ["GridKnn", "grid_neighbourhoods", "MAX_K"]

MAX_K = 32  # neighbours a query keeps in its invocation's registers (or spilled local memory)
_GROUP = 64  # shaders/knn_grid.glsl's local_size_x
# queries per dispatch: drivers end a dispatch that runs for seconds (a watchdog or a Mesa
# timeout), and 2**20 queries of ~100 candidates are milliseconds on a GPU
_SLICE = 1 << 20
# sample for the cell edge: enough points for the density's scaling exponent, few enough for
# its np.unique calls to cost little against the bucket's sort
_SAMPLE = 1 << 16


def _bounds(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The lower and upper corners (3,) float64 of points ``p`` (n, 3); column by column, ten
    times faster than numpy's reduction along axis 0 of an (n, 3) array."""
    return (np.array([p[:, a].min() for a in range(3)], np.float64),
            np.array([p[:, a].max() for a in range(3)], np.float64))


def _cell_keys(p: np.ndarray, lo: np.ndarray, h: float, dims) -> np.ndarray:
    """(n,) int64 cell of each point of ``p`` (n, 3) in the grid of corner ``lo``, edge ``h`` and
    ``dims`` cells: ``(y * nx + x) * nz + z``, i.e. by (x, y) column, then z."""
    key = np.zeros(len(p), np.int64)
    for a, scale in ((1, dims[0]), (0, dims[2]), (2, 1)):
        i = np.floor((p[:, a] - lo[a]) / h).astype(np.int64)
        np.minimum(i, dims[a] - 1, out=i)
        key += i
        key *= scale
    return key


def _occupancy(p: np.ndarray, lo: np.ndarray, h: float, ext: np.ndarray) -> float:
    """Mean points per occupied cell of edge ``h`` for points ``p`` (m, 3) float64 within the box
    of corner ``lo`` and extent ``ext``."""
    return len(p) / len(np.unique(_cell_keys(p, lo, h, np.floor(ext / h).astype(np.int64) + 1)))


def cell_edge(p: np.ndarray, cell_points: float, lo: np.ndarray, ext: np.ndarray) -> float:
    """A grid cell edge whose occupied cells hold about ``cell_points`` of the points ``p``.

    Parameters
    ----------
    p : (n, 3) float metres
    cell_points : float
    lo, ext : (3,) float64
        The points' lower corner and extent, metres.

    Returns
    -------
    float, metres (> 0). From a sample of the points: its occupancy at two cell sizes gives the
    exponent of points per cell against the edge (2 on surfaces, 3 in volumes), which scales the
    edge to the whole cloud's density.
    """
    n = len(p)
    size = float(ext.max())
    if n < 2 or size == 0.0:
        return 1.0
    m = min(n, _SAMPLE)
    s = p[np.random.default_rng(0).choice(n, m, replace=False)] if m < n else p
    s = s.astype(np.float64)
    # volume-filling start (too large on surfaces: those then show a larger occupancy)
    vol = float(np.prod(np.maximum(ext, size * 1e-3)))
    h1 = (vol * cell_points / m) ** (1.0 / 3.0)
    p1, p2 = _occupancy(s, lo, h1, ext), _occupancy(s, lo, h1 / 2, ext)
    e = float(np.clip(np.log2(p1 / p2), 1.0, 3.0)) if p2 > 0 else 3.0
    h = h1 / 2 * (cell_points * m / (n * p2)) ** (1.0 / e)
    return max(h, size * 1e-6)


class GridKnn:
    """Exact k nearest neighbours of every point among the same points, on the GPU.

    Parameters
    ----------
    points : (n, 3) float
        Metres (converted to float32 about their bounding box's centre: the distances keep their
        digits there).
    cell_points : float, optional
        Mean points per occupied grid cell (default 8: about k / 2 for k = 16); a speed knob only,
        the result is exact for any value.
    ctx : moderngl.Context, optional
        Default :func:`dmrt.gl.get_context`.

    Attributes
    ----------
    cell : float
        The grid's cell edge, metres.
    dims : (3,) int
        Cells along x, y, z.
    n_cells : int
        Occupied cells.
    """

    def __init__(self, points: np.ndarray, cell_points: float = 8.0, ctx=None):
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ValueError(f"points must have shape (n, 3), got {p.shape}")
        self.n = len(p)
        self.ctx = ctx or get_context()
        if self.n == 0:
            return
        c32 = (p - sum(_bounds(p)) / 2).astype(np.float32)  # what the GPU sees: binned as such
        lo, hi = _bounds(c32)
        ext = hi - lo
        h = cell_edge(c32, cell_points, lo, ext)
        # the dense column table (nx * ny uints) stays within a few times the points
        h = max(h, math.sqrt(ext[0] * ext[1] / (4.0 * self.n + 4096)), float(ext.max()) / 32767)
        dims = np.floor(ext / h).astype(np.int64) + 1
        key = _cell_keys(c32, lo, h, dims)
        order = np.argsort(key)
        key = key[order]
        first = np.flatnonzero(np.r_[True, key[1:] != key[:-1]])
        cell_key = key[first]
        cells = np.empty((len(first) + 1, 2), np.uint32)
        cells[:-1, 0] = cell_key % dims[2]
        cells[:-1, 1] = first
        cells[-1] = (0xFFFFFFFF, self.n)
        columns = np.zeros(dims[0] * dims[1] + 1, np.uint32)
        np.cumsum(np.bincount(cell_key // dims[2], minlength=dims[0] * dims[1]), out=columns[1:])
        pts = np.empty((self.n, 4), np.float32)  # struct Point: x, y, z, then the uint index
        np.take(c32, order, axis=0, out=pts[:, :3])
        pts.view(np.uint32)[:, 3] = order
        self.cell, self.dims, self.n_cells = float(h), dims, len(first)
        self._origin = tuple(float(x) for x in lo.astype(np.float32))
        self._buffers = {abi.B_KNN_POINTS: self.ctx.buffer(pts.tobytes()),
                         abi.B_KNN_COLUMNS: self.ctx.buffer(columns.tobytes()),
                         abi.B_KNN_CELLS: self.ctx.buffer(cells.tobytes())}
        # a few float32 ulps of the grid's farthest coordinate (see u_slack in the shader)
        self._slack = float(8 * np.finfo(np.float32).eps * (np.abs(lo).max() + float(dims.max()) * h))

    def query(self, k: int) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest points of every point, itself first, nearest first.

        Parameters
        ----------
        k : int
            1 <= k <= min(n, MAX_K).

        Returns
        -------
        d : (n, k) float32 distances, metres (float32 positions about the bounding box's centre).
        idx : (n, k) uint32 indices into the points, in the caller's order.
        """
        k = int(k)
        if not 1 <= k <= self.n:
            raise ValueError(f"k = {k} neighbours of {self.n} points")
        if k > MAX_K:
            raise ValueError(f"k = {k} neighbours: the GPU grid search keeps at most {MAX_K}")
        if self.n * k >= 2**32:
            raise ValueError(f"{self.n} points x {k} neighbours: more results than uint32 indices address")
        ctx = self.ctx
        program = load_program(ctx, "knn_grid", {"K": k})
        idx_buf = ctx.buffer(reserve=self.n * k * 4)
        dist_buf = ctx.buffer(reserve=self.n * k * 4)
        try:
            for binding, buf in {**self._buffers, abi.B_KNN_INDICES: idx_buf, abi.B_KNN_DISTANCES: dist_buf}.items():
                buf.bind_to_storage_buffer(binding)
            set_uniforms(program, u_origin=self._origin, u_cell=self.cell, u_dims=tuple(int(x) for x in self.dims),
                         u_slack=self._slack)
            step = min(_SLICE, max_groups(ctx) * _GROUP)
            for first in range(0, self.n, step):
                count = min(step, self.n - first)
                set_uniforms(program, u_first=first, u_count=count)
                program.run(-(-count // _GROUP))
            ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT)
            idx = np.frombuffer(idx_buf.read(), np.uint32).reshape(self.n, k)
            d = np.frombuffer(dist_buf.read(), np.float32).reshape(self.n, k)
        finally:
            idx_buf.release()
            dist_buf.release()
        return d, idx

    def release(self) -> None:
        """Free the grid's GPU buffers."""
        for buf in getattr(self, "_buffers", {}).values():
            buf.release()
        self._buffers = {}


def grid_neighbourhoods(c: np.ndarray, k_normals: int | None = None, k_radius: int | None = None,
                        cell_points: float = 8.0) -> tuple[np.ndarray | None, np.ndarray | None]:
    """:func:`dmrt.preprocess.knn.neighbourhoods` over the GPU grid search (no tree to pass).

    Parameters
    ----------
    c : (n, 3) float64 metres, centred near the origin
    k_normals : int, optional
        Neighbourhood of the plane fit, the point included (3 <= k_normals <= min(n, MAX_K)).
    k_radius : int, optional
        Rank of the radius neighbour, the point excluded (1 <= k_radius < min(n, MAX_K)).
    cell_points : float
        :class:`GridKnn`'s.

    Returns
    -------
    normals : (n, 3) float64 unit normals, sign arbitrary (None without ``k_normals``).
    d_k : (n,) float64 distance to the ``k_radius``-th other point, metres (None without
        ``k_radius``); float32-exact (positions rounded to float32 about the bucket's centre).
    """
    n = len(c)
    kq = max(k_normals or 1, k_radius + 1 if k_radius else 1)
    grid = GridKnn(c, cell_points)
    try:
        d, idx = grid.query(kq)
    finally:
        grid.release()
    d_k = d[:, k_radius].astype(np.float64) if k_radius else None
    normals = None
    if k_normals:
        normals = np.empty((n, 3), np.float64)

        def work(s, e):
            normals[s:e] = pca_normals(c, idx[s:e, :k_normals])

        on_threads(n, PCA_RUN, work)
    return normals, d_k
