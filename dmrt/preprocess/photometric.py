"""Global photometric adjustment: one colour gain per photo and channel, solved once in
preprocessing from the photos' overlaps (an addition to the paper).

Photos of one scene differ by exposure and white balance (a camera's auto-exposure, the time of
day), so the same surface point has different colours in different photos, and a frame textured
from several photos shows their seams. Like the global colour adjustment of mvs-texturing
(Waechter, Moehrle, Goesele, ECCV 2014), this module equalises the photos before any frame is
drawn, but with the simplest per-photo model: photo ``j`` records a point of radiance ``r`` as
``c = r / g_j`` per channel, so ``g_j`` times the photo's colour is that of a common camera.

The observations are the proxies' candidates (:mod:`dmrt.preprocess.candidates`): each proxy
``i`` seen by several photos has a colour ``c_ij`` in each. In log space, ``y_ij = log c_ij``,
per channel,

    minimise over x, m   sum_(i,j) w_ij (y_ij + x_j - m_i)^2  +  sum_j (reg * deg_j + prior) x_j^2

with ``x_j = log g_j``, ``m_i`` the proxy's common log colour (eliminated: the problem is a
weighted graph Laplacian over the photos), ``deg_j`` the diagonal of that Laplacian (how much
photo ``j`` is tied to the others; ``reg`` = 0 by default) and ``prior`` a pull toward gain 1
worth a few observations, so that a photo tied to the others by a few dozen points (a real
scene's narrow overlaps, where those few may well be a reflection or a moving car) keeps a gain
nearer 1 while well-tied ones are barely biased (4 against ~100 observations: 4 % of their log
gain). ``w_ij`` are Huber weights refitted a few times (iteratively reweighted least squares), so
that occlusions the depth maps missed, misregistration, specular highlights and moving objects do
not pull the gains. Two photos are *tied* when they share at least ``min_shared`` points and the
tie lies on a cycle of ties (``cycles``): an offset that no second chain of overlaps confirms is
not trusted. That is the classic consistency check of global alignment, and what a real camera
rig needs: nuScenes' six outward-facing cameras overlap pairwise in narrow strips that form a
chain, and one strip is a glass facade whose reflection differs by e^1 between two cameras; taken
as exposure, it cost up to 6 dB at held-out views. A photo tied to none keeps gain 1 (no
evidence), as does one joined to the others by a single bridge of overlaps. The common scale is free (the gauge): within each group
of tied photos the mean log gain is set to 0, so the scene's overall brightness stays the photos'
mean. Clipped and near-black samples carry no exposure information and are left out.

The gains go into ``bundle.json`` (``photo_gains``, (n_photos, 3)) and the texturing pass of
both renderers multiplies each photo's colour by its gain (``RenderConfig.photometric``).
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field

import numpy as np

from dmrt.options import option, validate
from dmrt.preprocess.parallel import default_workers


@dataclass
class PhotometricConfig:
    """Parameters of the gain solve (log units are natural logs of 0..1 colours)."""

    regularization: float = option(0.0, "pull of each log gain toward 0, relative to how strongly the photo is "
                                        "tied to the others", minimum=0.0)
    prior_observations: float = option(4.0, "and an absolute pull toward 0 worth this many observations: a photo "
                                             "that shares only a few points with the others keeps a gain near 1",
                                       minimum=0.0)
    huber: float = option(0.1, "log residual beyond which an observation is down-weighted (IRLS, Huber)",
                          minimum=1e-6)
    iterations: int = option(5, "reweighting iterations (1 = plain least squares)", minimum=1)
    min_value: float = option(2 / 255, "samples with a channel below this (black, noise) are left out",
                              minimum=0.0, maximum=1.0)
    max_value: float = option(250 / 255, "samples with a channel above this (clipped) are left out",
                              minimum=0.0, maximum=1.0)
    min_shared: int = option(16, "two photos are tied when they share at least this many points; a photo tied to "
                                 "none keeps gain 1", minimum=1)
    cycles: bool = option(True, "trust a tie only on a cycle of ties (another chain of overlaps confirms its offset); "
                                "off, a bridge between two groups of photos ties them too")
    max_gain: float = option(4.0, "gains are clamped to [1 / max_gain, max_gain]", minimum=1.0)

    def __post_init__(self):
        validate(self)


@dataclass
class PhotometricResult:
    """The solved gains and what they rest on.

    Attributes
    ----------
    gains : (n_photos, 3) float32, the RGB gain of each photo (1 = unchanged).
    observations : int, candidate samples used (of proxies seen by >= 2 tied photos, not clipped).
    proxies : int, proxies those samples belong to.
    photos_adjusted : int, photos tied to another (sharing >= ``min_shared`` proxies with it).
    groups : int, groups of photos connected by such ties (each has its own mean log gain 0).
    group_of : (n_photos,) int64, each photo's group (0 .. groups - 1), -1 for a photo tied to none.
    rms_before, rms_after : float, RMS of the log residuals ``y_ij + x_j - m_i`` (``m_i`` the point's
        mean; mean over the channels) with gains 1 and with the solved gains: how much the photos
        disagree, outliers included.
    seconds : float, wall time of the solve.
    """

    gains: np.ndarray
    observations: int = 0
    proxies: int = 0
    photos_adjusted: int = 0
    groups: int = 0
    rms_before: float = float("nan")
    rms_after: float = float("nan")
    seconds: float = 0.0
    config: PhotometricConfig = field(default_factory=PhotometricConfig)
    group_of: np.ndarray | None = None

    def meta(self) -> dict:
        """bundle.json's ``photometric`` record (the gains themselves are ``photo_gains``)."""
        return {"observations": self.observations, "proxies": self.proxies, "photos_adjusted": self.photos_adjusted,
                "groups": self.groups,
                "photo_groups": (self.group_of if self.group_of is not None
                                 else np.full(len(self.gains), -1)).astype(int).tolist(),
                "rms_log_before": _finite(self.rms_before),
                "rms_log_after": _finite(self.rms_after), "seconds": round(self.seconds, 3),
                "parameters": asdict(self.config)}


