"""The per-point kernels of :mod:`dmrt.preprocess.normals`: exact k-nearest-neighbour search, PCA
normals and splat radii from neighbour distances.

* :class:`KnnTree`: exact kNN queries over fixed points (pykdtree: a kd-tree in C whose queries run
  on OpenMP threads), with ``cKDTree.query``'s signature and neighbours.
* :func:`pca_normals`: the least-squares plane of each neighbourhood, from its 3x3 covariance's
  smallest eigenvector in closed form (:func:`smallest_eigenvectors`), vectorised over cache-sized
  blocks, within 1e-5 degrees of ``np.linalg.eigh``.
* :func:`neighbourhoods`: normals and the radius neighbour's distance from one query of
  ``max(k_normals, k_radius + 1)`` neighbours, on all cores.

Per point on one core, a bucket of 1M points of bench_octree's site with k = 16
(``python -m bench.bench_normals --kernels``, best of 3): the query 2.9 -> 1.8 us (cKDTree ->
pykdtree), the normals 3.0 -> 0.5 us (batched eigh -> closed form), the whole kernel
6.2 -> 2.5 us (again at 4b7640b, calm: 5.82 -> 2.49 us, 2.34x, the query 1.85 of it). The
query is now three quarters of it.

What stops the query there (#40 asks >= 3x, i.e. <= ~1.9 us for the kernel): the variants tried
for it, on the same bucket (``python -m bench.bench_normals --query-variants``: CPU us per
point of the 16-NN query, best of 3, interleaved, on one core of this 2-core machine while other
jobs ran: load 3, two runs), and their instructions and last-level misses per query
(cachegrind, 100k queries, an 8 MiB LL standing for one core's share of a shared L3):

==============================  ===========  ===========  =============================
variant                         run 1 (us)   run 2 (us)   cachegrind per query
==============================  ===========  ===========  =============================
plain (octree order, leaf 16)   2.98         2.14         11,578 instr., 22 LL misses
Morton-ordered queries          2.51         2.13
Morton-ordered tree             2.43         2.01
Morton tree and queries         2.16         2.17         11,528 instr., 12 LL misses
float32                         2.77         2.48
leafsize 8 / 12                 2.79 / 2.92  2.31 / 2.21  8: 11,265 instr.
leafsize 24 / 32                2.76 / 2.62  2.19 / 2.04  32: 12,889 instr.
distance_upper_bound (max)      2.44         2.02         at the median d16: 10,635
==============================  ===========  ===========  =============================

On a calm core (load 1.4) plain and Morton-ordered tree and queries took 1.74 and 1.75 us. The
query is bound by pykdtree's instructions, ~11,500 per query whatever the order, dtype, leaf size or
bound: it computes ~200 distances for 16 neighbours (``calc_dist``) and spends 40 % of its
instructions in its sorted insertion (``insert_point``). Spatial order halves the simulated cache
misses, which could matter only where one core's share of the last-level cache is small (here the
24 MB of points fit in a 300 MiB L3); the run-to-run noise (+-30 %) is larger than any variant's
difference, and none is kept. Beyond this takes another search: an exact grid kNN (cells of about the 16th-neighbour
distance, visited ring by ring with box-distance pruning) scans 32-43 candidates per query instead
of ~200; a numba prototype gave the same neighbours and distances bit for bit, its query 15-30 %
faster than pykdtree's in the same runs but its build (a counting sort into cells) 0.3-0.5 us per
point slower: 10-20 % of the kernel, not enough for a new dependency without further work (or the
GPU, #40).
"""

from __future__ import annotations

import math

import numpy as np
from pykdtree.kdtree import KDTree

from dmrt.preprocess.parallel import default_workers

__all__ = ["KnnTree", "pca_normals", "smallest_eigenvectors", "radius_factor", "neighbourhoods", "on_threads", "PCA_RUN",
           "kernel"]


def kernel() -> str:
    """What ``bundle.json`` records as the kNN kernel (``normals_radii.kernel``)."""
    from importlib.metadata import version

    return f"pykdtree {version('pykdtree')} exact kNN, closed-form PCA"

