"""Photos reprojected into another view through the scene's geometry: what the data allows there.

A renderer at a new view can at best show, at each pixel, the colour some photo recorded of that
pixel's surface point. Given the surface at the view (camera z per pixel: an Embree cast of the
reference mesh, or a renderer's depth), each photo is *reprojected* into it: every surface point
is projected into the photo, kept where the photo sees it (an occlusion test: Embree on the mesh,
or the photo's depth map within a tolerance) and given the photo's colour there (bilinear). Two
bounds follow (Debevec et al. 1996; Buehler et al. 2001 rank photos the same way):

- the best single photo: one photo reprojected alone (the caller ranks them, e.g. by PSNR);
- the view-closest photo per pixel: among the photos that see the point, the one whose ray to it
  is closest in angle to the view's ray (:class:`ViewClosest`).

Plain numpy; visibility is a callable so the mesh (:meth:`reference.raycast.MeshRaycaster.visible`)
and depth maps (:func:`depth_map_visibility`) plug in alike.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable, Iterable, Iterator

import numpy as np

from dmrt.camera import Camera
from dmrt.preprocess.candidates import sample_bilinear

# A depth map sees a point when its depth there is within DEPTH_TOLERANCE_REL * z +
# DEPTH_TOLERANCE_TEXELS texel footprints (z / f) of the point's own depth: 2 % covers a
# Kinect's range noise (~1.5 % at 4 m) and the splat bias of depth maps drawn from points; two
# texels cover the depth change across a texel of a surface slanted up to ~60 degrees.
DEPTH_TOLERANCE_REL = 0.02
DEPTH_TOLERANCE_TEXELS = 2.0

# (m, 3) world points -> (m,) bool: whether the photo sees them (unoccluded)
Visibility = Callable[[np.ndarray], np.ndarray]


def surface_points(camera: Camera, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """World points of the pixels of ``camera`` that have a surface.

    Parameters
    ----------
    camera : the view.  depth : (h, w) float camera z, metres, 0 = no surface.

    Returns
    -------
    points : (m, 3) float64 world metres, row-major over the surface pixels.
    hit : (h, w) bool, the surface pixels.
    """
    if depth.shape != (camera.height, camera.width):
        raise ValueError(f"depth {depth.shape} is not the camera's {camera.height}x{camera.width}")
    hit = depth > 0
    dirs, center = camera.pixel_rays()  # scaled so that the ray parameter is camera z
    return center + dirs[hit.ravel()] * depth[hit].astype(np.float64)[:, None], hit


def in_frame(camera: Camera, points: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel coordinates ``uv`` (m, 2), depth ``z`` (m,) and ``inside`` (m,) bool (in front of
    ``camera`` and within its frame) of world ``points`` (m, 3)."""
    uv, z = camera.project(points)
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] < camera.height)
    return uv, z, inside


def depth_map_visibility(camera: Camera, depth_map: np.ndarray, rel: float = DEPTH_TOLERANCE_REL,
                         texels: float = DEPTH_TOLERANCE_TEXELS) -> Visibility:
    """Visibility from photo ``camera``'s depth map ``depth_map`` ((h, w) float32 camera z, 0 =
    empty; any resolution, the camera is scaled to it): a point is seen where the map's nearest
    texel holds a depth within ``rel * z + texels * z / f`` of the point's ``z`` (see
    :data:`DEPTH_TOLERANCE_REL`); never where the map is empty."""
    cam = camera.scaled(depth_map.shape[1], depth_map.shape[0])

    def visible(points: np.ndarray) -> np.ndarray:
        uv, z, inside = in_frame(cam, points)
        ij = np.where(inside[:, None], uv, 0).astype(np.int64)
        d = np.where(inside, depth_map[ij[:, 1], ij[:, 0]], 0.0)
        return inside & (d > 0) & (np.abs(d - z) <= z * (rel + texels / cam.fx))

    return visible