def _finite(x: float):
    return float(x) if np.isfinite(x) else None


def solve_photo_gains(indptr: np.ndarray, photos: np.ndarray, colors: np.ndarray, n_photos: int,
                      config: PhotometricConfig | None = None) -> PhotometricResult:
    """Per-photo RGB gains that make the photos agree on the points they share (module doc).

    Parameters
    ----------
    indptr : (n_points + 1,) int64, CSR offsets: entries ``indptr[i]:indptr[i+1]`` belong to point ``i``
        (:class:`dmrt.preprocess.labeling.Candidates`).
    photos : (nnz,) int, the photo of each entry, ``0 <= photo < n_photos``, each at most once per point.
    colors : (nnz, 3) float, the point's RGB in that photo, 0..1 (display-referred, as the photos).
    n_photos : int
    config : PhotometricConfig, optional

    Returns
    -------
    PhotometricResult
        ``gains`` (n_photos, 3) float32: multiply photo ``j``'s colours by ``gains[j]``.
    """
    from scipy import sparse
    from scipy.sparse.csgraph import connected_components
    from scipy.sparse.linalg import spsolve

    t0 = time.perf_counter()
    config = config or PhotometricConfig()
    n = int(n_photos)
    out = PhotometricResult(np.ones((n, 3), np.float32), config=config, group_of=np.full(n, -1, np.int64))
    indptr = np.asarray(indptr, np.int64)
    photos = np.asarray(photos, np.int64)
    colors = np.asarray(colors, np.float64).reshape(-1, 3)
    point = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
    usable = np.all((colors >= max(config.min_value, 1e-6)) & (colors <= config.max_value), axis=1)
    point, photo, y = point[usable], photos[usable], np.log(np.maximum(colors[usable], 1e-6))
    # Photos tied to another by >= min_shared points, on a cycle of such ties; the others keep gain
    # 1 and leave the solve. A point seen by photos of several groups counts once per group (its
    # entries split), so no untrusted tie couples two groups. Repeat until nothing changes: dropping
    # a photo or splitting a point can untie others.
    while True:
        _, point = np.unique(point, return_inverse=True)
        m = int(point.max()) + 1 if len(point) else 0
        multi = np.bincount(point, minlength=m)[point] >= 2
        point, photo, y = point[multi], photo[multi], y[multi]
        if len(point) == 0:
            out.seconds = time.perf_counter() - t0
            return out
        P = sparse.csr_matrix((np.ones(len(point)), (point, photo)), shape=(m, n))
        co = (P.T @ P).tocsr()
        co.setdiag(0)
        co.data[co.data < config.min_shared] = 0
        co.eliminate_zeros()
        if config.cycles:
            co = _without_bridges(co)
        n_groups, group = connected_components(co, directed=False)
        tied = np.asarray((co != 0).sum(axis=1)).ravel() > 0
        keep = tied[photo]
        split = point * n + group[photo]
        if keep.all() and len(np.unique(split)) == len(np.unique(point)):
            break
        point, photo, y = split[keep], photo[keep], y[keep]
    _, point = np.unique(point, return_inverse=True)  # compact point indices
    m = int(point.max()) + 1
    out.observations, out.proxies = int(len(point)), m
    out.photos_adjusted = int(tied.sum())

    x = np.zeros((n, 3))
    # Without a pull toward 0 the system is singular (each group's common scale is free): one photo
    # of each group is pinned to 0, the solution the gauge below makes unique either way.
    pinned = np.zeros(n, bool)
    if config.prior_observations == 0 and config.regularization == 0:
        firsts = np.unique(group[tied], return_index=True)[1]
        pinned[np.flatnonzero(tied)[firsts]] = True
    for ch in range(3):
        yc = y[:, ch]
        w = np.ones(len(point))
        for it in range(config.iterations):
            if it > 0:  # Huber weights from the last solution's residuals (the first pass: plain least squares)
                a = np.abs(_residuals(yc + x[photo, ch], point, w, m))
                w = np.where(a <= config.huber, 1.0, config.huber / np.maximum(a, 1e-12))
            W = np.bincount(point, weights=w, minlength=m)
            # normal equations with the m_i eliminated: A = P^T diag(w) P - B^T diag(1 / W) B, B = diag(w) P,
            # sparse (photos share points with their neighbours only): a dense solve is cubic in
            # the photos, 15 solves of 10,000^2 took hours
            Pw = sparse.csr_matrix((w, (point, photo)), shape=(m, n))
            A = sparse.diags(np.asarray(Pw.sum(axis=0)).ravel()) - Pw.T @ sparse.diags(1.0 / W) @ Pw
            b = np.bincount(photo, weights=w * _residuals(yc, point, w, m), minlength=n)
            A = A + sparse.diags(config.regularization * A.diagonal() + config.prior_observations
                                 + np.where(tied, 0.0, 1.0))
            free = sparse.diags((~pinned).astype(float))
            A = free @ A @ free + sparse.diags(pinned.astype(float))
            xc = np.atleast_1d(spsolve(A.tocsc(), -np.where(pinned, 0.0, b)))
            xc[~tied] = 0.0
            x[:, ch] = xc
    for g in range(n_groups):  # the gauge: mean log gain 0 within each group of tied photos
        sel = (group == g) & tied
        if sel.any():
            x[sel] -= x[sel].mean(axis=0)
    out.gains = np.clip(np.exp(x), 1.0 / config.max_gain, config.max_gain).astype(np.float32)
    labels = np.unique(group[tied])
    out.groups = int(len(labels))
    out.group_of = np.where(tied, np.searchsorted(labels, group), -1).astype(np.int64)
    ones = np.ones(len(point))
    out.rms_before = float(np.mean([_rms(_residuals(y[:, c], point, ones, m)) for c in range(3)]))
    out.rms_after = float(np.mean([_rms(_residuals(y[:, c] + np.log(out.gains[photo, c]), point, ones, m))
                                   for c in range(3)]))
    out.seconds = time.perf_counter() - t0
    return out


