"""Candidates (paper Section 4.3): the photos that see each proxy point, by the occlusion test
against each photo's depth map, and the proxy's colour in each (the labeling's seam term)."""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from dmrt.preprocess.config import PreprocessConfig
from dmrt.preprocess.frustum import Buckets
from dmrt.preprocess.labeling import Candidates


def sample_bilinear(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup of pixel-corner-origin coordinates.

    Parameters
    ----------
    image : (h, w, c) uint8 or float
    uv : (n, 2) float64, pixel coordinates (centre of pixel (i, j) at (j + 0.5, i + 0.5)).

    Returns
    -------
    (n, c) float32 in the image's value range, edge-clamped.
    """
    h, w = image.shape[:2]
    x = np.clip(uv[:, 0] - 0.5, 0, w - 1)
    y = np.clip(uv[:, 1] - 0.5, 0, h - 1)
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    img = image.astype(np.float32)
    top = img[y0, x0] * (1 - fx) + img[y0, x1] * fx
    bottom = img[y1, x0] * (1 - fx) + img[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def find_candidates(positions: np.ndarray, normals: np.ndarray, hd_radii: np.ndarray, cameras,
                    depth_maps, photos, config: PreprocessConfig, progress: bool = True,
                    radii: np.ndarray | None = None, executor=None) -> Candidates:
    """The photos that see each proxy point, and the proxy's colour in each.

    Parameters
    ----------
    positions : (n, 3) float32, origin-relative metres.  normals : (n, 3) float32 unit.
    hd_radii : (n,) float32, the points' P_HD splat radii (the depth maps were drawn with them).
    cameras : origin-relative cameras (photo resolution).
    depth_maps : callable ``j -> (h, w) float32`` depth map of photo ``j``.
    photos : callable ``j -> (H, W, 3) uint8`` photo ``j``.
    radii : (n,) float32, optional, the proxies' own splat radii: with them a candidate must also
        see ``config.candidate_rim_fraction`` of the disc's rim.
    executor : optional, :mod:`dmrt.preprocess.parallel`: the photos are cut into one contiguous
        group per worker, each a task (``depth_maps`` and ``photos`` must then pickle); the result
        is the same, the groups being joined in photo order before the rim rule.

    Returns
    -------
    Candidates (CSR over points; colours RGB 0..1).
    """
    if executor is None or not executor.distributed:
        found = photo_candidates(range(len(cameras)), positions, normals, hd_radii, cameras, depth_maps,
                                 photos, config, radii, progress)
    else:
        from dmrt.preprocess.parallel import split

        parts = executor.map(photo_candidates, split(len(cameras), executor.workers), desc="candidates",
                             progress=progress, positions=positions, normals=normals, hd_radii=hd_radii,
                             cameras=cameras, depth_maps=depth_maps, photos=photos, config=config, radii=radii)
        found = [pair for part in parts for pair in part]
    return join_candidates(found, len(positions), len(cameras), rims=radii is not None and
                           config.candidate_rim_fraction > 0)


def photo_candidates(js, positions: np.ndarray, normals: np.ndarray, hd_radii: np.ndarray, cameras,
                     depth_maps, photos, config: PreprocessConfig, radii: np.ndarray | None = None,
                     progress: bool = False) -> list[tuple]:
    """:func:`find_candidates` for the photos ``js`` alone, before the rim rule.

    Returns
    -------
    list of ``(points, photo, colors, rim_ok)``, one per photo of ``js`` that sees any point, in
    the order of ``js``: ``points`` (m,) int64 point indices, ``photo`` (m,) its index, ``colors``
    (m, 3) float32 RGB 0..1, ``rim_ok`` (m,) bool or None (no rim test).
    """
    p = positions.astype(np.float64)
    rims = None
    if radii is not None and config.candidate_rim_fraction > 0:
        n = np.asarray(normals, np.float64)
        u = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
        v = np.cross(n, u)
        r = 0.8 * np.asarray(radii, np.float64)[:, None]
        rims = [p + r * (np.cos(a) * u + np.sin(a) * v) for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)]

    def seen(cam, depth, q, idx):
        """Which points ``q`` (m, 3) the depth map sees (its surface within the tolerance)."""
        h, w = depth.shape
        uv, z = cam.project(q)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        uvi = np.where(inside[:, None], uv, 0).astype(np.int64)
        d = np.where(inside, depth[uvi[:, 1], uvi[:, 0]], 0.0)
        # within a few splat radii (the map was drawn with discs of that size) plus a texel
        # footprint at this depth (sampling)
        tol = config.occlusion_tolerance * hd_radii[idx] + config.occlusion_texels * z / cam.fx
        return inside & (d > 0) & (np.abs(d - z) <= tol)

    # only the points of the buckets a photo's frustum meets are projected (dmrt.preprocess.frustum);
    # the others would fail the test below anyway
    buckets = Buckets.of(positions, None, config.cull_points) if config.cull_points else None
    found = []
    for j in tqdm(js, desc="candidates", unit="photo", disable=not progress):
        cam = cameras[j]
        depth = depth_maps(j)
        h, w = depth.shape
        dm_cam = cam.scaled(w, h)
        rows = slice(None) if buckets is None else buckets.rows(buckets.visible(dm_cam))
        uv, z = dm_cam.project(p[rows])
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        idx = np.flatnonzero(inside) if buckets is None else rows[inside]
        to_eye = cam.center - p[idx]
        cos = np.abs(np.einsum("ij,ij->i", to_eye, normals[idx])) / np.linalg.norm(to_eye, axis=1)
        idx = idx[(cos >= config.candidate_min_cos) & seen(dm_cam, depth, p[idx], idx)]
        if len(idx) == 0:
            continue
        uv_photo, _ = cam.project(p[idx])
        rim_ok = None
        if rims is not None:
            frac = np.mean([seen(dm_cam, depth, rim[idx], idx) for rim in rims], axis=0)
            rim_ok = frac >= config.candidate_rim_fraction
        found.append((idx, np.full(len(idx), j), sample_bilinear(photos(j), uv_photo) / 255.0, rim_ok))
    return found


def join_candidates(found: list[tuple], n_points: int, n_photos: int, rims: bool) -> Candidates:
    """The :class:`Candidates` of :func:`photo_candidates`' pairs of all photos (in photo order),
    after the rim rule: a point none of whose photos sees its rim keeps them all."""
    if not found:
        return Candidates(np.zeros(n_points + 1, np.int64), np.zeros(0, np.int32), None, n_photos)
    pts, phs, cols = (np.concatenate([f[i] for f in found]) for i in range(3))
    if rims:
        ok = np.concatenate([f[3] for f in found])
        has_ok = np.zeros(n_points, bool)
        has_ok[pts[ok]] = True
        keep = ok | ~has_ok[pts]  # a point none of whose photos sees its rim keeps them all
        pts, phs, cols = pts[keep], phs[keep], cols[keep]
    return Candidates.from_pairs(pts, phs, cols, n_points, n_photos)
