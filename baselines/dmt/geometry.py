"""DMT geometry on the CPU: depth maps at a DMT resolution, their texel points and normals, the
grid triangulation with its discontinuity test, bounding boxes and view-frustum culling.

Everything here is plain numpy in the bundle's scene-origin-relative frame (metres). The GPU runtime
(:mod:`baselines.dmt.renderer`, ``shaders/dmt_mesh.glsl``) builds the very same triangles; the tests
check it against :func:`grid_triangles`.

Resampling to a DMT resolution
------------------------------
A bundle stores one depth map per photo at one resolution (``W_s`` texels wide). DMT at width
``W <= W_s`` uses ``(W, H)`` maps, ``H`` following the photo's aspect (:func:`dmrt.preprocess.depthmaps.depth_map_size`).
Coarse texel ``(r, c)`` takes the value of the *stored texel nearest to its centre*: column
``floor((c + 0.5) W_s / W)``, row ``floor((r + 0.5) H_s / H)``. No averaging, so an empty texel never
mixes with a surface and a depth edge stays a jump (a mean or bilinear filter would invent surface
in mid-air across a silhouette). The value is then treated as the depth at the coarse texel's centre;
where ``W_s / W`` is even the two centres are half a stored texel apart, which moves the point by at
most half a stored texel's footprint along the surface (under a coarse texel's, the runtime's
resolution). A higher resolution than stored cannot be made up and is refused.
"""

from __future__ import annotations

import numpy as np

from dmrt.camera import Camera
from dmrt.preprocess.depthmaps import depth_map_size
from dmrt.errors import InputError

# Triangle split of the quad of texels (00, 10, 01, 11) - (column, row) offsets - along the 10-01
# diagonal, as DMRT's surface_depth (shaders/dmrt_photos.glsl): T0 = (00, 10, 01), T1 = (10, 11, 01).
TRIANGLES = (((0, 0), (1, 0), (0, 1)), ((1, 0), (1, 1), (0, 1)))


def dmt_size(camera: Camera, width: int) -> tuple[int, int]:
    """``(width, height)`` of camera's DMT depth map ``width`` texels wide."""
    return depth_map_size(camera, width)


def resample_nearest(depth: np.ndarray, width: int, height: int) -> np.ndarray:
    """The depth map at ``width`` x ``height``: each texel the stored texel nearest its centre.

    Parameters
    ----------
    depth : (H_s, W_s) float32, camera z, 0 = empty.
    width, height : int, at most ``W_s`` and ``H_s``.

    Returns
    -------
    (height, width) float32.
    """
    hs, ws = depth.shape
    if width > ws or height > hs:
        raise ValueError(f"cannot resample a {ws}x{hs} depth map up to {width}x{height}")
    cols = np.minimum(((np.arange(width) + 0.5) * ws / width).astype(np.int64), ws - 1)
    rows = np.minimum(((np.arange(height) + 0.5) * hs / height).astype(np.int64), hs - 1)
    return np.ascontiguousarray(depth[rows][:, cols], np.float32)


def load_depth_map(bundle, i: int, width: int, stored: np.ndarray | None = None) -> np.ndarray:
    """Photo ``i``'s depth map at DMT width ``width``: (h, w) float32 camera z, 0 = empty.

    ``stored`` : the bundle's map if already read. Raises :class:`InputError` (naming the depth-map
    file) when ``width`` exceeds the stored resolution.
    """
    d = bundle.depth_map(i) if stored is None else stored
    w, h = check_dmt_size(bundle, i, width, (d.shape[1], d.shape[0]))
    return resample_nearest(d, w, h)


def check_dmt_size(bundle, i: int, width: int, stored: tuple[int, int]) -> tuple[int, int]:
    """Photo ``i``'s DMT map size ``(w, h)`` at ``width``; :class:`InputError` naming the depth-map
    file when it exceeds the stored map's ``(width, height)``."""
    w, h = dmt_size(bundle.cameras[i], width)
    if w > stored[0] or h > stored[1]:
        raise InputError(bundle.path("depthmaps", i),
                         f"DMT resolution {w}x{h} is higher than the stored depth map's "
                         f"{stored[0]}x{stored[1]}: preprocess with --depthmap-width {w} or more")
    return w, h