def _without_bridges(co):
    """The symmetric adjacency ``co`` (n, n) without its bridges: the edges on no cycle (Tarjan's
    low-link, iteratively). Their offset is confirmed by no other chain of overlaps."""
    from scipy import sparse

    co = sparse.csr_matrix(co)
    n = co.shape[0]
    disc, low = np.full(n, -1), np.zeros(n, np.int64)
    bridges, t = set(), 0
    for root in range(n):
        if disc[root] >= 0:
            continue
        disc[root] = low[root] = t
        t += 1
        stack = [(root, -1, iter(co.indices[co.indptr[root]:co.indptr[root + 1]]))]
        while stack:
            v, parent, it = stack[-1]
            u = next(it, None)
            if u is None:
                stack.pop()
                if parent >= 0:
                    low[parent] = min(low[parent], low[v])
                    if low[v] > disc[parent]:
                        bridges.add((min(v, parent), max(v, parent)))
                continue
            if u == parent:
                continue
            if disc[u] < 0:
                disc[u] = low[u] = t
                t += 1
                stack.append((u, v, iter(co.indices[co.indptr[u]:co.indptr[u + 1]])))
            else:
                low[v] = min(low[v], disc[u])
    if not bridges:
        return co
    co = co.tolil()
    for a, b in bridges:
        co[a, b] = co[b, a] = 0
    co = co.tocsr()
    co.eliminate_zeros()
    return co


