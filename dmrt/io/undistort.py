"""Lens distortion ends here: a photo of a distorted COLMAP camera becomes a pinhole photo, once,
in preprocessing, so that depth maps, the bundle and every renderer stay pinhole.

COLMAP's models and their parameters (its ``sensor/models.h``)::

    SIMPLE_RADIAL   f, cx, cy, k                       OpenCV distCoeffs (k, 0, 0, 0)
    RADIAL          f, cx, cy, k1, k2                  (k1, k2, 0, 0)
    OPENCV          fx, fy, cx, cy, k1, k2, p1, p2     (k1, k2, p1, p2)
    FULL_OPENCV     fx, fy, cx, cy, k1, k2, p1, p2,    (k1, k2, p1, p2, k3, k4, k5, k6): OpenCV's
                    k3, k4, k5, k6                     rational model, in OpenCV's own order
    OPENCV_FISHEYE  fx, fy, cx, cy, k1, k2, k3, k4     ``cv2.fisheye``'s equidistant model

The first four with all coefficients 0 are plain pinhole cameras (:func:`lens` gives None: the
photo is used as it is); a fisheye with zero coefficients is still equidistant, not pinhole.

**The pinhole camera that replaces a distorted one** (:func:`undistorted_camera`) keeps the
photo's size and its ratio fx/fy, and crops: its focal lengths are the distorted camera's times
one factor, and its principal point centres the frame, such that every pixel of the new photo
samples inside the distorted one. The photo then has no black border that could texture a
surface black; the price is the edge of the original frame that pincushion distortion pushes
outside. OpenCV does the pixel work (``initUndistortRectifyMap`` and ``remap``, or the
``cv2.fisheye`` twins): its models are COLMAP's.

Pixel coordinates: COLMAP puts the top-left pixel's centre at (0.5, 0.5), OpenCV at (0, 0); the
conversion is :func:`_cv_matrix`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from dmrt.camera import Camera

LENS_MODELS = ("SIMPLE_RADIAL", "RADIAL", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE")
_BORDER_SAMPLES = 257  # points along each edge of the photo whose undistortion bounds the crop


@dataclass(frozen=True)
class Lens:
    """A COLMAP camera's distortion.

    Attributes
    ----------
    model : one of :data:`LENS_MODELS`.
    coeffs : (k,) float64
        OpenCV's ``distCoeffs`` (4 or 8 values), or the fisheye's ``D`` (k1..k4).
    """

    model: str
    coeffs: tuple[float, ...]

    @property
    def fisheye(self) -> bool:
        return self.model == "OPENCV_FISHEYE"

    def cv_coeffs(self) -> np.ndarray:
        return np.asarray(self.coeffs, np.float64)


def split_params(model: str, params) -> tuple[tuple[float, float, float, float], Lens | None]:
    """A COLMAP camera's parameters -> ``((fx, fy, cx, cy), lens)``; ``lens`` is None for PINHOLE,
    SIMPLE_PINHOLE and the non-fisheye models whose coefficients are all 0 (exactly pinhole).
    ``params`` must have the model's length (the caller checks it)."""
    p = [float(v) for v in params]
    if model == "SIMPLE_PINHOLE":
        return (p[0], p[0], p[1], p[2]), None
    if model == "PINHOLE":
        return (p[0], p[1], p[2], p[3]), None
    if model in ("SIMPLE_RADIAL", "RADIAL"):
        intrinsics, coeffs = (p[0], p[0], p[1], p[2]), (p[3:] + [0.0] * 4)[:4]
    else:
        intrinsics, coeffs = tuple(p[:4]), p[4:]
    if model != "OPENCV_FISHEYE" and not any(coeffs):
        return intrinsics, None
    return intrinsics, Lens(model, tuple(coeffs))


def _cv_matrix(c: Camera) -> np.ndarray:
    """(3, 3) float64 OpenCV camera matrix of ``c`` (pixel centres at integers)."""
    return np.array([[c.fx, 0.0, c.cx - 0.5], [0.0, c.fy, c.cy - 0.5], [0.0, 0.0, 1.0]])


def _undistort_points(uv: np.ndarray, camera: Camera, lens: Lens) -> np.ndarray:
    """(n, 2) OpenCV pixel coordinates of the distorted photo -> (n, 2) float64 normalised
    pinhole coordinates ``(x / z, y / z)``; iterated to 1e-12 (OpenCV's default 5 iterations
    leave pixels of error at strongly distorted corners)."""
    import cv2

    pts = np.ascontiguousarray(uv, np.float64).reshape(-1, 1, 2)
    crit = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 200, 1e-12)
    K = _cv_matrix(camera)
    if lens.fisheye:
        out = cv2.fisheye.undistortPoints(pts, K, lens.cv_coeffs(), criteria=crit)
    elif hasattr(cv2, "undistortPointsIter"):  # OpenCV 4: the iterated form has its own name
        out = cv2.undistortPointsIter(pts, K, lens.cv_coeffs(), None, None, crit)
    else:
        out = cv2.undistortPoints(pts, K, lens.cv_coeffs(), criteria=crit)
    return out.reshape(-1, 2)


