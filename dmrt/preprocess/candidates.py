"""Candidates (paper Section 4.3): the photos that see each proxy point, by the occlusion test
against each photo's depth map, and the proxy's colour in each (the labeling's seam term)."""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from dmrt.preprocess.config import PreprocessConfig
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
                    radii: np.ndarray | None = None) -> Candidates:
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

    Returns
    -------
    Candidates (CSR over points; colours RGB 0..1).
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

    pts, phs, cols, rim_ok = [], [], [], []
    for j, cam in enumerate(tqdm(cameras, desc="candidates", unit="photo", disable=not progress)):
        depth = depth_maps(j)
        h, w = depth.shape
        dm_cam = cam.scaled(w, h)
        uv, z = dm_cam.project(p)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        idx = np.flatnonzero(inside)
        to_eye = cam.center - p[idx]
        cos = np.abs(np.einsum("ij,ij->i", to_eye, normals[idx])) / np.linalg.norm(to_eye, axis=1)
        idx = idx[(cos >= config.candidate_min_cos) & seen(dm_cam, depth, p[idx], idx)]
        if len(idx) == 0:
            continue
        uv_photo, _ = cam.project(p[idx])
        pts.append(idx)
        phs.append(np.full(len(idx), j))
        cols.append(sample_bilinear(photos(j), uv_photo) / 255.0)
        if rims is not None:
            frac = np.mean([seen(dm_cam, depth, rim[idx], idx) for rim in rims], axis=0)
            rim_ok.append(frac >= config.candidate_rim_fraction)
    if not pts:
        return Candidates(np.zeros(len(p) + 1, np.int64), np.zeros(0, np.int32), None, len(cameras))
    pts, phs, cols = np.concatenate(pts), np.concatenate(phs), np.concatenate(cols)
    if rims is not None:
        ok = np.concatenate(rim_ok)
        has_ok = np.zeros(len(p), bool)
        has_ok[pts[ok]] = True
        keep = ok | ~has_ok[pts]  # a point none of whose photos sees its rim keeps them all
        pts, phs, cols = pts[keep], phs[keep], cols[keep]
    return Candidates.from_pairs(pts, phs, cols, len(p), len(cameras))
