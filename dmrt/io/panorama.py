"""Panoramas cut into pinhole views: E57's spherical and cylindrical images (ASTM E2807,
8.4.14-15) become photos that depth maps and raytracing use unchanged.

The panorama's frame (the standard's): x through the image's horizontal centre, z up; azimuth
``θ = atan2(y, x)``, elevation ``φ`` up from the xy plane. Image coordinates have (0, 0) at the
top-left corner of the top-left pixel::

    spherical    x_image = W/2 - θ / pixelWidth     y_image = H/2 - φ / pixelHeight      (radians)
    cylindrical  x_image = W/2 - θ / pixelWidth     y_image = principalPointY - (z/ρ) radius / pixelHeight

**The views** (:func:`cube_views`): the six faces of a cube around the panorama's centre (90°
fields of view), each ``S = 2 / pixelWidth`` pixels wide, so that at a face's centre one view
pixel spans one panorama pixel: the panorama's resolution is kept (towards a face's edges the
view samples more finely than the panorama). A face with directions the panorama does not cover
(a partial panorama, a cylinder's poles, pixels its mask marks invalid) is cropped to its largest
rectangle of covered pixels, which keeps it a pinhole view, and dropped when that rectangle holds
less than :data:`MIN_FACE_SHARE` of the face.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from dmrt.camera import Camera

MIN_FACE_SHARE = 1 / 16  # a face cropped to less of its area than this is dropped
_COVERAGE_GRID = 128     # a partial face's coverage is tested on this many cells a side

# face -> (forward, image-down) in the panorama's frame; image-right = down x forward
FACES = {"front": ((1, 0, 0), (0, 0, -1)), "left": ((0, 1, 0), (0, 0, -1)),
         "back": ((-1, 0, 0), (0, 0, -1)), "right": ((0, -1, 0), (0, 0, -1)),
         "up": ((0, 0, 1), (1, 0, 0)), "down": ((0, 0, -1), (-1, 0, 0))}


def face_rotation(face: str) -> np.ndarray:
    """(3, 3) float64 rotation panorama frame -> the face camera's (OpenCV axes)."""
    forward, down = (np.asarray(v, np.float64) for v in FACES[face])
    return np.stack([np.cross(down, forward), down, forward])


