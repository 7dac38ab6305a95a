"""Labeling (paper Section 4.3): one photograph per proxy point, by alpha-expansion graph cut.

Every proxy point ``p`` has a set of *candidate* photos (those in which ``p`` is not occluded,
computed elsewhere). Labeling picks one candidate per point by minimising, on the kNN graph of the
proxy points, the energy

    E(l) = sum_p E_d(p, l_p)  +  sum_{(p,q) in kNN edges} V_pq(l_p, l_q)

with the data term of DMT (Arikan et al. 2014: "favours orthogonal and close views") and the
Lempitsky & Ivanov (CVPR 2007) seam smoothness term ("penalises label changes with strong colour
differences along edges"). Labels are int32 photo indices, ``-1`` where a point has no candidate.

Data term (dimensionless, in *octaves of texel footprint*)
-----------------------------------------------------------
A pixel of photo ``j`` (focal length ``f_j`` pixels, centre ``C_j``) covers, on the surface at
point ``p_i`` (unit normal ``n_i``), a footprint of

    s_ij = d_ij / (f_j * cos θ_ij)      metres per pixel,

``d_ij = |C_j - p_i|`` (metres), ``cos θ_ij = |n_i · (C_j - p_i)| / d_ij`` (clamped below at
``min_cos``; ``|.|`` because scanned normals are often unoriented). Close and orthogonal views give
small footprints, i.e. sharp texture. The data cost is the footprint relative to the best candidate
of the same point, on a log scale:

    E_d(i, j) = w_dist * log2(d_ij / f_j) - w_orth * log2(max(cos θ_ij, min_cos))  -  min_{j'} (same)

With ``w_dist = w_orth = 1`` this is exactly ``log2(s_ij / min_j' s_ij')``: 0 for the sharpest
candidate, 1 for a view with half its linear resolution, 2 for a quarter, ... The log keeps the
term scale-free (metres and pixels cancel) and bounded for grazing views, and subtracting the
per-point minimum is a per-point constant, so it changes the reported energy but never the
optimum. Non-candidates cost ``inf``. The pinhole's off-axis variation of pixel size is ignored
(every pixel is given the on-axis angular size ``1/f``): the exact model favours image borders,
where real photos are worst (distortion, vignetting).

Smoothness term (same units as the data term)
---------------------------------------------
``c_p^a`` is the colour (RGB, 0..1) of point ``p`` as seen in photo ``a``. For an edge ``(p, q)``
with labels ``a = l_p != b = l_q``:

    V_pq(a, b) = λ * (|c_p^a - c_p^b| + |c_q^a - c_q^b|) + λ0,     V_pq(a, a) = 0,

the Lempitsky-Ivanov seam cost (colour disagreement of the two photos at both ends of the edge;
Euclidean RGB distance, so each term is in [0, √3]) plus a constant ``λ0`` so that any label change
costs something. ``λ = smoothness_weight`` is in octaves per unit RGB distance, ``λ0 =
label_change_cost`` in octaves per edge. ``c_p^a`` and ``c_q^b`` always exist (labels are
candidates). Where ``c_p^b`` does not (``b`` is not a candidate of ``p``) the nearest available
sample of photo ``b`` at the seam stands in: ``c_q^b``; likewise ``c_q^a`` falls back to ``c_p^a``.

Minimisation
------------
Alpha-expansion (Boykov, Veksler & Zabih 2001) with PyMaxflow, initialised with winner-take-all
(lowest data cost). The expansion move for label ``α`` only involves the points that have ``α``
as a candidate and do not carry it yet; everything else keeps its label and enters the move as
unary terms of its neighbours. Graphs are built with whole-array numpy calls (one Python loop, over
labels). A sweep visits every label once; sweeps stop when the energy decreases by less than
``tolerance`` (relative), when no point changes, or after ``max_sweeps``. Two economies, both on by
default and both keeping every move energy-decreasing:

* a label is skipped when none of its candidate points or their neighbours changed since its last
  move (its move would pose the same problem again: ``skip_unchanged_labels``);
* after the first sweep, a move lets only the points within ``local_hops`` graph hops of a point
  relabeled since that label's last move switch; the rest of ``α``'s points stay fixed
  (``local_moves``). This is no longer the full expansion move, so the factor-2 bound of
  alpha-expansion (for metric ``V``) is only guaranteed with ``local_moves=False``; on the
  benchmark (1M points, 192 photos) the final energy differs from full moves by ~0.01 % at a
  fraction of the time.

``V`` is not a metric in general (colours differ per point and photo, and some are missing), but
every pairwise term an expansion move builds is submodular: both ends of a pair of graph nodes have
``α`` as a candidate, so with ``E00 = V(a, b)``, ``E01 = V(a, α)``, ``E10 = V(α, b)``, ``E11 = 0``
and ``r_p^b`` the (possibly fallback) colour of ``p`` in ``b``, the triangle inequality gives
``|c_p^a - r_p^b| <= |c_p^a - c_p^α| + |c_p^α - r_p^b|`` (likewise at ``q``), hence
``E00 <= E01 + E10 - λ0``. (This is why the fallback is per edge end and independent of ``α``.)
The solver still guards every pair: a term with ``E00 > E01 + E10`` would be made submodular by
*raising* ``E01`` and ``E10`` by half the violation each (a truncation in the sense of Rother et al.
2005 that over-estimates instead of under-estimating, so the move energy stays an upper bound that
is exact at "keep every label" and the true energy cannot increase); ``truncated_terms`` counts
them (0 in every run so far). Points without a candidate get ``-1`` and are left out of the graph,
and so are their edges.

Sparse input
------------
At scale the dense forms are too big (1M points × 192 photos: 768 MB of float32 costs, 2.3 GB of
colours), so everything runs on :class:`Candidates`, a CSR list of each point's candidate photos
with their colours and data costs (about 15 per point in a real scan). Dense ``(n, m)`` inputs are
accepted everywhere and converted.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import numpy as np

from dmrt.morton import morton_order
from dmrt.options import option, validate

__all__ = [
    "LabelingConfig", "LabelingResult", "Candidates", "data_costs", "candidate_data_costs",
    "knn_edges", "smoothness_costs", "energy", "winner_take_all", "icm", "alpha_expansion",
    "label_points",
]


# --------------------------------------------------------------------------------------------
# configuration and result
# --------------------------------------------------------------------------------------------
@dataclass
class LabelingConfig:
    """Parameters of the labeling energy and of its minimisation (units in the module docstring);
    each field is a ``dmrt preprocess`` option."""

    k_neighbors: int = option(6, "neighbours per point of the kNN graph (the symmetric union: about 0.6 k edges "
                                 "per point)", minimum=1)
    smoothness_weight: float = option(1.0, "lambda, octaves of footprint per unit RGB distance (colours 0..1): a "
                                           "seam where the two photos' colours differ by 0.1 per channel at both "
                                           "ends costs 0.35 octaves per edge", minimum=0.0)
    label_change_cost: float = option(0.1, "lambda0, octaves per kNN edge whose two ends carry different labels",
                                      minimum=0.0)
    distance_weight: float = option(1.0, "w_dist: weight of log2(distance / focal length) in the data term",
                                    minimum=0.0)
    orthogonality_weight: float = option(1.0, "w_orth: weight of -log2(cos theta) (obliqueness) in the data term",
                                         minimum=0.0)
    min_cos: float = option(0.05, "clamp of |cos theta| (0.05 = 87 degrees) so grazing views cost log2(20) = 4.3 "
                                  "octaves, not infinity", minimum=1e-6, maximum=1.0)
    max_sweeps: int = option(5, "alpha-expansion sweeps over all labels at most", minimum=0)
    tolerance: float = option(1e-3, "stop when a sweep lowers the energy by less than this fraction of the energy "
                                    "before it", minimum=0.0)
    skip_unchanged_labels: bool = option(True, "skip a label whose candidate points and their neighbours have not "
                                               "changed since its last move")
    local_moves: bool = option(True, "after the first sweep, let only points next to a change since the label's "
                                     "last move switch (a restricted, still energy-decreasing move; off = full "
                                     "expansion moves every sweep)")
    local_hops: int = option(3, "graph hops around a relabeled point within which local moves may switch points",
                             minimum=0)
    spatial_sort: bool = option(True, "process points in Morton (Z-curve) order: better memory locality, identical "
                                      "energy")

    def __post_init__(self):
        validate(self)


@dataclass
class LabelingResult:
    """Output of :func:`label_points` and :func:`alpha_expansion`.

    Attributes
    ----------
    labels : (n,) int32
        Photo index per point, ``-1`` where the point has no candidate.
    energy_per_sweep : list of float
        Total energy after the winner-take-all initialisation, then after each sweep.
    seconds_per_sweep : list of float
        Wall-clock seconds of each sweep.
    data_energy, smooth_energy : float
        The two parts of the final energy.
    moves_per_sweep, skipped_per_sweep, changed_per_sweep : list of int
        Graph cuts solved, labels skipped as unchanged, and points relabeled, per sweep.
    n_edges : int
        kNN edges in the graph (both ends with a candidate).
    truncated_terms : int
        Pairwise move terms that violated submodularity and were raised (module docstring).
    seconds_setup : float
        kNN graph, data costs and initialisation.
    seconds_total : float
        Everything, end to end.
    """

    labels: np.ndarray
    energy_per_sweep: list = field(default_factory=list)
    seconds_per_sweep: list = field(default_factory=list)
    data_energy: float = 0.0
    smooth_energy: float = 0.0
    moves_per_sweep: list = field(default_factory=list)
    skipped_per_sweep: list = field(default_factory=list)
    changed_per_sweep: list = field(default_factory=list)
    n_edges: int = 0
    truncated_terms: int = 0
    seconds_setup: float = 0.0
    seconds_total: float = 0.0


# --------------------------------------------------------------------------------------------
# sparse candidate lists
# --------------------------------------------------------------------------------------------
@dataclass
class Candidates:
    """Each point's candidate photos, in CSR form.

    Entries ``indptr[i]:indptr[i+1]`` belong to point ``i``, photos ascending within a point.

    Attributes
    ----------
    indptr : (n + 1,) int64
    photos : (nnz,) int32
        Photo index of each entry, ``0 <= photo < n_photos``.
    colors : (nnz, 3) float32
        Colour (RGB 0..1) of the point as seen in that photo.
    n_photos : int
    costs : (nnz,) float32 or None
        Data cost of each entry (:func:`candidate_data_costs`), filled in by :func:`label_points`.
    """

    indptr: np.ndarray
    photos: np.ndarray
    colors: np.ndarray
    n_photos: int
    costs: np.ndarray | None = None

    def __post_init__(self):
        self.indptr = np.asarray(self.indptr, dtype=np.int64)
        self.photos = np.asarray(self.photos, dtype=np.int32)
        nnz = self.photos.size
        if self.colors is None:
            self.colors = np.zeros((nnz, 3), np.float32)
        self.colors = np.asarray(self.colors, dtype=np.float32).reshape(nnz, 3)
        self.n_photos = int(self.n_photos)
        if self.costs is not None:
            self.costs = np.asarray(self.costs, dtype=np.float32).reshape(nnz)
        if self.indptr.ndim != 1 or self.indptr.size < 1 or self.indptr[0] != 0 \
                or self.indptr[-1] != nnz or np.any(np.diff(self.indptr) < 0):
            raise ValueError("Candidates: indptr must rise from 0 to len(photos)")
        if nnz and (self.photos.min() < 0 or self.photos.max() >= self.n_photos):
            raise ValueError(f"Candidates: photo index outside 0..{self.n_photos - 1}")
        if nnz > 1:
            d = np.diff(self.photos)
            start = np.zeros(nnz, bool)
            start[self.indptr[1:-1][self.indptr[1:-1] < nnz]] = True
            if np.any((d <= 0) & ~start[1:]):
                raise ValueError("Candidates: photos must be strictly ascending within a point")

    # -- construction ---------------------------------------------------------------------
    @classmethod
    def _trusted(cls, indptr, photos, colors, n_photos, costs=None) -> "Candidates":
        """Build without the checks of ``__post_init__`` (internal: arrays already valid)."""
        self = object.__new__(cls)
        self.indptr, self.photos, self.colors = indptr, photos, colors
        self.n_photos, self.costs = int(n_photos), costs
        return self

    @classmethod
    def from_dense(cls, candidates, colors=None, costs=None) -> "Candidates":
        """From ``candidates (n, m) bool``, optional ``colors (n, m, 3)`` and ``costs (n, m)``."""
        cand = np.asarray(candidates, dtype=bool)
        n, m = cand.shape
        rows, cols = np.nonzero(cand)  # row-major: sorted by point, then photo
        indptr = np.zeros(n + 1, np.int64)
        np.cumsum(np.bincount(rows, minlength=n), out=indptr[1:])
        col = None if colors is None else np.asarray(colors, np.float32)[rows, cols]
        cst = None if costs is None else np.asarray(costs, np.float32)[rows, cols]
        return cls(indptr, cols.astype(np.int32), col, m, cst)

    @classmethod
    def from_pairs(cls, points, photos, colors, n_points: int, n_photos: int) -> "Candidates":
        """From unordered ``(point, photo)`` pairs (e.g. gathered photo by photo); duplicates dropped."""
        points = np.asarray(points, np.int64).ravel()
        photos = np.asarray(photos, np.int64).ravel()
        key = points * n_photos + photos
        key, first = np.unique(key, return_index=True)
        rows = key // n_photos
        indptr = np.zeros(n_points + 1, np.int64)
        np.cumsum(np.bincount(rows, minlength=n_points), out=indptr[1:])
        col = None if colors is None else np.asarray(colors, np.float32).reshape(-1, 3)[first]
        return cls(indptr, (key % n_photos).astype(np.int32), col, n_photos)

    # -- access ---------------------------------------------------------------------------
    @property
    def n_points(self) -> int:
        return self.indptr.size - 1

    @property
    def nnz(self) -> int:
        return self.photos.size

    def counts(self) -> np.ndarray:
        """(n,) int64: candidates per point."""
        return np.diff(self.indptr)

    def rows(self) -> np.ndarray:
        """(nnz,) int32: the point of each entry."""
        return np.repeat(np.arange(self.n_points, dtype=np.int32), self.counts())

    def keys(self) -> np.ndarray:
        """(nnz,) int64 ascending: ``point * n_photos + photo`` of each entry."""
        return self.rows().astype(np.int64) * self.n_photos + self.photos

    def lookup(self, points, photos, keys=None):
        """Entries of ``(point, photo)`` pairs.

        Returns ``(index (k,) int64, found (k,) bool)``; ``index`` is meaningless where not found.
        """
        keys = self.keys() if keys is None else keys
        q = np.asarray(points, np.int64) * self.n_photos + np.asarray(photos, np.int64)
        idx = np.searchsorted(keys, q)
        idx = np.minimum(idx, max(keys.size - 1, 0))
        found = (keys[idx] == q) if keys.size else np.zeros(q.shape, bool)
        return idx, found

    def take(self, order) -> "Candidates":
        """The candidate lists of points ``order`` (a permutation or subset), in that order."""
        order = np.asarray(order, np.int64)
        cnt = self.counts()[order]
        indptr = np.zeros(order.size + 1, np.int64)
        np.cumsum(cnt, out=indptr[1:])
        ent = _ranges(self.indptr[order], cnt)
        return Candidates._trusted(indptr, self.photos[ent], np.take(self.colors, ent, axis=0),
                                   self.n_photos, None if self.costs is None else self.costs[ent])

    def dense(self):
        """``(candidates (n, m) bool, colors (n, m, 3) float32, costs (n, m) float32 inf-filled)``."""
        n, m = self.n_points, self.n_photos
        r = self.rows()
        cand = np.zeros((n, m), bool)
        cand[r, self.photos] = True
        col = np.zeros((n, m, 3), np.float32)
        col[r, self.photos] = self.colors
        cst = np.full((n, m), np.inf, np.float32)
        if self.costs is not None:
            cst[r, self.photos] = self.costs
        return cand, col, cst


def _ranges(starts, lengths) -> np.ndarray:
    """Concatenation of ``arange(s, s + l)`` for each pair, vectorised. (sum l,) int64."""
    starts = np.asarray(starts, np.int64)
    lengths = np.asarray(lengths, np.int64)
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    nz = lengths > 0
    starts, lengths = starts[nz], lengths[nz]
    ends = np.cumsum(lengths)
    step = np.ones(total, np.int64)
    step[0] = starts[0]
    step[ends[:-1]] = starts[1:] - (starts[:-1] + lengths[:-1]) + 1
    return np.cumsum(step)


def _as_candidates(data, colors) -> Candidates:
    """Normalise the (data, colors) argument pair of the public functions to Candidates with costs."""
    if isinstance(colors, Candidates):
        if data is None:
            if colors.costs is None:
                raise ValueError("no data costs: pass them or fill Candidates.costs")
            return colors
        data = np.asarray(data, np.float32)
        if data.ndim == 2:  # dense costs next to sparse colours
            data = data[colors.rows(), colors.photos]
        return Candidates(colors.indptr, colors.photos, colors.colors, colors.n_photos, data)
    data = np.asarray(data, np.float32)
    if data.ndim != 2:
        raise ValueError("dense data costs must be (n, m); sparse ones need colors=Candidates")
    return Candidates.from_dense(np.isfinite(data), colors, data)


# --------------------------------------------------------------------------------------------
# energy terms
# --------------------------------------------------------------------------------------------
def candidate_data_costs(positions, normals, cam_centers, focal_px, candidates: Candidates,
                         config: LabelingConfig | None = None) -> np.ndarray:
    """Data cost of every candidate entry (formula and units in the module docstring).

    Parameters
    ----------
    positions : (n, 3) float32, metres
    normals : (n, 3) float32, unit length (sign ignored)
    cam_centers : (m, 3) float64, metres
    focal_px : (m,) float, focal length in pixels (``sqrt(fx * fy)``)
    candidates : Candidates

    Returns
    -------
    costs : (nnz,) float32, octaves of footprint above the point's best candidate (min 0 per point)
    """
    cfg = config or LabelingConfig()
    pos = np.asarray(positions)
    n = candidates.n_points
    origin = pos.mean(0, dtype=np.float64) if n else np.zeros(3)
    # float32 structure-of-arrays relative to the points' centroid (exact enough: metres near 0)
    p = [np.ascontiguousarray(pos[:, k] - origin[k], np.float32) for k in range(3)]
    nr = [np.ascontiguousarray(np.asarray(normals)[:, k], np.float32) for k in range(3)]
    c = np.asarray(cam_centers, np.float64).reshape(-1, 3) - origin
    c = [np.ascontiguousarray(c[:, k], np.float32) for k in range(3)]
    logf = np.log2(np.asarray(focal_px, np.float64).reshape(-1)).astype(np.float32)
    wd, wo = np.float32(cfg.distance_weight), np.float32(cfg.orthogonality_weight)
    ph = candidates.photos
    ptr = candidates.indptr
    cnt = candidates.counts()
    out = np.empty(ph.size, np.float32)
    step = 1 << 18
    for a in range(0, n, step):  # chunks of points: bounded temporaries at scale
        b = min(a + step, n)
        e0, e1 = ptr[a], ptr[b]
        if e1 == e0:
            continue
        j, k = ph[e0:e1], cnt[a:b]
        vx = c[0][j] - np.repeat(p[0][a:b], k)
        vy = c[1][j] - np.repeat(p[1][a:b], k)
        vz = c[2][j] - np.repeat(p[2][a:b], k)
        d2 = vx * vx + vy * vy + vz * vz
        dot = vx * np.repeat(nr[0][a:b], k) + vy * np.repeat(nr[1][a:b], k) \
            + vz * np.repeat(nr[2][a:b], k)
        np.maximum(d2, np.float32(1e-24), out=d2)
        ld = np.log2(d2) * np.float32(0.5)           # log2 d
        cos = np.abs(dot) / np.exp2(ld)
        np.maximum(cos, np.float32(cfg.min_cos), out=cos)
        out[e0:e1] = wd * (ld - logf[j]) - wo * np.log2(cos)
    nz = cnt > 0
    if out.size:
        mins = np.minimum.reduceat(out, ptr[:-1][nz])
        out -= np.repeat(mins, cnt[nz])
    return out


def data_costs(positions, normals, cam_centers, focal_px, candidates,
               config: LabelingConfig | None = None) -> np.ndarray:
    """Dense data costs: ``candidates (n, m) bool`` -> ``(n, m) float32``, ``inf`` off candidates.

    Same formula as :func:`candidate_data_costs` (module docstring); ``focal_px (m,)`` in pixels.
    """
    cand = Candidates.from_dense(candidates)
    c = candidate_data_costs(positions, normals, cam_centers, focal_px, cand, config)
    out = np.full(np.shape(candidates), np.inf, np.float32)
    out[cand.rows(), cand.photos] = c
    return out


def knn_edges(positions, k: int) -> np.ndarray:
    """Undirected kNN graph: ``(e, 2) int64`` unique edges ``(i, j)``, ``i < j``, sorted.

    An edge joins ``i`` and ``j`` when either is among the other's ``k`` nearest neighbours.
    """
    import scipy.sparse as sp
    from scipy.spatial import cKDTree

    pos = np.asarray(positions, np.float64).reshape(-1, 3)
    n = len(pos)
    if n < 2 or k < 1:
        return np.zeros((0, 2), np.int64)
    pos = pos - pos.mean(0)
    kk = min(k + 1, n)
    tree = cKDTree(pos, balanced_tree=False, compact_nodes=False)
    _, nb = tree.query(pos, k=kk, workers=-1)
    nb = np.asarray(nb, np.int64).reshape(n, kk)
    i = np.repeat(np.arange(n, dtype=np.int64), kk)
    j = nb.ravel()
    keep = (j != i) & (j < n)
    i, j = i[keep], j[keep]
    lo, hi = np.minimum(i, j), np.maximum(i, j)
    A = sp.csr_matrix((np.ones(lo.size, np.int8), (lo, hi)), shape=(n, n))
    A.sum_duplicates()
    A.sort_indices()
    rows = np.repeat(np.arange(n, dtype=np.int64), np.diff(A.indptr))
    return np.stack([rows, A.indices.astype(np.int64)], axis=1)


def _norm3(a):
    return np.sqrt(np.einsum("ij,ij->i", a, a))


def _seam(cpx, ref_py, cqy, ref_qx, cfg: LabelingConfig):
    """V for x != y from the four colours (fallbacks already applied). (k,) float64."""
    return (cfg.smoothness_weight * (_norm3(cpx - ref_py) + _norm3(cqy - ref_qx))
            + cfg.label_change_cost)


def _pair_costs(cands: Candidates, p, x, q, y, cfg, keys=None):
    """V_pq(x, y) for arrays of edges (p, q) and labels x of p, y of q (all candidates). (k,) float64."""
    p, q = np.asarray(p, np.int64), np.asarray(q, np.int64)
    x, y = np.asarray(x, np.int64), np.asarray(y, np.int64)
    out = np.zeros(p.size, np.float64)
    diff = x != y
    if not diff.any():
        return out
    p, q, x, y = p[diff], q[diff], x[diff], y[diff]
    keys = cands.keys() if keys is None else keys
    ipx, fpx = cands.lookup(p, x, keys)
    iqy, fqy = cands.lookup(q, y, keys)
    if not (fpx.all() and fqy.all()):
        raise ValueError("a label is not a candidate of its point")
    ipy, fpy = cands.lookup(p, y, keys)
    iqx, fqx = cands.lookup(q, x, keys)
    col = cands.colors
    cpx, cqy = col[ipx], col[iqy]
    ref_py = np.where(fpy[:, None], col[ipy], cqy)
    ref_qx = np.where(fqx[:, None], col[iqx], cpx)
    out[diff] = _seam(cpx, ref_py, cqy, ref_qx, cfg)
    return out


def smoothness_costs(edges, labels_p, labels_q, colors, config: LabelingConfig | None = None,
                     candidates=None) -> np.ndarray:
    """Seam cost ``V_pq(labels_p, labels_q)`` of every edge (module docstring). (e,) float64.

    Parameters
    ----------
    edges : (e, 2) int
    labels_p, labels_q : (e,) int, the labels given to ``edges[:, 0]`` and ``edges[:, 1]``;
        each must be a candidate of its point. Edges with a ``-1`` end cost 0.
    colors : Candidates, or dense (n, m, 3) float32 together with ``candidates (n, m) bool``
    """
    cfg = config or LabelingConfig()
    cands = colors if isinstance(colors, Candidates) else Candidates.from_dense(candidates, colors)
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    lp, lq = np.asarray(labels_p, np.int64), np.asarray(labels_q, np.int64)
    ok = (lp >= 0) & (lq >= 0)
    out = np.zeros(len(edges), np.float64)
    out[ok] = _pair_costs(cands, edges[ok, 0], lp[ok], edges[ok, 1], lq[ok], cfg)
    return out


def energy(labels, data, edges, colors, config: LabelingConfig | None = None):
    """Energy of a labeling: ``(total, data_part, smooth_part)`` as floats.

    Parameters
    ----------
    labels : (n,) int, ``-1`` = unlabeled (no data cost, its edges cost nothing)
    data : (n, m) float32 dense costs (``inf`` off candidates) with ``colors (n, m, 3)``, or
        (nnz,) costs aligned with ``colors`` given as :class:`Candidates` (or None to use
        ``colors.costs``)
    edges : (e, 2) int
    colors : see ``data``

    A label that is not a candidate of its point gives ``inf``.
    """
    cfg = config or LabelingConfig()
    cands = _as_candidates(data, colors)
    labels = np.asarray(labels, np.int64)
    has = labels >= 0
    pts = np.flatnonzero(has)
    idx, found = cands.lookup(pts, labels[has])
    if not found.all():
        return np.inf, np.inf, np.inf
    e_data = float(np.sum(cands.costs[idx], dtype=np.float64))
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    e_smooth = float(smoothness_costs(edges, labels[edges[:, 0]], labels[edges[:, 1]], cands,
                                      cfg).sum()) if len(edges) else 0.0
    return e_data + e_smooth, e_data, e_smooth


# --------------------------------------------------------------------------------------------
# simple baselines
# --------------------------------------------------------------------------------------------
def _wta(cands: Candidates) -> tuple[np.ndarray, np.ndarray]:
    """Winner-take-all labels and the chosen entry per point (-1 where none)."""
    n = cands.n_points
    labels = np.full(n, -1, np.int32)
    ent = np.full(n, -1, np.int64)
    cnt = cands.counts()
    nz = np.flatnonzero(cnt > 0)
    if nz.size:
        c = cands.costs
        mins = np.minimum.reduceat(c, cands.indptr[nz])
        is_min = np.flatnonzero(c <= np.repeat(mins, cnt[nz]))
        r = cands.rows()[is_min]
        _, first = np.unique(r, return_index=True)  # first (lowest photo) minimum of each point
        ent[nz] = is_min[first]
        labels[nz] = cands.photos[ent[nz]]
    return labels, ent


def winner_take_all(data, candidates: Candidates | None = None) -> np.ndarray:
    """Lowest-data-cost candidate per point: ``(n,) int32``, ``-1`` where none (ties: lowest index).

    ``data`` is dense ``(n, m)`` (``inf`` off candidates), or ``(nnz,)`` aligned with ``candidates``.
    """
    if candidates is None:
        data = np.asarray(data, np.float32)
        return _wta(Candidates.from_dense(np.isfinite(data), None, data))[0]
    return _wta(_as_candidates(data, candidates))[0]


def icm(labels0, data, edges, colors, config: LabelingConfig | None = None, sweeps: int = 100,
        seed: int = 0) -> np.ndarray:
    """Iterated conditional modes from ``labels0`` (a baseline to compare the graph cut against).

    Every round, each point computes its best candidate given its neighbours' labels; the
    improving points that beat all improving neighbours in a random priority move at once (an
    independent set, so the energy decreases by exactly the sum of their gains). Stops when no
    point can improve alone, or after ``sweeps`` rounds. Arguments as in :func:`energy`.
    Returns ``(n,) int32``.
    """
    cfg = config or LabelingConfig()
    cands = _as_candidates(data, colors)
    keys = cands.keys()
    labels = np.asarray(labels0, np.int32).copy()
    edges = np.asarray(edges, np.int64).reshape(-1, 2)
    n = cands.n_points
    valid = cands.counts() > 0
    edges = edges[valid[edges[:, 0]] & valid[edges[:, 1]]]
    # directed incidences (point, neighbour)
    src = np.concatenate([edges[:, 0], edges[:, 1]])
    dst = np.concatenate([edges[:, 1], edges[:, 0]])
    order = np.argsort(src, kind="stable")
    src, dst = src[order], dst[order]
    inc_ptr = np.zeros(n + 1, np.int64)
    np.cumsum(np.bincount(src, minlength=n), out=inc_ptr[1:])
    cnt = cands.counts()
    rows = cands.rows()
    rng = np.random.default_rng(seed)
    # pair every candidate entry of a point p with each incidence (p, q) of p
    per_entry = np.diff(inc_ptr)[rows]
    ent = np.repeat(np.arange(cands.nnz), per_entry)
    inc = _ranges(inc_ptr[rows], per_entry)
    p, q = src[inc], dst[inc]
    x = cands.photos[ent]
    for _ in range(sweeps):
        # local energy of each candidate entry: data + sum over incident edges
        loc = cands.costs.astype(np.float64).copy()
        v = _pair_costs(cands, p, x, q, labels[q], cfg, keys)
        loc += np.bincount(ent, v, minlength=cands.nnz)
        nzr = np.flatnonzero(cnt > 0)
        best = np.full(n, np.inf)
        best[nzr] = np.minimum.reduceat(loc, cands.indptr[nzr])
        cur_idx, _ = cands.lookup(nzr, labels[nzr], keys)
        cur = np.full(n, np.inf)
        cur[nzr] = loc[cur_idx]
        improving = np.zeros(n, bool)
        improving[nzr] = cur[nzr] - best[nzr] > 1e-9 * np.maximum(1.0, np.abs(cur[nzr]))
        if not improving.any():
            break
        prio = rng.random(n)
        both = improving[src] & improving[dst]
        loser = np.where(prio[src] < prio[dst], src, dst)[both]
        accept = improving.copy()
        accept[loser] = False
        # the best entry of each accepted point (first minimum)
        cand_ent = np.flatnonzero((loc <= best[rows]) & accept[rows])
        r = rows[cand_ent]
        _, first = np.unique(r, return_index=True)
        labels[r[first]] = cands.photos[cand_ent[first]]
    return labels


# --------------------------------------------------------------------------------------------
# alpha-expansion
# --------------------------------------------------------------------------------------------
# Colours inside the expansion are packed as 4 float32 (RGB + 0) and moved around as one
# complex128 per colour: numpy gathers one 16-byte scalar far faster than a (k, 3) row.
def _pack(col3) -> np.ndarray:
    """(k, 3) float32 -> (k,) complex128 holding (r, g, b, 0) as float32 bits."""
    c4 = np.zeros((len(col3), 4), np.float32)
    c4[:, :3] = col3
    return c4.view(np.complex128).reshape(-1)


def _unpack(c) -> np.ndarray:
    """(k,) complex128 packed colours -> (k, 4) float32 view."""
    return np.ascontiguousarray(c).view(np.float32).reshape(-1, 4)


def _dist(c1, c2) -> np.ndarray:
    """Euclidean RGB distance of packed colours: (k,) float32."""
    d = _unpack(c1) - _unpack(c2)
    d *= d
    s = d[:, 0] + d[:, 1]
    s += d[:, 2]
    return np.sqrt(s, out=s)


def _submodular(E00, E01, E10):
    """Make binary pair terms (with ``E11 = 0``) submodular by raising ``E01`` and ``E10``.

    Returns ``(E01', E10', cap, n_raised)``: ``E01' >= E01``, ``E10' >= E10``,
    ``E01' + E10' >= E00``, and ``cap = E01' + E10' - E00 >= 0``, the capacity of the graph edge.
    """
    fix = np.maximum(E00 - E01 - E10, 0) * 0.5
    E01, E10 = E01 + fix, E10 + fix
    return E01, E10, np.maximum(E01 + E10 - E00, 0), int(np.count_nonzero(fix))


class _Expansion:
    """Alpha-expansion state: current labels plus per-half-edge caches, all vectorised.

    The kNN graph is stored as half-edges in CSR order by their source node: ``nbr[h]`` is the
    other end, ``rev[h]`` the opposite half-edge. Each half-edge caches ``ref[h]``, the colour of
    its source point in the label of its target (with the seam fallback applied), and ``hv[h]``,
    the current pairwise cost of its edge (stored on both halves).
    """

    def __init__(self, cands: Candidates, edges: np.ndarray, cfg: LabelingConfig, labels0=None):
        import maxflow  # PyMaxflow
        import scipy.sparse as sp

        self.maxflow = maxflow
        self.cfg = cfg
        self.lam = np.float32(cfg.smoothness_weight)
        self.lam0 = np.float32(cfg.label_change_cost)
        self.c = cands
        self.keys = cands.keys()
        n, m = cands.n_points, cands.n_photos
        self.n, self.m = n, m
        self.col = _pack(cands.colors)
        self.costs = cands.costs.astype(np.float32)
        valid = cands.counts() > 0
        edges = np.asarray(edges, np.int64).reshape(-1, 2)
        edges = edges[valid[edges[:, 0]] & valid[edges[:, 1]]]
        ne = len(edges)
        self.n_edges = ne
        # half-edges, CSR by source node (scipy's counting sort)
        src = np.concatenate([edges[:, 0], edges[:, 1]])
        dst = np.concatenate([edges[:, 1], edges[:, 0]])
        hid = np.arange(2 * ne, dtype=np.int64) + 1  # +1: keep explicit zeros out of the matrix
        A = sp.csr_matrix((hid, (src, dst)), shape=(n, n))
        A.sort_indices()
        self.ptr = A.indptr.astype(np.int64)
        self.nbr = A.indices.astype(np.int32)
        hid = A.data.astype(np.int64) - 1
        pos = np.empty(2 * ne, np.int64)
        pos[hid] = np.arange(2 * ne)
        self.rev = pos[(hid + ne) % max(2 * ne, 1)].astype(np.int32)
        self.rev_off = (self.rev - self.ptr[self.nbr]).astype(np.int32)
        self.deg = np.diff(self.ptr).astype(np.int32)
        # photo -> its candidate points and their entries (radix sort on 16-bit photo ids)
        ph = cands.photos.astype(np.uint16) if m <= 65535 else cands.photos
        self.csc_ent = np.argsort(ph, kind="stable").astype(np.int32)
        self.csc_rows = cands.rows()[self.csc_ent]
        self.csc_ptr = np.zeros(m + 1, np.int64)
        np.cumsum(np.bincount(cands.photos, minlength=m), out=self.csc_ptr[1:])
        # current labeling: winner-take-all, or the given start
        if labels0 is None:
            self.labels, ent = _wta(cands)
        else:
            self.labels = np.asarray(labels0, np.int32).copy()
            ent = np.full(n, -1, np.int64)
            if self.labels.shape != (n,) or np.any(self.labels[~valid] != -1):
                raise ValueError("labels0: (n,) labels, -1 exactly where a point has no candidate")
            idx, found = cands.lookup(np.flatnonzero(valid), self.labels[valid], self.keys)
            if not found.all():
                raise ValueError("labels0: a label is not a candidate of its point")
            ent[valid] = idx
        has = ent >= 0
        self.cur = np.zeros(n, np.complex128)
        self.cur[has] = self.col[ent[has]]
        self.cur_cost = np.zeros(n, np.float32)
        self.cur_cost[has] = self.costs[ent[has]]
        # per-half-edge caches
        h_src = np.repeat(np.arange(n, dtype=np.int32), self.deg)
        l_src, l_dst = self.labels[h_src], self.labels[self.nbr]
        idx, found = cands.lookup(h_src, l_dst, self.keys)
        self.ref = np.where(found, self.col[idx], self.cur[self.nbr])
        self.hv = np.zeros(2 * ne, np.float32)
        if ne:
            v = self.lam * (_dist(self.cur[h_src], self.ref) + _dist(self.cur[self.nbr],
                                                                    self.ref[self.rev])) + self.lam0
            self.hv = np.where(l_src == l_dst, np.float32(0), v).astype(np.float32)
        del h_src, l_src, l_dst, idx, found
        # scratch and bookkeeping
        self.sidx = np.full(n, -1, np.int32)  # index of a point in S_alpha during a move
        self.stamp = np.zeros(n, np.int64)    # move at which a point or a neighbour last changed
        self.last = np.full(m, -1, np.int64)  # move at which each label was last expanded
        self.step = 0
        self.n_truncated = 0                  # pair terms made submodular so far

    def energy(self):
        d = float(self.cur_cost[self.labels >= 0].sum(dtype=np.float64))
        s = float(self.hv.sum(dtype=np.float64)) / 2
        return d + s, d, s

    # -- one expansion move ---------------------------------------------------------------
    def expand(self, alpha: int, restrict: bool) -> int:
        """Expansion move of ``alpha``; returns points relabeled, or -1 when skipped.

        ``restrict``: only points whose neighbourhood changed since alpha's last move may switch
        (the others keep their label and act as fixed neighbours).
        """
        cfg, lam, lam0 = self.cfg, self.lam, self.lam0
        s0, s1 = self.csc_ptr[alpha], self.csc_ptr[alpha + 1]
        S = self.csc_rows[s0:s1]
        if S.size == 0:
            return -1
        prev = self.last[alpha]
        stS = self.stamp[S]
        if cfg.skip_unchanged_labels and prev >= 0 and stS.max() <= prev:
            return -1
        self.step += 1
        self.last[alpha] = self.step
        entS = self.csc_ent[s0:s1]
        ns = S.size
        is_alpha = self.labels[S] == alpha
        var = ~is_alpha
        if restrict and prev >= 0:
            var &= stS > prev
        nv = int(var.sum())
        if nv == 0:
            return 0
        # per-S arrays get one trailing sentinel so that index -1 (a point not in S) reads it
        aS = np.empty(ns + 1, np.complex128)
        aS[:ns] = self.col[entS]                  # colour of each S point in alpha
        aS[ns] = 0
        dS = np.zeros(ns + 1, np.float32)         # |c^cur - c^alpha| of each S point
        dS[:ns] = _dist(self.cur[S], aS[:ns])
        gid = np.full(ns + 1, -1, np.int32)       # graph node of each S point (-1: fixed)
        gid[:ns][var] = np.arange(nv, dtype=np.int32)
        alS = np.zeros(ns + 1, bool)
        alS[:ns] = is_alpha
        V = S[var]
        vS = np.flatnonzero(var).astype(np.int32)  # S index of each graph node
        self.sidx[S] = np.arange(ns, dtype=np.int32)

        # half-edges leaving the graph nodes
        deg = self.deg[V]
        h = _ranges(self.ptr[V], deg)
        sl = np.repeat(np.arange(nv, dtype=np.int32), deg)  # graph node of the source
        t = self.nbr[h]
        ts = self.sidx[t]                          # S index of the target, -1 if not in S
        tg = gid[ts]                               # graph node of the target, -1 if fixed
        tvar = tg >= 0
        A = self.hv[h]                             # current pairwise cost
        a_s = np.repeat(aS[vS], deg)
        # C = V(alpha, l_t): source takes alpha, target keeps its label
        second = dS[ts]                            # |c_t - c_t^alpha|, t in S
        out = np.flatnonzero(ts < 0)
        if out.size:                               # t not in S: fallback to the source's colour
            second[out] = _dist(self.cur[t[out]], a_s[out])
        C = lam * (_dist(a_s, self.ref[h]) + second) + lam0
        C[alS[ts]] = 0                             # target already carries alpha
        # pairs of graph nodes, each edge once (from its lower graph node)
        pr = np.flatnonzero(tvar & (tg > sl))
        bstart = np.zeros(nv, np.int64)
        np.cumsum(deg[:-1], out=bstart[1:])
        tgp = tg[pr]
        B = C[bstart[tgp] + self.rev_off[h[pr]]]   # C of the opposite half-edge
        Cp, Ap = C[pr], A[pr]
        B, Cp, cap, nt = _submodular(Ap, B, Cp)
        self.n_truncated += nt
        slp = sl[pr]
        # unary terms as the difference cost(x=1) - cost(x=0): data, edges to fixed targets
        # (C - A), and the pairs' reparametrisation (C - A at the source, -C at the target)
        C -= A
        C[tvar] = 0
        du = (self.costs[entS[vS]] - self.cur_cost[V]).astype(np.float64) + np.bincount(
            np.concatenate([sl, slp, tgp]), np.concatenate([C, Cp - Ap, -Cp]), minlength=nv)
        g = self.maxflow.Graph[float](nv, max(pr.size, 1))
        ids = g.add_nodes(nv)
        g.add_grid_tedges(ids, np.maximum(du, 0), np.maximum(-du, 0))  # x=1 (alpha): sink side
        if pr.size:
            g.add_edges(slp, tgp, cap.astype(np.float64), np.zeros(pr.size))
        g.maxflow()
        take = np.asarray(g.get_grid_segments(ids), bool)
        n_changed = int(take.sum())
        if n_changed:
            self._apply(alpha, V, vS, take, aS, h, sl, t, ts, tg, alS)
        self.sidx[S] = -1
        return n_changed

    def _apply(self, alpha, V, vS, take, aS, h, sl, t, ts, tg, alS):
        """Relabel the points that took alpha and refresh the caches of their half-edges."""
        lam, lam0 = self.lam, self.lam0
        X = V[take]
        ax = aS[vS[take]]
        self.labels[X] = alpha
        self.cur[X] = ax
        self.cur_cost[X] = self.costs[self.csc_ent[self.csc_ptr[alpha] + vS[take]]]
        k = np.flatnonzero(take[sl])               # half-edges leaving a relabeled point
        hk, tk, slk = h[k], t[k], sl[k]
        a_x = aS[vS[slk]]
        tsk, tgk = ts[k], tg[k]
        t_alpha = alS[tsk] | ((tgk >= 0) & take[np.maximum(tgk, 0)])
        # colour of the source in the target's label
        ref = a_x.copy()
        o = np.flatnonzero(~t_alpha)
        if o.size:
            idx, found = self.c.lookup(V[slk[o]], self.labels[tk[o]], self.keys)
            ref[o] = np.where(found, self.col[idx], self.cur[tk[o]])
        # colour of the target in alpha (S points have one; others fall back to the source's)
        rref = np.where(tsk >= 0, aS[tsk], a_x)
        v = lam * (_dist(a_x, ref) + _dist(self.cur[tk], rref)) + lam0
        v[t_alpha] = 0
        self.ref[hk] = ref
        self.hv[hk] = v
        rk = self.rev[hk]
        self.ref[rk] = rref
        self.hv[rk] = v
        self.stamp[X] = self.step
        self.stamp[tk] = self.step
        ring = tk
        for _ in range(self.cfg.local_hops - 1):
            ring = np.unique(ring)
            hh = _ranges(self.ptr[ring], self.deg[ring])
            ring = self.nbr[hh]
            self.stamp[ring] = self.step


def alpha_expansion(data, edges, colors=None, config: LabelingConfig | None = None,
                    labels0=None, progress: bool = False) -> LabelingResult:
    """Minimise the labeling energy on a given graph by alpha-expansion (the solver of
    :func:`label_points`, usable on any graph, e.g. DMT's depth-map pixels).

    Parameters
    ----------
    data : (n, m) float32 dense data costs (``inf`` off candidates) with ``colors (n, m, 3)``,
        or (nnz,) costs aligned with ``colors`` given as :class:`Candidates` (None: its ``costs``)
    edges : (e, 2) int, undirected, each pair once
    colors : see ``data``
    config : LabelingConfig (``k_neighbors``, ``spatial_sort`` and the data-term weights unused)
    labels0 : (n,) int, optional start (candidates, -1 where none); default winner-take-all
    progress : bool, a tqdm bar per sweep

    Returns
    -------
    LabelingResult (``seconds_setup`` covers building the solver's graph)
    """
    from tqdm.auto import tqdm

    cfg = config or LabelingConfig()
    t_start = time.perf_counter()
    cands = _as_candidates(data, colors)
    st = _Expansion(cands, edges, cfg, labels0)
    res = LabelingResult(labels=st.labels, n_edges=int(st.n_edges))
    e_prev = st.energy()[0]
    res.energy_per_sweep.append(e_prev)
    res.seconds_setup = time.perf_counter() - t_start
    m = cands.n_photos
    for sweep in range(cfg.max_sweeps):
        t0 = time.perf_counter()
        moves = skipped = changed = 0
        bar = tqdm(total=m, desc=f"labeling sweep {sweep + 1}/{cfg.max_sweeps}", leave=False,
                   disable=not progress, unit="label")
        for alpha in range(m):
            c = st.expand(alpha, cfg.local_moves)
            if c < 0:
                skipped += 1
            else:
                moves += 1
                changed += c
            bar.update(1)
        bar.close()
        e_now = st.energy()[0]
        res.energy_per_sweep.append(e_now)
        res.seconds_per_sweep.append(time.perf_counter() - t0)
        res.moves_per_sweep.append(moves)
        res.skipped_per_sweep.append(skipped)
        res.changed_per_sweep.append(changed)
        if progress:
            tqdm.write(f"labeling sweep {sweep + 1}: energy {e_now:.6g} "
                       f"({changed} points relabeled, {moves} cuts, {skipped} labels skipped, "
                       f"{res.seconds_per_sweep[-1]:.2f} s)")
        if changed == 0 or e_prev - e_now <= cfg.tolerance * abs(e_prev):
            break
        e_prev = e_now
    _, res.data_energy, res.smooth_energy = st.energy()
    res.truncated_terms = st.n_truncated
    res.labels = st.labels.astype(np.int32)
    res.seconds_total = time.perf_counter() - t_start
    return res


def label_points(positions, normals, candidates, cameras, colors=None,
                 config: LabelingConfig | None = None, progress: bool = True) -> LabelingResult:
    """Label every proxy point with one candidate photo (paper Section 4.3).

    Builds the kNN graph and the data costs, then runs :func:`alpha_expansion` from the
    winner-take-all labeling (points in Morton order inside; the result is in input order).

    Parameters
    ----------
    positions : (n, 3) float32 or float64, metres, in the cameras' frame (use
        ``Camera.relative_to(origin)`` when the points are relative to a scene origin)
    normals : (n, 3) float32, unit (sign ignored)
    candidates : (n, m) bool (photo ``j`` sees point ``i`` unoccluded) with ``colors``, or a
        :class:`Candidates` (sparse; its ``colors`` are used, its ``costs`` recomputed)
    cameras : list of m :class:`dmrt.camera.Camera`
    colors : (n, m, 3) float32 0..1, colour of point ``i`` in photo ``j`` (dense form only;
        arbitrary where ``candidates`` is False)
    config : LabelingConfig
    progress : bool, show a tqdm bar per sweep

    Returns
    -------
    LabelingResult (``seconds_setup``: ordering, data costs, kNN graph, solver set-up;
    ``seconds_total``: end to end)
    """
    cfg = config or LabelingConfig()
    t_start = time.perf_counter()
    cands = candidates if isinstance(candidates, Candidates) else \
        Candidates.from_dense(candidates, colors)
    n = cands.n_points
    if len(cameras) != cands.n_photos:
        raise ValueError(f"{len(cameras)} cameras for {cands.n_photos} photos")
    positions = np.asarray(positions).reshape(n, 3)
    normals = np.asarray(normals, np.float32).reshape(n, 3)
    centers = np.array([c.center for c in cameras], np.float64).reshape(-1, 3)
    focal = np.array([np.sqrt(c.fx * c.fy) for c in cameras], np.float64)

    order = morton_order(positions) if (cfg.spatial_sort and n > 1) else None
    if order is not None:
        positions, normals, cands = positions[order], normals[order], cands.take(order)
    costs = candidate_data_costs(positions, normals, centers, focal, cands, cfg)
    cands = Candidates._trusted(cands.indptr, cands.photos, cands.colors, cands.n_photos, costs)
    edges = knn_edges(positions, cfg.k_neighbors)
    t_graph = time.perf_counter() - t_start
    res = alpha_expansion(None, edges, cands, cfg, progress=progress)
    res.seconds_setup += t_graph
    if order is not None:
        out = np.empty_like(res.labels)
        out[order] = res.labels
        res.labels = out
    res.seconds_total = time.perf_counter() - t_start
    return res