def _residuals(v: np.ndarray, point: np.ndarray, w: np.ndarray, m: int) -> np.ndarray:
    """``v`` minus the ``w``-weighted mean of its point's entries (``point``: (k,) in 0..m-1)."""
    mean = np.bincount(point, weights=w * v, minlength=m) / np.maximum(np.bincount(point, weights=w, minlength=m),
                                                                        1e-300)
    return v - mean[point]


def _rms(r: np.ndarray) -> float:
    return float(np.sqrt(np.mean(r * r))) if r.size else float("nan")


def patch_colors(positions: np.ndarray, normals: np.ndarray, radii: np.ndarray, point: np.ndarray,
                 photo: np.ndarray, cameras, photos, progress: bool = False) -> np.ndarray:
    """The mean colour of each proxy's disc in each photo that sees it: the colours the gain solve
    compares.

    A single bilinear sample is not comparable across photos that see a point at different
    distances: a photo pixel is the mean of its footprint, so a far photo reports the local mean of
    a fine texture where a near one reports one texel of it, and since log(mean) > mean(log), far
    photos look brighter (on the tiny synthetic scene that biased the gains of one room against the
    other by 0.18 in log). Averaging the same patch of surface in every photo removes it: here the
    axis-aligned box around the projection of the disc's rim (at least one pixel), averaged exactly
    with a summed-area table.

    Parameters
    ----------
    positions : (n, 3) float, origin-relative metres.  normals : (n, 3) float, unit.
    radii : (n,) float, the proxies' splat radii, metres.
    point, photo : (k,) int, the (proxy, photo) pairs to sample (e.g. the candidates' entries).
    cameras : list of Camera, origin-relative, photo resolution.
    photos : callable ``j -> (H, W, 3) uint8`` photo ``j``, called from several threads.

    Returns
    -------
    (k, 3) float32, RGB 0..1 (NaN where the box misses the photo).
    """
    from concurrent.futures import ThreadPoolExecutor

    from tqdm import tqdm

    positions = np.asarray(positions, np.float64)
    nrm = np.asarray(normals, np.float64)
    u = np.cross(nrm, np.where(np.abs(nrm[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
    u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
    v = np.cross(nrm, u)
    r = np.asarray(radii, np.float64)[:, None]
    out = np.full((len(point), 3), np.nan, np.float32)
    order = np.argsort(photo, kind="stable")
    bounds = np.searchsorted(photo[order], np.arange(len(cameras) + 1))

    def one(j):  # photo j's rows of ``out`` (the photos' rows are disjoint: threads may share ``out``)
        sel = order[bounds[j]:bounds[j + 1]]
        if len(sel) == 0:
            return
        cam, img = cameras[j], np.asarray(photos(j), np.uint8)
        h, w = img.shape[:2]
        # exact integer sums (at most 255 h w: 2^31 holds 8.4M pixels; larger photos take int64):
        # half float64's bytes and no conversion pass: the table is the phase's main cost per photo
        # (one 1024x684 photo on the 2-core sandbox, timeit: 27 against 97 ms)
        sat = np.zeros((h + 1, w + 1, 3), np.int32 if 255 * h * w < 2 ** 31 else np.int64)
        np.cumsum(img, axis=0, dtype=sat.dtype, out=sat[1:, 1:])
        np.cumsum(sat[1:, 1:], axis=1, out=sat[1:, 1:])
        q = positions[point[sel]]
        corners = []
        for a in np.linspace(0, 2 * np.pi, 8, endpoint=False):
            rim = q + r[point[sel]] * (np.cos(a) * u[point[sel]] + np.sin(a) * v[point[sel]])
            uv, z = cam.project(rim)
            corners.append(np.where((z > 0)[:, None], uv, np.nan))
        corners = np.stack(corners)  # (8, m, 2)
        lo, hi = np.nanmin(corners, axis=0), np.nanmax(corners, axis=0)
        centre = (lo + hi) / 2
        half = np.maximum((hi - lo) / 2, 0.5)  # at least one pixel
        lo = np.clip(centre - half, 0, [w, h])
        hi = np.clip(centre + half, 0, [w, h])
        area = np.prod(hi - lo, axis=1)
        ok = np.isfinite(area) & (area > 0.25)
        lo, hi = np.where(ok[:, None], lo, 0), np.where(ok[:, None], hi, 1)
        total = (_sat_at(sat, hi[:, 0], hi[:, 1]) - _sat_at(sat, lo[:, 0], hi[:, 1])
                 - _sat_at(sat, hi[:, 0], lo[:, 1]) + _sat_at(sat, lo[:, 0], lo[:, 1]))
        mean = total / (255.0 * np.maximum(area, 1e-12)[:, None])
        out[sel[ok]] = mean[ok]

    # numpy's array work and the photo decoding release the GIL: one thread per core
    with ThreadPoolExecutor(max(1, min(len(cameras), default_workers()))) as pool:
        for _ in tqdm(pool.map(one, range(len(cameras))), total=len(cameras), desc="photometric", unit="photo",
                      disable=not progress):
            pass
    return out


def _sat_at(sat: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """The integral of the piecewise-constant image over [0, x] x [0, y] (pixels; bilinear in the
    summed-area table ``sat`` (h + 1, w + 1, c), exact for a pixel-constant image)."""
    h, w = sat.shape[0] - 1, sat.shape[1] - 1
    x0 = np.clip(np.floor(x).astype(np.int64), 0, w - 1)
    y0 = np.clip(np.floor(y).astype(np.int64), 0, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((sat[y0, x0] * (1 - fx) + sat[y0, x0 + 1] * fx) * (1 - fy)
            + (sat[y0 + 1, x0] * (1 - fx) + sat[y0 + 1, x0 + 1] * fx) * fy)


def solve_for_proxies(proxy: dict, candidates, cameras, photos, config: PhotometricConfig | None = None,
                      progress: bool = False) -> PhotometricResult:
    """The gains of preprocessing: :func:`solve_photo_gains` on the proxies' candidate photos.

    Two things make the observations comparable: each is the mean colour of the proxy's disc
    (:func:`patch_colors`), and only photos that see the disc's front (the side its normal faces,
    oriented toward the nearest photo) count. The candidate test accepts either side of a surface
    thinner than its tolerance (a pole, a statue's arm, a door leaf), and the far side is another
    surface with other colours and light: on the tiny synthetic scene, the few such samples that
    tie its two rooms together put 0.2 of log gain between them.

    Parameters
    ----------
    proxy : dict with ``positions`` (n, 3) float32 origin-relative metres, ``normals`` (n, 3) float32
        and ``radii`` (n,) float32 metres (:class:`dmrt.preprocess.proxies.ProxySet`'s ``proxy``).
    candidates : :class:`dmrt.preprocess.labeling.Candidates` of those proxies.
    cameras : list of Camera, origin-relative, photo resolution.
    photos : callable ``j -> (H, W, 3) uint8`` photo ``j`` (called once per photo, in order).
    """
    indptr = np.asarray(candidates.indptr, np.int64)
    point = np.repeat(np.arange(len(indptr) - 1), np.diff(indptr))
    photo = np.asarray(candidates.photos, np.int64)
    pos = np.asarray(proxy["positions"], np.float64)
    centres = np.array([c.center for c in cameras]).reshape(-1, 3)
    front = np.einsum("ij,ij->i", np.asarray(proxy["normals"], np.float64)[point], centres[photo] - pos[point]) > 0
    point, photo = point[front], photo[front]
    colors = patch_colors(pos, proxy["normals"], proxy["radii"], point, photo, cameras, photos, progress)
    ok = np.isfinite(colors).all(axis=1)
    point, photo, colors = point[ok], photo[ok], colors[ok]  # still sorted by point
    new_indptr = np.concatenate([[0], np.cumsum(np.bincount(point, minlength=len(indptr) - 1))])
    return solve_photo_gains(new_indptr, photo, colors, len(cameras), config)