@dataclass
class Reprojection:
    """One photo reprojected into a view.

    Attributes
    ----------
    photo : the photo's index.
    color : (h, w, 3) float32 RGB in the photo's range (0..255), 0 where ``seen`` is False.
    seen : (h, w) bool: the photo sees the pixel's surface point.
    cos : (h, w) float32: cosine of the angle between the view's ray and the photo's ray to the
        point (1 = same direction), -1 where not ``seen``.
    """

    photo: int
    color: np.ndarray
    seen: np.ndarray
    cos: np.ndarray


def reproject(view: Camera, depth: np.ndarray, photo: int, camera: Camera, image: np.ndarray,
              visible: Visibility) -> Reprojection:
    """Photo ``photo`` (its ``camera`` and ``image`` (H, W, 3) uint8, ``visible`` its occlusion
    test) reprojected into ``view`` through the surface ``depth`` ((h, w) camera z of ``view``,
    metres, 0 = none)."""
    points, hit = surface_points(view, depth)
    return _reproject(view, points, hit, photo, camera, image, visible)


def _reproject(view, points, hit, photo, camera, image, visible) -> Reprojection:
    h, w = hit.shape
    cam = camera.scaled(image.shape[1], image.shape[0])  # the photo as stored
    uv, _, inside = in_frame(cam, points)
    idx = np.flatnonzero(inside)
    idx = idx[visible(points[idx])] if len(idx) else idx
    flat = np.flatnonzero(hit.ravel())[idx]
    color = np.zeros((h * w, 3), np.float32)
    seen = np.zeros(h * w, bool)
    cos = np.full(h * w, -1.0, np.float32)
    if len(idx):
        color[flat] = sample_bilinear(image, uv[idx])
        seen[flat] = True
        p = points[idx]
        a, b = p - view.center, p - camera.center
        cos[flat] = np.einsum("ij,ij->i", a, b) / np.maximum(np.linalg.norm(a, axis=1) * np.linalg.norm(b, axis=1), 1e-30)
    return Reprojection(photo, color.reshape(h, w, 3), seen.reshape(h, w), cos.reshape(h, w))


def reproject_photos(view: Camera, depth: np.ndarray, cameras: list[Camera], images: Callable[[int], np.ndarray],
                     visibility: Callable[[int], Visibility], photos: Iterable[int] | None = None) -> Iterator[Reprojection]:
    """:func:`reproject` of each photo (``photos``, default all of ``cameras``) whose frame holds
    any of the view's surface points; ``images(j)`` and ``visibility(j)`` are asked only for those,
    so a caller may read photos and depth maps lazily."""
    points, hit = surface_points(view, depth)
    for j in range(len(cameras)) if photos is None else photos:
        if len(points) == 0 or not in_frame(cameras[j], points)[2].any():
            continue
        yield _reproject(view, points, hit, j, cameras[j], images(j), visibility(j))


class ViewClosest:
    """The per-pixel view-closest photo: fed :class:`Reprojection` s of one view one at a time,
    it keeps at each pixel the colour of the photo that sees the point with the smallest angle
    between its ray and the view's ray (the first one on a tie).

    Attributes
    ----------
    color : (h, w, 3) float32, 0 where no photo sees the point.
    label : (h, w) int32 photo index, -1 = none.
    cos : (h, w) float32 cosine of the chosen photo's angle, -1 = none.
    """

    def __init__(self, height: int, width: int):
        self.color = np.zeros((height, width, 3), np.float32)
        self.label = np.full((height, width), -1, np.int32)
        self.cos = np.full((height, width), -1.0, np.float32)

    @property
    def seen(self) -> np.ndarray:
        """(h, w) bool: some photo sees the pixel's point."""
        return self.label >= 0

    def add(self, r: Reprojection) -> None:
        better = r.seen & (r.cos > self.cos)
        self.color[better] = r.color[better]
        self.label[better] = r.photo
        self.cos[better] = r.cos[better]