def _distort_points(xy: np.ndarray, camera: Camera, lens: Lens) -> np.ndarray:
    """(n, 2) normalised pinhole coordinates -> (n, 2) float64 OpenCV pixels of the distorted photo."""
    import cv2

    pts = np.concatenate([xy, np.ones((len(xy), 1))], axis=1).reshape(-1, 1, 3)
    zero, K, D = np.zeros(3), _cv_matrix(camera), lens.cv_coeffs()
    project = cv2.fisheye.projectPoints if lens.fisheye else cv2.projectPoints
    return project(pts, zero, zero, K, D)[0].reshape(-1, 2)


def undistorted_camera(camera: Camera, lens: Lens) -> Camera:
    """The pinhole camera whose photo :class:`Undistortion` makes from ``camera``'s.

    Same name, pose and size; ``fx' = s fx``, ``fy' = s fy`` with the smallest ``s`` for which
    the frame fits inside the undistorted outline of the photo's outermost pixel centres, and the
    principal point centring the frame in the largest rectangle inside that outline.

    Raises
    ------
    ValueError
        When the coefficients fold the image (no such rectangle), with the reason.
    """
    W, H, n = camera.width, camera.height, _BORDER_SAMPLES
    us, vs = np.linspace(0, W - 1, n), np.linspace(0, H - 1, n)
    edges = [np.stack([np.zeros(n), vs], 1), np.stack([np.full(n, W - 1.0), vs], 1),
             np.stack([us, np.zeros(n)], 1), np.stack([us, np.full(n, H - 1.0)], 1)]
    left, right, top, bottom = (_undistort_points(e, camera, lens) for e in edges)
    x0, x1 = left[:, 0].max(), right[:, 0].min()
    y0, y1 = top[:, 1].max(), bottom[:, 1].min()
    # beyond a fold the distortion has no inverse: the iteration ends anywhere, off the border
    back = _distort_points(np.concatenate([left, right, top, bottom]), camera, lens)
    if not (np.isfinite([x0, x1, y0, y1]).all() and x1 > x0 and y1 > y0
            and np.abs(back - np.concatenate(edges)).max() < 0.01):
        raise ValueError(f"its {lens.model} coefficients {list(lens.coeffs)} fold the image: the "
                         f"distortion has no inverse out to the photo's border")
    # pixel centres 0.5 .. W - 0.5 of the new photo span (W - 1) / fx' in normalised units
    s = max((W - 1) / ((x1 - x0) * camera.fx), (H - 1) / ((y1 - y0) * camera.fy))
    fx, fy = s * camera.fx, s * camera.fy
    return Camera(camera.name, W, H, fx, fy, W / 2 - fx * (x0 + x1) / 2, H / 2 - fy * (y0 + y1) / 2,
                  camera.R, camera.t)


class Undistortion:
    """``rgb -> rgb``: a photo of ``source`` (distorted by ``lens``) resampled into ``target``'s
    pinhole photo (bilinear); the maps are made on first use and not pickled."""

    def __init__(self, source: Camera, lens: Lens, target: Camera):
        self.source, self.lens, self.target = source, lens, target
        self._maps = None

    def maps(self) -> tuple[np.ndarray, np.ndarray]:
        """(H, W) float32 x and y: the OpenCV pixel of the distorted photo each pixel samples."""
        import cv2

        if self._maps is None:
            K, D, P = _cv_matrix(self.source), self.lens.cv_coeffs(), _cv_matrix(self.target)
            size = (self.target.width, self.target.height)
            if self.lens.fisheye:
                self._maps = cv2.fisheye.initUndistortRectifyMap(K, D, np.eye(3), P, size, cv2.CV_32FC1)
            else:
                self._maps = cv2.initUndistortRectifyMap(K, D, None, P, size, cv2.CV_32FC1)
        return self._maps

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        import cv2

        mx, my = self.maps()
        # the crop keeps every sample inside the photo; replicate covers float round-off at its edge
        return cv2.remap(np.ascontiguousarray(rgb), mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)

    def __getstate__(self):
        return {**self.__dict__, "_maps": None}
