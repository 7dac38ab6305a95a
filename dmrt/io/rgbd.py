"""RGB-D frames -> a scene (DESIGN.md, "Scene input"): the depth frames back-projected into one
voxel-filtered ``points.ply``, beside the frames' COLMAP model, colour photos and mesh.

Input layout (as ``../shared/real/kitchen-7scenes`` and other RGB-D sequences converted to COLMAP)::

    FRAMES/sparse/           COLMAP model of the colour frames, PINHOLE (or sparse/0/)
    FRAMES/images/<name>     the colour frames the model names
    FRAMES/depth/<stem>.png  each frame's depth, 16-bit PNG (millimetres by default; 0 = no reading)
    FRAMES/mesh.ply          optional, kept as the scene's reference mesh

A depth frame is read with its colour frame's camera (scaled to the depth frame's size if the two
differ): the depth camera is taken to be the colour camera, as the model gives one pose per frame.
Where a data set's colour camera is not calibrated against its depth camera (7-Scenes), colours
land a few pixels off the geometry; the cloud keeps that, as the photos do.
"""

from __future__ import annotations

import os
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from dmrt.camera import Camera
from dmrt.errors import InputError
from dmrt.options import option, validate

# 7-Scenes marks a pixel without a reading 65535, others 0: both are dropped
_NO_READING = (0, 65535)
# A pixel whose 3x3 neighbourhood spans more than this share of its depth straddles an occlusion
# boundary: a depth sensor's "flying pixel" there lies between the two surfaces, on neither.
# A surface seen 80 degrees off its normal changes depth by ~1% of z a pixel at 585 px focal
# length, so real surfaces stay well below.
_FLYING_JUMP = 0.05
# voxel indices packed into one int64 key: 21 bits an axis, about +-4 km at the default 4 mm
_KEY_BITS = 21


@dataclass
class RGBDConfig:
    """How ``dmrt scene rgbd`` turns depth frames into a point cloud."""

    every: int = option(1, "back-project every n-th depth frame (all colour frames stay photos)", minimum=1)
    voxel: float = option(0.004, "voxel filter edge, metres: one point (the mean of the readings) per voxel",
                          minimum=1e-5)
    depth_scale: float = option(1000.0, "depth units per metre (1000: millimetres, as 7-Scenes; TUM RGB-D: 5000)",
                                minimum=1e-9)

    def __post_init__(self):
        validate(self)


def read_depth(path: Path, scale: float = 1000.0) -> np.ndarray:
    """A 16-bit depth PNG as (h, w) float64 metres, 0 where there is no reading."""
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise InputError(path, "depth frame is missing")
    try:
        with Image.open(path) as im:
            raw = np.asarray(im)
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise InputError(path, f"unreadable depth frame: {e}") from None
    if raw.ndim != 2 or raw.dtype.kind not in "ui" or raw.dtype.itemsize < 2:
        raise InputError(path, f"a depth frame must be a single-channel 16-bit PNG, not {raw.dtype} of shape "
                               f"{raw.shape}")
    depth = raw.astype(np.float64) / scale
    depth[np.isin(raw, _NO_READING)] = 0.0
    return depth


def back_project(camera: Camera, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The depth frame's readings as world points, flying pixels dropped (:data:`_FLYING_JUMP`).

    Parameters
    ----------
    camera : Camera, the frame's pose and intrinsics (any resolution: scaled to the frame's).
    depth : (h, w) float64 camera z, metres, 0 = no reading.

    Returns
    -------
    points : (m, 3) float64 world metres.  pixels : (m,) int64 flat pixel indices into ``depth``.
    """
    from scipy import ndimage

    h, w = depth.shape
    cam = camera.scaled(w, h)
    valid = depth > 0
    hi = ndimage.maximum_filter(depth, size=3)
    lo = ndimage.minimum_filter(np.where(valid, depth, np.inf), size=3)
    keep = valid & (hi - lo <= _FLYING_JUMP * depth)
    pixels = np.flatnonzero(keep)
    i, j = np.divmod(pixels, w)
    z = depth.ravel()[pixels]
    p_cam = np.stack([(j + 0.5 - cam.cx) / cam.fx * z, (i + 0.5 - cam.cy) / cam.fy * z, z], axis=1)
    return (p_cam - cam.t) @ cam.R, pixels


class VoxelFilter:
    """One point per voxel of edge ``voxel`` metres: the mean position and colour of the points
    added in it, accumulated frame by frame (memory: the occupied voxels, not the readings).

    ``origin`` (3,) float64 world metres anchors the grid (keys are indices relative to it).
    """

    def __init__(self, voxel: float, origin):
        self.voxel, self.origin = float(voxel), np.asarray(origin, np.float64)
        self.keys = np.zeros(0, np.int64)
        self.sums = np.zeros((0, 6), np.float64)  # x, y, z, r, g, b summed per voxel
        self.counts = np.zeros(0, np.int64)

    def add(self, points: np.ndarray, colors: np.ndarray) -> None:
        """Add ``points`` (n, 3) float64 world metres with ``colors`` (n, 3) uint8."""
        idx = np.floor((points - self.origin) / self.voxel).astype(np.int64)
        half = 1 << (_KEY_BITS - 1)
        if len(idx) and (idx.min() < -half or idx.max() >= half):
            raise ValueError(f"points more than {half * self.voxel:.0f} m from the first frame: use a larger --voxel")
        idx += half
        keys = (idx[:, 0] << (2 * _KEY_BITS)) | (idx[:, 1] << _KEY_BITS) | idx[:, 2]
        values = np.concatenate([points, colors.astype(np.float64)], axis=1)
        merged, inverse = np.unique(np.concatenate([self.keys, keys]), return_inverse=True)
        old, new = inverse[:len(self.keys)], inverse[len(self.keys):]
        sums, counts = np.zeros((len(merged), 6)), np.zeros(len(merged), np.int64)
        sums[old], counts[old] = self.sums, self.counts  # the old keys are distinct
        for c in range(6):
            sums[:, c] += np.bincount(new, weights=values[:, c], minlength=len(merged))
        counts += np.bincount(new, minlength=len(merged))
        self.keys, self.sums, self.counts = merged, sums, counts

    def points(self) -> tuple[np.ndarray, np.ndarray]:
        """(m, 3) float64 mean positions and (m, 3) uint8 mean colours, one per occupied voxel."""
        mean = self.sums / np.maximum(self.counts, 1)[:, None]
        return mean[:, :3], np.clip(np.rint(mean[:, 3:]), 0, 255).astype(np.uint8)


def _model_dir(root: Path) -> Path:
    """``root/sparse``, or ``root/sparse/0`` where COLMAP's mapper put the model."""
    sparse = root / "sparse"
    if not sparse.is_dir():
        raise InputError(sparse, "COLMAP model directory 'sparse/' is missing")
    return sparse / "0" if (sparse / "0").is_dir() and not any(sparse.glob("images.*")) else sparse


