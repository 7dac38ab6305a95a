"""COLMAP sparse models (text and binary) <-> ``Camera`` lists.

Format as in COLMAP's documentation ("Output Format") and its ``scripts/python/
read_write_model.py``: all binary values little-endian; ``qvec`` is a Hamilton quaternion
``(w, x, y, z)`` of the world -> camera rotation, ``tvec`` its translation. Besides PINHOLE and
SIMPLE_PINHOLE, the distorted models :mod:`dmrt.io.undistort` turns into pinhole photos are read
(:func:`read_model_lenses`); other models are refused.
"""

from __future__ import annotations

import struct
from dataclasses import replace
from pathlib import Path

import numpy as np

from dmrt.camera import Camera
from dmrt.errors import InputError
from dmrt.io.atomic import write_bytes
from dmrt.io.undistort import LENS_MODELS, Lens, split_params, undistorted_camera

# model id -> (name, number of params); the counts are needed to skip cameras we cannot use
_MODELS = {
    0: ("SIMPLE_PINHOLE", 3), 1: ("PINHOLE", 4), 2: ("SIMPLE_RADIAL", 4), 3: ("RADIAL", 5),
    4: ("OPENCV", 8), 5: ("OPENCV_FISHEYE", 8), 6: ("FULL_OPENCV", 12), 7: ("FOV", 5),
    8: ("SIMPLE_RADIAL_FISHEYE", 4), 9: ("RADIAL_FISHEYE", 5), 10: ("THIN_PRISM_FISHEYE", 12),
    11: ("RAD_TAN_THIN_PRISM_FISHEYE", 16),
}
_NPARAMS = {name: n for name, n in _MODELS.values()}