@dataclass(frozen=True)
class Panorama:
    """A spherical or cylindrical image's projection (the E57 representation's fields).

    Attributes
    ----------
    kind : "spherical" or "cylindrical"
    width, height : int, pixels
    pixel_width : float, radians of azimuth per pixel
    pixel_height : float, radians of elevation (spherical) or metres on the cylinder per pixel
    radius : float, metres: the cylinder's radius (cylindrical only)
    principal_y : float, pixels: the row of the z = 0 plane (cylindrical only)
    """

    kind: Literal["spherical", "cylindrical"]
    width: int
    height: int
    pixel_width: float
    pixel_height: float
    radius: float = 0.0
    principal_y: float = 0.0

    @property
    def full_turn(self) -> bool:
        """The columns cover all azimuths (within half a pixel)."""
        return (self.width + 0.5) * self.pixel_width >= 2 * np.pi

    @property
    def full_sphere(self) -> bool:
        """Spherical, and every direction is covered."""
        return (self.kind == "spherical" and self.full_turn
                and (self.height + 0.5) * self.pixel_height >= np.pi)

    def pixel_of(self, d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Where directions land in the image.

        Parameters
        ----------
        d : (n, 3) float64 directions in the panorama's frame (any length > 0).

        Returns
        -------
        xy : (n, 2) float64 image coordinates (corner origin); x wrapped into [0, W) for a full turn.
        covered : (n,) bool, inside the image.
        """
        x, y, z = np.asarray(d, np.float64).T
        rho = np.hypot(x, y)
        theta = np.arctan2(y, x)
        xi = self.width / 2 - theta / self.pixel_width
        with np.errstate(divide="ignore", invalid="ignore"):
            if self.kind == "spherical":
                yi = self.height / 2 - np.arctan2(z, rho) / self.pixel_height
            else:
                yi = self.principal_y - z / rho * self.radius / self.pixel_height
        if self.full_turn:
            xi = np.mod(xi, self.width)
        covered = np.isfinite(yi) & (xi >= 0) & (xi <= self.width) & (yi >= 0) & (yi <= self.height)
        return np.stack([xi, yi], axis=1), covered

    def face_size(self) -> int:
        """Pixels a side of a full cube face: one panorama pixel per view pixel at its centre."""
        return max(2, int(round(2 / self.pixel_width)))


def largest_rectangle(valid: np.ndarray) -> tuple[int, int, int, int] | None:
    """``(row0, col0, row1, col1)`` (ends exclusive) of the largest all-True axis-aligned
    rectangle of the (h, w) bool array ``valid``, None if it has no True; the largest rectangle
    under each row's histogram of True runs, with a stack."""
    h, w = valid.shape
    heights = np.zeros(w + 1, np.int64)  # heights[w] = 0 empties the stack at each row's end
    best, box = 0, None
    for r in range(h):
        heights[:w] = np.where(valid[r], heights[:w] + 1, 0)
        stack: list[tuple[int, int]] = []  # (first column, height), heights increasing
        for c in range(w + 1):
            start = c
            while stack and stack[-1][1] >= heights[c]:
                s, hgt = stack.pop()
                if hgt * (c - s) > best:
                    best, box = hgt * (c - s), (r - hgt + 1, s, r + 1, c)
                start = s
            stack.append((start, int(heights[c])))
    return box


def valid_box(cells: np.ndarray, height: int, width: int) -> tuple[int, int, int, int] | None:
    """``(row0, col0, row1, col1)`` pixels (ends exclusive) of the largest rectangle of valid
    ``cells`` ((gr, gc) bool spanning ``height`` x ``width`` pixels evenly), rounded inwards;
    None if no cell is valid."""
    rect = largest_rectangle(cells)
    if rect is None:
        return None
    gr, gc = cells.shape
    return (int(np.ceil(rect[0] * height / gr)), int(np.ceil(rect[1] * width / gc)),
            int(rect[2] * height // gr), int(rect[3] * width // gc))


def mask_cells(mask: np.ndarray) -> np.ndarray:
    """(gr, gc) bool: which cells of an (h, w) bool ``mask``, cut into at most
    :data:`_COVERAGE_GRID` even cells a side, are valid throughout (for :func:`valid_box`)."""
    h, w = mask.shape
    rows = np.floor(np.linspace(0, h, min(h, _COVERAGE_GRID) + 1)[:-1]).astype(np.int64)
    cols = np.floor(np.linspace(0, w, min(w, _COVERAGE_GRID) + 1)[:-1]).astype(np.int64)
    return np.logical_and.reduceat(np.logical_and.reduceat(mask, rows, axis=0), cols, axis=1)


def _covered_cells(pano: Panorama, rotation: np.ndarray, size: int, mask: np.ndarray | None) -> np.ndarray:
    """(g, g) bool: the cells of a ``size``-wide face whose four corners the panorama covers."""
    g = min(size, _COVERAGE_GRID)
    f = size / 2
    u = np.linspace(0, size, g + 1)
    uu, vv = np.meshgrid(u, u)
    d = np.stack([(uu.ravel() - f) / f, (vv.ravel() - f) / f, np.ones(uu.size)], axis=1) @ rotation
    xy, ok = pano.pixel_of(d)
    if mask is not None:
        mh, mw = mask.shape
        col = np.clip(np.floor(np.nan_to_num(xy[:, 0])).astype(np.int64), 0, mw - 1)
        row = np.clip(np.floor(np.nan_to_num(xy[:, 1])).astype(np.int64), 0, mh - 1)
        ok &= mask[row, col]
    ok = ok.reshape(g + 1, g + 1)
    return ok[:-1, :-1] & ok[1:, :-1] & ok[:-1, 1:] & ok[1:, 1:]


def cube_views(pano: Panorama, name: str, mask: np.ndarray | None = None) -> list[tuple[str, Camera]]:
    """The pinhole views cut from ``pano`` (module docstring), in :data:`FACES` order.

    Parameters
    ----------
    pano : the panorama's projection.
    name : each view's camera is named ``f"{name}-{face}"``.
    mask : (H, W) bool, optional: the panorama's valid pixels (E57 ``imageMask``).

    Returns
    -------
    list of (face, Camera)
        Each view's camera in the panorama's frame (``R`` = :func:`face_rotation`, ``t`` = 0):
        focal length ``S/2`` pixels, principal point where the face's centre falls in the crop.
    """
    size = pano.face_size()
    f = size / 2
    views = []
    for face in FACES:
        rotation = face_rotation(face)
        box = (0, 0, size, size)
        if not (pano.full_sphere and mask is None):
            box = valid_box(_covered_cells(pano, rotation, size, mask), size, size)
        h, w = (0, 0) if box is None else (box[2] - box[0], box[3] - box[1])
        if h < 1 or w < 1 or h * w < MIN_FACE_SHARE * size * size:
            continue
        views.append((face, Camera(f"{name}-{face}", w, h, f, f, f - box[1], f - box[0], rotation, np.zeros(3))))
    return views


class PanoramaView:
    """``rgb -> rgb``: the panorama's (H, W, 3) uint8 pixels resampled (bilinear) into the view
    ``camera`` (in the panorama's frame, as :func:`cube_views` gives it); the maps are made on
    first use and not pickled."""

    def __init__(self, pano: Panorama, camera: Camera):
        self.pano, self.camera = pano, camera
        self._maps = None

    def maps(self) -> tuple[np.ndarray, np.ndarray]:
        """(h, w) float32 x and y: the OpenCV pixel of the panorama each view pixel samples (one
        column more on each side for a full turn, see :meth:`__call__`)."""
        if self._maps is None:
            d, _ = self.camera.pixel_rays()
            xy, _ = self.pano.pixel_of(d)
            xy = xy - 0.5 + [1.0 if self.pano.full_turn else 0.0, 0.0]
            shape = (self.camera.height, self.camera.width)
            self._maps = tuple(np.nan_to_num(a).reshape(shape).astype(np.float32) for a in xy.T)
        return self._maps

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        import cv2

        rgb = np.ascontiguousarray(rgb)
        if rgb.shape[:2] != (self.pano.height, self.pano.width):
            raise ValueError(f"the panorama is {rgb.shape[1]}x{rgb.shape[0]} pixels, its header says "
                             f"{self.pano.width}x{self.pano.height}")
        if self.pano.full_turn:  # the seam: the last column next to the first
            rgb = np.concatenate([rgb[:, -1:], rgb, rgb[:, :1]], axis=1)
        mx, my = self.maps()
        return cv2.remap(rgb, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def __getstate__(self):
        return {**self.__dict__, "_maps": None}