def _copy_files(src: Path, dst: Path, copy) -> None:
    """Every file under ``src`` to the same place under ``dst`` by ``copy(src, dst)``; folders are
    made anew (writable, whatever the source's permissions: a read-only data set stays replaceable)."""
    for f in sorted(src.rglob("*")):
        if f.is_file():
            (dst / f.relative_to(src)).parent.mkdir(parents=True, exist_ok=True)
            copy(f, dst / f.relative_to(src))


def _link_or_copy(src, dst) -> None:
    """A hard link (no second copy of the photos) where the file system allows, else a copy."""
    try:
        os.link(src, dst)
    except OSError:
        shutil.copy2(src, dst)


def rgbd_scene(frames_dir, out, config: RGBDConfig | None = None, force: bool = False,
               progress: bool = False) -> dict:
    """Write the scene ``out`` from the RGB-D frames in ``frames_dir`` (module docstring).

    ``out/points.ply`` holds every ``config.every``-th depth frame back-projected (flying pixels
    dropped), one point per ``config.voxel`` voxel with the mean colour of the colour frames at
    those pixels; ``sparse/`` is copied, ``images/`` and ``mesh.ply`` hard-linked (or copied).
    The folder appears only when complete (:func:`dmrt.io.atomic.atomic_dir`).

    Returns
    -------
    dict : ``frames`` (depth frames used), ``readings`` (points back-projected), ``points``
    (points written), ``photos`` (colour frames in the model).
    """
    from PIL import Image
    from tqdm import tqdm

    from dmrt.io import colmap
    from dmrt.io.atomic import atomic_dir
    from dmrt.io.pointcloud import PointCloud, write_points

    config = config or RGBDConfig()
    root = Path(frames_dir)
    if Path(out).exists() and not force:  # refused before minutes of back-projection
        raise InputError(out, "scene already exists (use --force to replace it)")
    if not root.is_dir():
        raise InputError(root, "RGB-D frames directory does not exist")
    for sub in ("depth", "images"):
        if not (root / sub).is_dir():
            raise InputError(root / sub, f"folder '{sub}/' is missing (expected {sub}/ and sparse/ beside it)")
    model = _model_dir(root)
    cameras = colmap.read_model(model)
    used = cameras[:: config.every]
    grid = VoxelFilter(config.voxel, used[0].center)
    readings = 0
    # on a terminal only, and erased when it ends: an error stays the one line on stderr
    for cam in tqdm(used, desc="depth frames", unit="frame", leave=False, disable=None if progress else True):
        depth = read_depth(root / "depth" / (Path(cam.name).stem + ".png"), config.depth_scale)
        points, pixels = back_project(cam, depth)
        colour_path = root / "images" / cam.name
        try:
            with Image.open(colour_path) as im:  # the colour frame at the depth frame's size
                rgb = np.asarray(im.convert("RGB").resize(depth.shape[::-1], Image.BILINEAR))
        except (OSError, ValueError) as e:
            raise InputError(colour_path, f"cannot read colour frame: {e}") from None
        try:
            grid.add(points, rgb.reshape(-1, 3)[pixels])
        except ValueError as e:
            raise InputError(root / "depth" / (Path(cam.name).stem + ".png"), str(e)) from None
        readings += len(points)
    positions, colours = grid.points()
    if len(positions) == 0:
        raise InputError(root / "depth", "no depth reading in the frames used: every pixel is 0 (no reading)")
    with atomic_dir(out, force=force, what="scene") as tmp:
        write_points(tmp / "points.ply", PointCloud(positions, colors=colours))
        _copy_files(model, tmp / "sparse", shutil.copyfile)
        _copy_files(root / "images", tmp / "images", _link_or_copy)
        if (root / "mesh.ply").is_file():
            _link_or_copy(root / "mesh.ply", tmp / "mesh.ply")
    return {"frames": len(used), "readings": readings, "points": len(positions), "photos": len(cameras)}