# -- quaternions ----------------------------------------------------------------------------------
def qvec_to_rotation(q) -> np.ndarray:
    """(4,) quaternion ``(w, x, y, z)`` -> (3, 3) float64 rotation (q is normalized first)."""
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def rotation_to_qvec(R) -> np.ndarray:
    """(3, 3) rotation -> (4,) float64 unit quaternion ``(w, x, y, z)`` with ``w >= 0``.

    Uses the symmetric-eigenproblem form (Bar-Itzhack 2000), as COLMAP's script does: it is
    stable for every rotation, including 180-degree turns where the trace formula divides by ~0.
    """
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3) or not np.allclose(R @ R.T, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise ValueError("R is not a proper 3x3 rotation matrix")
    (xx, yx, zx), (xy, yy, zy), (xz, yz, zz) = R  # COLMAP script names: Ryx = R[0, 1]
    K = np.array([
        [xx - yy - zz, 0, 0, 0],
        [yx + xy, yy - xx - zz, 0, 0],
        [zx + xz, zy + yz, zz - xx - yy, 0],
        [yz - zy, zx - xz, xy - yx, xx + yy + zz],
    ]) / 3.0
    vals, vecs = np.linalg.eigh(K)  # reads the lower triangle only
    q = vecs[[3, 0, 1, 2], np.argmax(vals)]
    return -q if q[0] < 0 else q


# -- reading --------------------------------------------------------------------------------------
class _Bin:
    """Sequential little-endian reader that reports truncation as an InputError."""

    def __init__(self, path: Path):
        self.path, self.data, self.pos = path, path.read_bytes(), 0

    def read(self, fmt: str, what: str):
        size = struct.calcsize("<" + fmt)
        if self.pos + size > len(self.data):
            raise InputError(self.path, f"file truncated at byte {len(self.data)} while reading {what}")
        out = struct.unpack_from("<" + fmt, self.data, self.pos)
        self.pos += size
        return out

    def skip(self, nbytes: int, what: str) -> None:
        if self.pos + nbytes > len(self.data):
            raise InputError(self.path, f"file truncated at byte {len(self.data)} while reading {what}")
        self.pos += nbytes

    def cstring(self, what: str) -> str:
        end = self.data.find(b"\0", self.pos)
        if end < 0:
            raise InputError(self.path, f"file truncated while reading {what}")
        s = self.data[self.pos:end].decode("utf-8", errors="replace")
        self.pos = end + 1
        return s


def _text_lines(path: Path):
    """(line number, stripped line) for the non-empty, non-comment lines of a COLMAP text file."""
    with open(path, encoding="utf-8") as f:
        for no, line in enumerate(f, start=1):
            line = line.strip()
            if line and not line.startswith("#"):
                yield no, line


def _numbers(path: Path, no: int, line: str, words, conv, what: str) -> list:
    out = []
    for word in words:
        try:
            out.append(conv(word))
        except ValueError:
            raise InputError(path, f"line {no}: non-numeric {what} {word!r} in {line!r}") from None
    return out


def _read_cameras_text(path: Path) -> dict:
    cams = {}
    for no, line in _text_lines(path):
        w = line.split()
        if len(w) < 4:
            raise InputError(path, f"line {no}: expected 'CAMERA_ID MODEL WIDTH HEIGHT PARAMS...'")
        cid, width, height = _numbers(path, no, line, [w[0], w[2], w[3]], int, "camera id/width/height")
        params = _numbers(path, no, line, w[4:], float, "camera parameter")
        cams[cid] = (w[1], width, height, params, f"line {no}")
    return cams


def _read_cameras_binary(path: Path) -> dict:
    b, cams = _Bin(path), {}
    (n,) = b.read("Q", "the camera count")
    for k in range(n):
        cid, model_id, width, height = b.read("iiQQ", f"camera record {k}")
        if model_id not in _MODELS:
            raise InputError(path, f"camera {cid} has unknown model id {model_id}")
        name, np_ = _MODELS[model_id]
        params = list(b.read(f"{np_}d", f"the parameters of camera {cid}"))
        cams[cid] = (name, width, height, params, f"record {k}")
    return cams


def _read_images_text(path: Path) -> list:
    images = []
    with open(path, encoding="utf-8") as f:
        lines = enumerate(f, start=1)
        for no, line in lines:
            line = line.strip()
            if not line or line.startswith("#"):
                continue
            w = line.split(maxsplit=9)
            if len(w) < 10:
                raise InputError(path, f"line {no}: expected 'IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME'")
            iid, cid = _numbers(path, no, line, [w[0], w[8]], int, "image/camera id")
            vals = _numbers(path, no, line, w[1:8], float, "pose value")
            images.append((iid, vals[:4], vals[4:], cid, w[9].strip(), f"line {no}"))
            # As in COLMAP's reader, the line after an image line is its POINTS2D line, even
            # when empty; the 2D observations are not needed here.
            next(lines, None)
    return images


def _read_images_binary(path: Path) -> list:
    b, images = _Bin(path), []
    (n,) = b.read("Q", "the image count")
    for k in range(n):
        iid, *vals, cid = b.read("i7di", f"image record {k}")
        name = b.cstring(f"the name of image {iid}")
        (n2d,) = b.read("Q", f"the 2D point count of image {iid}")
        b.skip(24 * n2d, f"the 2D points of image {iid}")  # each: x, y double; point3D_id int64
        images.append((iid, vals[:4], vals[4:], cid, name, f"record {k}"))
    return images


def _intrinsics(cam_path: Path, cid: int, cam) -> tuple[Camera, tuple[Camera, Lens] | None]:
    """Camera record ``cid`` -> (its pinhole camera, undistorted where the model is distorted;
    ``(the camera as the model gives it, its lens)`` or None), both with the identity pose."""
    model, width, height, params, cwhere = cam
    if model not in ("PINHOLE", "SIMPLE_PINHOLE", *LENS_MODELS):
        raise InputError(cam_path, f"camera {cid} uses model {model}, which this suite cannot undistort "
                                   f"(it undistorts {', '.join(LENS_MODELS)}): undistort the images first "
                                   f"(e.g. colmap image_undistorter) so the model is PINHOLE")
    if len(params) != _NPARAMS[model]:
        raise InputError(cam_path, f"camera {cid} ({cwhere}): model {model} takes "
                                   f"{_NPARAMS[model]} parameters, found {len(params)}")
    (fx, fy, cx, cy), lens = split_params(model, params)
    if not np.all(np.isfinite(params)) or fx <= 0 or fy <= 0 or width <= 0 or height <= 0:
        raise InputError(cam_path, f"camera {cid} ({cwhere}): non-finite or non-positive intrinsics "
                                   f"(size {width}x{height}, params {params})")
    given = Camera("", width, height, fx, fy, cx, cy)
    if lens is None:
        return given, None
    try:
        return undistorted_camera(given, lens), (given, lens)
    except ValueError as e:
        raise InputError(cam_path, f"camera {cid} ({cwhere}): {e}") from None


def _to_camera(img_path, intrinsics, img) -> tuple[Camera, tuple[Camera, Lens] | None]:
    iid, q, t, cid, name, where = img
    if intrinsics is None:
        raise InputError(img_path, f"image {iid} ({name!r}, {where}) references unknown camera id {cid}")
    q = np.asarray(q, dtype=np.float64)
    norm = np.linalg.norm(q)
    if not np.all(np.isfinite(q)) or not np.all(np.isfinite(t)) or not norm > 0:
        raise InputError(img_path, f"image {iid} ({name!r}, {where}): pose is not finite or the "
                                   f"quaternion is zero (NaN/inf): qvec={q.tolist()} tvec={list(t)}")
    pose = {"name": name, "R": qvec_to_rotation(q / norm), "t": np.asarray(t, np.float64)}
    pinhole, distorted = intrinsics
    return replace(pinhole, **pose), None if distorted is None else (replace(distorted[0], **pose), distorted[1])


def read_model_lenses(sparse_dir) -> tuple[list[Camera], list[tuple[Camera, Lens] | None]]:
    """Read a COLMAP sparse model: one pinhole ``Camera`` per registered image, ordered by image
    id, and where the model is distorted, the camera it replaces.

    Binary files (``cameras.bin`` + ``images.bin``) are used when both exist, else the text ones.
    ``points3D`` is not read.

    Returns
    -------
    cameras : list of Camera
        Pinhole cameras: a distorted camera is replaced by the pinhole camera of its undistorted
        photo (:func:`dmrt.io.undistort.undistorted_camera`).
    distorted : list of (Camera, Lens) or None
        Per image, the camera as the model gives it and its lens; None for a pinhole (zero
        coefficients included).

    Raises
    ------
    InputError
        Naming the offending file: a missing model, truncated or malformed files, camera models
        that cannot be undistorted (or coefficients that fold the image), unknown camera ids,
        non-finite poses, duplicate image names, models without images.
    """
    d = Path(sparse_dir)
    if (d / "cameras.bin").is_file() and (d / "images.bin").is_file():
        cam_path, img_path = d / "cameras.bin", d / "images.bin"
        cams, images = _read_cameras_binary(cam_path), _read_images_binary(img_path)
    elif (d / "cameras.txt").is_file() and (d / "images.txt").is_file():
        cam_path, img_path = d / "cameras.txt", d / "images.txt"
        cams, images = _read_cameras_text(cam_path), _read_images_text(img_path)
    else:
        raise InputError(d, "no COLMAP model: expected cameras.bin + images.bin or "
                            "cameras.txt + images.txt")
    if not images:
        raise InputError(img_path, "the model has no images")
    seen = {}
    for img in images:
        if img[4] in seen:
            raise InputError(img_path, f"duplicate image name {img[4]!r} (images {seen[img[4]]} and {img[0]})")
        seen[img[4]] = img[0]
    images.sort(key=lambda img: img[0])
    used = {img[3] for img in images}
    intrinsics = {cid: _intrinsics(cam_path, cid, cam) for cid, cam in cams.items() if cid in used}
    pairs = [_to_camera(img_path, intrinsics.get(img[3]), img) for img in images]
    return [c for c, _ in pairs], [d for _, d in pairs]


def read_model(sparse_dir) -> list[Camera]:
    """:func:`read_model_lenses` for a model of pinhole cameras only (zero distortion included);
    a camera with lens distortion is an ``InputError`` (:func:`dmrt.io.scene.load_scene`
    undistorts such photos)."""
    cameras, distorted = read_model_lenses(sparse_dir)
    for c, d in zip(cameras, distorted):
        if d is not None:
            raise InputError(sparse_dir, f"image {c.name!r} has a {d[1].model} camera with lens distortion; "
                                         f"dmrt.io.scene.load_scene undistorts it")
    return cameras


# -- writing --------------------------------------------------------------------------------------



def write_model(sparse_dir, cameras: list[Camera], binary: bool = False,
                points3d: np.ndarray | None = None, point_colors=None) -> None:
    """Write ``cameras`` as a COLMAP sparse model in ``sparse_dir`` (created if needed).

    Each camera becomes its own PINHOLE camera; image and camera ids are ``1..n`` in list order.
    Text floats are written with ``repr`` so that they read back bit-exactly.

    Parameters
    ----------
    points3d : (m, 3) float64, optional
        Written to ``points3D`` with empty tracks and error 0; the file is empty if omitted.
    point_colors : (m, 3) uint8, optional
        Their colours (grey if omitted).

    The other format's files, if present, are removed: ``read_model`` prefers binary, so a stale
    ``.bin`` model would otherwise shadow a freshly written text one.
    """
    d = Path(sparse_dir)
    d.mkdir(parents=True, exist_ok=True)
    names = [c.name for c in cameras]
    if len(set(names)) != len(names):
        raise ValueError("camera names must be unique")
    pts = np.zeros((0, 3)) if points3d is None else np.asarray(points3d, np.float64).reshape(-1, 3)
    cols = (np.full((len(pts), 3), 128, np.uint8) if point_colors is None
            else np.asarray(point_colors, np.uint8).reshape(-1, 3))
    if len(cols) != len(pts):
        raise ValueError("point_colors must have one row per point")
    poses = [(rotation_to_qvec(c.R), c.t) for c in cameras]
    ext, other = (".bin", ".txt") if binary else (".txt", ".bin")

    if binary:
        cam = [struct.pack("<Q", len(cameras))]
        img = [struct.pack("<Q", len(cameras))]
        for i, (c, (q, t)) in enumerate(zip(cameras, poses), start=1):
            cam.append(struct.pack("<iiQQ4d", i, 1, c.width, c.height, c.fx, c.fy, c.cx, c.cy))
            img.append(struct.pack("<i7di", i, *q, *t, i) + c.name.encode("utf-8") + b"\0"
                       + struct.pack("<Q", 0))
        p3d = [struct.pack("<Q", len(pts))]
        for k, (x, rgb) in enumerate(zip(pts, cols), start=1):
            p3d.append(struct.pack("<Q3d3BdQ", k, *x, *rgb, 0.0, 0))
        files = {"cameras": b"".join(cam), "images": b"".join(img), "points3D": b"".join(p3d)}
    else:
        r = lambda v: repr(float(v))  # noqa: E731  shortest string that round-trips exactly
        cam = ["# Camera list with one line of data per camera:",
               "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
               f"# Number of cameras: {len(cameras)}"]
        img = ["# Image list with two lines of data per image:",
               "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
               "#   POINTS2D[] as (X, Y, POINT3D_ID)",
               f"# Number of images: {len(cameras)}, mean observations per image: 0"]
        for i, (c, (q, t)) in enumerate(zip(cameras, poses), start=1):
            cam.append(f"{i} PINHOLE {c.width} {c.height} {r(c.fx)} {r(c.fy)} {r(c.cx)} {r(c.cy)}")
            img.append(f"{i} {' '.join(map(r, q))} {' '.join(map(r, t))} {i} {c.name}")
            img.append("")  # no 2D observations
        p3d = ["# 3D point list with one line of data per point:",
               "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
               f"# Number of points: {len(pts)}, mean track length: 0"]
        p3d += [f"{k} {r(x[0])} {r(x[1])} {r(x[2])} {rgb[0]} {rgb[1]} {rgb[2]} 0"
                for k, (x, rgb) in enumerate(zip(pts, cols), start=1)]
        files = {n: ("\n".join(lines) + "\n").encode("utf-8")
                 for n, lines in (("cameras", cam), ("images", img), ("points3D", p3d))}

    for name, data in files.items():
        write_bytes(d / (name + ext), data)
        (d / (name + other)).unlink(missing_ok=True)