# rows per PCA block: the block's (k, rows, 3) float64 neighbourhood and its products stay in the
# L2 cache (16 x 2048 x 24 B = 768 KiB); blocks of 16,384 rows measured 10-40 % slower, numpy's
# element-wise passes then streaming from memory. The eigenvectors are solved per run of blocks, as
# their ~80 numpy calls cost ~0.1 us per row in Python overhead on a block alone.
_BLOCK = 2048
PCA_RUN = 16 * _BLOCK  # rows a thread of pca_normals solves at once (on_threads' run)
# rows per kNN query: OpenMP threads share one query; this bounds its (rows, k) results
# (16 neighbours: 192 MiB of distances and indices)
_CHUNK = 1 << 20


class KnnTree:
    """Exact k-nearest-neighbour queries over fixed points.

    Parameters
    ----------
    points : (m, 3) float64
        Metres, best centred near the origin (the squared distances keep their digits there).
    leafsize : int
        Points per leaf: 8 to 32 within the timing noise for k = 16, 8 slower in a calm run; 16 is
        within 3 % of the fewest instructions per query (module doc).
    """

    def __init__(self, points: np.ndarray, leafsize: int = 16):
        self.data = np.ascontiguousarray(points, dtype=np.float64)
        if self.data.ndim != 2 or self.data.shape[1] != 3:
            raise ValueError(f"points must have shape (m, 3), got {self.data.shape}")
        self.n = len(self.data)
        self._tree = KDTree(self.data, leafsize=leafsize) if self.n else None

    def query(self, x: np.ndarray, k: int, workers: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The ``k`` nearest points of each row of ``x``, nearest first (as ``cKDTree.query``).

        Parameters
        ----------
        x : (b, 3) float
        k : int
            At most the number of points.
        workers : int, optional
            Accepted for ``cKDTree.query``'s signature; the threads are OpenMP's, one per core or
            ``OMP_NUM_THREADS`` (1 in :class:`dmrt.preprocess.parallel.ProcessPool`'s workers).

        Returns
        -------
        d : (b, k) float64 distances, metres.
        idx : (b, k) unsigned int indices into the points (uint32 below 2**32 points).
        """
        k = int(k)
        if not 1 <= k <= self.n:
            # pykdtree pads missing neighbours with an out-of-range index: refuse rather than return it
            raise ValueError(f"k = {k} neighbours of {self.n} points")
        x = np.ascontiguousarray(x, dtype=np.float64).reshape(-1, 3)
        d, idx = self._tree.query(x, k=k)
        return d.reshape(len(x), k), idx.reshape(len(x), k)


def smallest_eigenvectors(a11, a22, a33, a12, a13, a23) -> np.ndarray:
    """Unit eigenvectors of the smallest eigenvalue of symmetric 3x3 matrices, in closed form.

    Parameters
    ----------
    a11, a22, a33, a12, a13, a23 : (b,) float64
        The matrices' entries (positive semi-definite here: covariances).

    Returns
    -------
    (b, 3) float64 unit vectors, sign arbitrary. Where the smallest eigenvalue is double (collinear
    neighbours) any unit vector of its plane; where it is triple (all neighbours equal) (0, 0, 1).

    Notes
    -----
    The eigenvalue: with ``q = tr(A) / 3``, ``p = sqrt(tr((A - qI)^2) / 6)`` and
    ``r = det((A - qI) / p) / 2``, ``lambda_min = q + 2 p cos(acos(r) / 3 + 2 pi / 3)``. The rows of
    ``A - lambda_min I`` span the plane orthogonal to its eigenvector, so their largest cross product
    is that eigenvector. Near a flat neighbourhood's ``r = 1`` the acos amplifies rounding to
    ``sqrt(eps) p`` in ``lambda_min``: in float64 ``1e-8 p``, which tilts the eigenvector by
    ``1e-8 p / (lambda_mid - lambda_min)`` radians, negligible unless the neighbourhood is nearly a line.
    """
    q = (a11 + a22 + a33) / 3.0
    b11, b22, b33 = a11 - q, a22 - q, a33 - q
    p = np.sqrt((b11 * b11 + b22 * b22 + b33 * b33 + 2.0 * (a12 * a12 + a13 * a13 + a23 * a23)) / 6.0)
    det = b11 * (b22 * b33 - a23 * a23) - a12 * (a12 * b33 - a23 * a13) + a13 * (a12 * a23 - b22 * a13)
    with np.errstate(invalid="ignore", divide="ignore"):
        r = np.clip(det / (2.0 * p * p * p), -1.0, 1.0)
    r[~np.isfinite(r)] = 1.0  # p = 0: all eigenvalues equal, lambda = q
    lam = q + 2.0 * p * np.cos(np.arccos(r) / 3.0 + 2.0 * math.pi / 3.0)
    m11, m22, m33 = a11 - lam, a22 - lam, a33 - lam
    # rows (m11, a12, a13), (a12, m22, a23), (a13, a23, m33); their pairwise cross products
    cr = np.stack([
        np.stack([a12 * a23 - a13 * m22, a13 * a12 - m11 * a23, m11 * m22 - a12 * a12]),
        np.stack([a12 * m33 - a13 * a23, a13 * a13 - m11 * m33, m11 * a23 - a12 * a13]),
        np.stack([m22 * m33 - a23 * a23, a23 * a13 - a12 * m33, a12 * a23 - m22 * a13]),
    ])  # (3 pairs, 3 components, b)
    norm2 = np.einsum("pcb,pcb->pb", cr, cr)
    best = norm2.argmax(axis=0)
    cols = np.arange(len(best))
    v = cr[best, :, cols]  # (b, 3)
    n2 = norm2[best, cols]
    # rank <= 1 (the smallest eigenvalue double or triple): the cross products are rounding noise,
    # orders below the rows' squared norms (each row at most lambda_max - lambda_min <= 3q, the
    # eigenvalues being >= 0); the eigenvectors are then every vector orthogonal to the largest
    # row (or every vector, that row being 0)
    flat = ~(n2 > 1e-20 * (3.0 * q) ** 4)
    if flat.any():
        f = np.flatnonzero(flat)
        rows = np.stack([np.stack([m11[f], a12[f], a13[f]], 1), np.stack([a12[f], m22[f], a23[f]], 1),
                         np.stack([a13[f], a23[f], m33[f]], 1)])  # (3 rows, f, 3)
        big = np.einsum("rfc,rfc->rf", rows, rows).argmax(axis=0)
        v[f] = _orthogonal(rows[big, np.arange(len(f))])
        n2[f] = 1.0
    return v / np.sqrt(n2)[:, None]


def _orthogonal(u: np.ndarray) -> np.ndarray:
    """(b, 3) unit vectors orthogonal to the rows of ``u`` (b, 3); (0, 0, 1) for a zero row."""
    axis = np.eye(3)[np.abs(u).argmin(axis=1)]  # the axis least parallel to u
    w = np.cross(u, axis)
    n = np.linalg.norm(w, axis=1, keepdims=True)
    return np.where(n > 0, w / np.where(n > 0, n, 1.0), [0.0, 0.0, 1.0])


def pca_normals(data: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Least-squares plane normals of neighbourhoods.

    Parameters
    ----------
    data : (m, 3) float64 metres, centred near the origin
    idx : (b, k) int indices into ``data``, k >= 3

    Returns
    -------
    (b, 3) float64 unit normals (sign arbitrary), within 1e-5 degrees of the covariance's smallest
    eigenvector by ``np.linalg.eigh`` (tests/test_knn.py).
    """
    b, k = idx.shape
    out = np.empty((b, 3), np.float64)
    cov = np.empty((6, min(b, PCA_RUN)), np.float64)  # xx, yy, zz, xy, xz, yz of a run of rows
    # the blocks' arrays, allocated once: fresh ones of this size come from mmap, and their page
    # faults cost as much as the arithmetic
    buf, rot = np.empty(k * _BLOCK * 3), np.empty(k * _BLOCK * 3)
    for r in range(0, b, PCA_RUN):
        e = min(b, r + PCA_RUN)
        for s in range(r, e, _BLOCK):
            t = min(e, s + _BLOCK)
            shape = (k, t - s, 3)
            # (k, rows, 3): whole 24-byte rows, the fastest gather ("clip": the tree's indices are
            # in range, and so unchecked and unbuffered)
            x = np.take(data, idx[s:t].T, axis=0, out=buf[:math.prod(shape)].reshape(shape), mode="clip")
            # relative to each neighbourhood's first point: small numbers, whose products lose no
            # digits to the bucket's coordinates
            x -= x[:1]
            y = np.take(x, [1, 2, 0], axis=2, out=rot[:math.prod(shape)].reshape(shape), mode="clip")
            m = x.sum(axis=0) / k
            sq = np.einsum("kbi,kbi->bi", x, x) / k - m * m
            cr = np.einsum("kbi,kbi->bi", x, y) / k - m * m[:, [1, 2, 0]]  # xy, yz, zx
            cov[:3, s - r:t - r] = sq.T
            cov[3:, s - r:t - r] = cr[:, [0, 2, 1]].T
        out[r:e] = smallest_eigenvectors(*cov[:, :e - r])
    return out


# The radius factor. For points on a square grid of spacing h, the discs of radius h/sqrt(2) (half
# the cell diagonal) are the smallest that cover the plane: each cell's centre is h/sqrt(2) from its
# four corner points. A grid point's 8 nearest neighbours (itself excluded) are the ring of its 3x3
# block, the farthest of them diagonal at sqrt(2)*h, so radius = d_8 / 2 gives exactly h/sqrt(2).
# For other k we keep the same radius for the same density: on a surface d_k grows like sqrt(k)
# (k ~ pi d_k^2 * density), hence radius = d_k / 2 * sqrt(8 / k).
# Irregular (random) sampling has larger gaps than a grid of the same density: there a ``scale`` of
# about 1.5 closes nearly all holes (a Poisson sample of density rho leaves exp(-pi rho r^2) of the
# plane uncovered: 1 % at r = 1.2 / sqrt(rho), i.e. scale ~1.5 on top of the grid factor).
def radius_factor(k: int) -> float:
    """Radius / (distance to the k-th neighbour) for gap-free discs on a square grid: ``sqrt(8/k)/2``."""
    return 0.5 * math.sqrt(8.0 / k)


def on_threads(n: int, rows: int, work) -> None:
    """``work(start, stop)`` over ``range(n)`` in runs of ``rows``, on one thread per core (numpy
    releases the GIL in its loops). Each call writes its own rows of the caller's output."""
    from concurrent.futures import ThreadPoolExecutor

    starts = range(0, n, rows)
    threads = min(len(starts), default_workers())
    if threads <= 1:
        for s in starts:
            work(s, min(n, s + rows))
        return
    with ThreadPoolExecutor(threads) as pool:
        for f in [pool.submit(work, s, min(n, s + rows)) for s in starts]:
            f.result()


def neighbourhoods(tree: KnnTree, c: np.ndarray, k_normals: int | None = None,
                   k_radius: int | None = None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """PCA normals and/or the radius neighbour's distance of every point of ``c``, from one query.

    Parameters
    ----------
    tree : KnnTree over ``c``
    c : (n, 3) float64 metres, centred near the origin
    k_normals : int, optional
        Neighbourhood of the plane fit, the point included (3 <= k_normals <= n).
    k_radius : int, optional
        Rank of the radius neighbour, the point excluded (1 <= k_radius < n).

    Returns
    -------
    normals : (n, 3) float64 unit normals, sign arbitrary (None without ``k_normals``).
    d_k : (n,) float64 distance to the ``k_radius``-th other point, metres (None without ``k_radius``).
    """
    n = len(c)
    kq = max(k_normals or 1, k_radius + 1 if k_radius else 1)
    normals = np.empty((n, 3), np.float64) if k_normals else None
    d_k = np.empty(n, np.float64) if k_radius else None
    for a in range(0, n, _CHUNK):
        b = min(n, a + _CHUNK)
        d, idx = tree.query(c[a:b], kq)  # on OpenMP's threads
        if k_radius:
            d_k[a:b] = d[:, k_radius]
        if k_normals:
            def work(s, e):
                normals[a + s:a + e] = pca_normals(c, idx[s:e, :k_normals])

            on_threads(b - a, PCA_RUN, work)
    return normals, d_k