def texel_points(depth: np.ndarray, camera: Camera) -> np.ndarray:
    """Points of every texel centre: (h, w, 3) float64 in ``camera``'s world frame, NaN where empty.

    ``camera`` is the photo's camera scaled to the depth map (``camera.scaled(w, h)``), e.g.
    relative to the scene origin.
    """
    h, w = depth.shape
    j, i = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    z = np.where(depth > 0, depth, np.nan).astype(np.float64)
    pc = np.stack([(j - camera.cx) / camera.fx * z, (i - camera.cy) / camera.fy * z, z], axis=-1)
    return (pc - camera.t) @ camera.R  # R^T (pc - t), row-vector form


def _pair_ok(depth: np.ndarray, threshold: float, axis: int) -> np.ndarray:
    """Neighbour pairs along ``axis`` (1: columns, 0: rows) that are both non-empty and within the
    discontinuity threshold. Shape: one less along ``axis``."""
    a = depth[:, :-1] if axis == 1 else depth[:-1]
    b = depth[:, 1:] if axis == 1 else depth[1:]
    return (a > 0) & (b > 0) & (np.abs(a - b) <= threshold)


def grid_edges(depth: np.ndarray, threshold: float) -> np.ndarray:
    """The 4-neighbourhood graph of a depth map: (e, 2) int64 flat texel indices ``r * w + c``,
    only between non-empty texels whose depths differ by at most ``threshold`` metres."""
    h, w = depth.shape
    idx = np.arange(h * w, dtype=np.int64).reshape(h, w)
    horiz = _pair_ok(depth, threshold, 1)
    vert = _pair_ok(depth, threshold, 0)
    return np.concatenate([np.stack([idx[:, :-1][horiz], idx[:, 1:][horiz]], 1),
                           np.stack([idx[:-1][vert], idx[1:][vert]], 1)]).reshape(-1, 2)


def grid_normals(points: np.ndarray, depth: np.ndarray, threshold: float) -> np.ndarray:
    """Unit normals of texel points from their grid neighbours: (h, w, 3) float32.

    Tangents are central differences where both neighbours are continuous with the texel (non-empty,
    within ``threshold``), one-sided where only one is; normal = cross(d/dcolumn, d/drow), not yet
    oriented (:func:`orient_normals`). NaN where a texel has no continuous neighbour along a grid
    axis. ``points`` from :func:`texel_points` (NaN where empty).
    """
    h, w = depth.shape
    tangents = []
    for axis in (1, 0):
        ok = _pair_ok(depth, threshold, axis)
        diff = np.diff(points, axis=axis)
        fwd = np.zeros_like(points)
        bwd = np.zeros_like(points)
        fok = np.zeros((h, w), bool)
        bok = np.zeros((h, w), bool)
        if axis == 1:
            fwd[:, :-1], fok[:, :-1] = diff, ok
            bwd[:, 1:], bok[:, 1:] = diff, ok
        else:
            fwd[:-1], fok[:-1] = diff, ok
            bwd[1:], bok[1:] = diff, ok
        t = np.where(fok[..., None], np.nan_to_num(fwd), 0.0) + np.where(bok[..., None], np.nan_to_num(bwd), 0.0)
        tangents.append((t, fok | bok))
    (tu, oku), (tv, okv) = tangents
    n = np.cross(tu, tv)
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    good = oku & okv & (length[..., 0] > 0)
    return np.where(good[..., None], n / np.maximum(length, 1e-30), np.nan).astype(np.float32)


def orient_normals(normals: np.ndarray, points: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """Normals (n, 3) turned to face ``eye`` (3,); NaN rows (no tangent) become the direction from
    the point to ``eye``. Returns (n, 3) float32 unit."""
    to_eye = np.asarray(eye, np.float64) - points
    to_eye /= np.maximum(np.linalg.norm(to_eye, axis=1, keepdims=True), 1e-30)
    n = np.where(np.isnan(normals).any(axis=1, keepdims=True), to_eye, normals)
    flip = np.einsum("ij,ij->i", n, to_eye) < 0
    n[flip] *= -1
    return n.astype(np.float32)


def grid_triangles(depth: np.ndarray, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """Which triangles of the grid mesh exist: ``(t0, t1)``, each (h-1, w-1) bool.

    Quad ``(r, c)`` (top-left texel) splits into T0 = (00, 10, 01) and T1 = (10, 11, 01)
    (:data:`TRIANGLES`, (column, row) offsets). A triangle exists when its three texels are
    non-empty and their depths span at most ``threshold`` metres (DMT drops triangles across
    depth discontinuities).
    """
    d = depth
    q = {(0, 0): d[:-1, :-1], (1, 0): d[:-1, 1:], (0, 1): d[1:, :-1], (1, 1): d[1:, 1:]}
    out = []
    for tri in TRIANGLES:
        z = np.stack([q[v] for v in tri])
        out.append((z > 0).all(0) & (z.max(0) - z.min(0) <= threshold))
    return out[0], out[1]


def bounding_box(points: np.ndarray) -> np.ndarray:
    """(2, 3) float64 min and max corner of the finite rows of ``points`` (..., 3); NaN if none."""
    p = points.reshape(-1, 3)
    p = p[np.isfinite(p).all(1)]
    if len(p) == 0:
        return np.full((2, 3), np.nan)
    return np.stack([p.min(0), p.max(0)])


def box_corners(boxes: np.ndarray) -> np.ndarray:
    """(n, 8, 3) corners of (n, 2, 3) boxes (bit k of the corner index picks max along axis k)."""
    boxes = np.asarray(boxes, np.float64).reshape(-1, 2, 3)
    sel = ((np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1).astype(bool)  # (8, 3) True = max
    return np.where(sel[None], boxes[:, None, 1, :], boxes[:, None, 0, :])


def frustum_culled(boxes: np.ndarray, view_projection: np.ndarray) -> np.ndarray:
    """(n,) bool: boxes wholly outside one plane of the view frustum (conservative: a box that is
    outside but not beyond a single plane is kept). Boxes with NaN (empty maps) are culled.

    ``view_projection`` (4, 4) maps the boxes' frame to OpenGL clip space; each frustum plane is the
    half-space ``w ± x >= 0`` (likewise y, z) in clip coordinates, a linear test in the boxes'
    frame, so "all 8 corners outside one plane" implies the whole box is.
    """
    c = box_corners(boxes)
    clip = np.concatenate([c, np.ones(c.shape[:2] + (1,))], axis=2) @ np.asarray(view_projection, np.float64).T
    x, y, z, w = (clip[..., k] for k in range(4))
    outside = [x > w, x < -w, y > w, y < -w, z > w, z < -w]
    culled = np.any([o.all(axis=1) for o in outside], axis=0)
    return culled | ~np.isfinite(np.asarray(boxes).reshape(-1, 6)).all(1)


def grid_mesh(depth: np.ndarray, camera: Camera, threshold: float) -> tuple[np.ndarray, np.ndarray]:
    """The triangle mesh DMT draws for one depth map (the CPU twin of ``shaders/dmt_mesh.glsl``).

    Parameters
    ----------
    depth : (h, w) float32, the map at the DMT resolution.
    camera : the photo's camera scaled to (w, h), in the frame the vertices should be in.
    threshold : float, discontinuity threshold, metres.

    Returns
    -------
    vertices : (h * w, 3) float64, texel points (NaN for empty texels, which no face uses).
    faces : (m, 3) int64 indices (flat texel index ``r * w + c``) of the existing triangles.
    """
    h, w = depth.shape
    t0, t1 = grid_triangles(depth, threshold)
    idx = np.arange(h * w, dtype=np.int64).reshape(h, w)
    corner = {(0, 0): idx[:-1, :-1], (1, 0): idx[:-1, 1:], (0, 1): idx[1:, :-1], (1, 1): idx[1:, 1:]}
    faces = [np.stack([corner[v][ok] for v in tri], axis=1) for tri, ok in zip(TRIANGLES, (t0, t1))]
    return texel_points(depth, camera).reshape(-1, 3), np.concatenate(faces).reshape(-1, 3)
