"""A user's scene directory (DESIGN.md, "Scene input"), loaded and validated in one place.

Layout::

    SCENE/points.ply | .las | .laz | .e57        point cloud (first found, in that order)
    SCENE/sparse/  (or sparse/0/)                 COLMAP model: PINHOLE, SIMPLE_PINHOLE, or a
                                                  distorted model dmrt.io.undistort handles
    SCENE/images/<name>                           one photo per registered image
    SCENE/mesh.ply                                optional reference mesh (Embree ground truth)
    SCENE/scans.json                              optional scan structure of the cloud: stations and
                                                  their angular grids (dmrt.io.stations)

Without ``sparse/``, a ``points.e57`` is a whole scene: its posed ``images2D`` entries are the
photos (pinhole images as they are, spherical and cylindrical panoramas cut into pinhole views by
:mod:`dmrt.io.panorama`); entries it cannot use are reported (:attr:`Scene.warnings`, one line
each on stderr) and skipped.

Every photo is a pinhole photo from here on: :meth:`Scene.read_image` undistorts it or cuts it
from its panorama, and ``cameras`` are the pinhole cameras of the photos it returns.

``load_scene`` checks everything a later stage would trip over (and streams the cloud once to
find its bounds), so bad input fails here with an ``InputError`` naming the file. A caller whose
own first pass reads every point anyway (preprocessing's scan-grid pass) may skip that stream for a
binary PLY (``bounds=False``) and give the bounds it finds (:meth:`Scene.with_bounds`): its
points are then validated by that pass, every reader validating as it goes.
"""

from __future__ import annotations

import os
import re
import sys
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Callable, Iterator

import numpy as np

from dmrt.io import colmap, e57, pointcloud, stations
from dmrt.camera import Camera
from dmrt.errors import InputError
from dmrt.io.panorama import Panorama, PanoramaView, cube_views, mask_cells, valid_box
from dmrt.io.pointcloud import PointCloud
from dmrt.io.undistort import Undistortion

_POINT_FILES = ("points.ply", "points.las", "points.laz", "points.e57")
_MODEL_FILES = ("cameras.bin", "cameras.txt", "images.bin", "images.txt")
# a spherical image whose pixel sizes give a narrower field than this (radians) states them in
# other units (some writers store 5e-6 for a full 8192 x 4096 panorama)
_MIN_PANORAMA_ANGLE = 0.1


def _decode_file(path: Path) -> np.ndarray:
    """The image file ``path`` as (height, width, 3) uint8 RGB (greyscale and alpha converted)."""
    from PIL import Image

    try:
        with Image.open(path) as im:
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except (OSError, ValueError) as e:
        raise InputError(path, f"cannot decode image: {e}") from None


class _Crop:
    """``rgb -> rgb[row0:row1, col0:col1]`` (picklable)."""

    def __init__(self, box: tuple[int, int, int, int]):
        self.box = box

    def __call__(self, rgb: np.ndarray) -> np.ndarray:
        r0, c0, r1, c1 = self.box
        return rgb[r0:r1, c0:c1]


@dataclass
class PhotoSource:
    """How a photo's pinhole pixels are made when they are not its image file as it is.

    Attributes
    ----------
    path : Path
        The file holding the source pixels (an image file, or the ``.e57``); errors name it.
    warp : callable or None
        (h, w, 3) uint8 source pixels -> (H, W, 3) uint8 pinhole photo: an
        :class:`~dmrt.io.undistort.Undistortion`, a :class:`~dmrt.io.panorama.PanoramaView`, a
        crop; None: the source pixels are the photo.
    about : dict
        What ``bundle.json`` records of it (``photo_sources``).
    e57_image : E57Image or None
        The ``images2D`` entry whose blob holds the source pixels; None: the file ``path``.
    """

    path: Path
    warp: Callable[[np.ndarray], np.ndarray] | None
    about: dict
    e57_image: e57.E57Image | None = None

    def read(self) -> np.ndarray:
        """The photo: (H, W, 3) uint8 RGB."""
        src = _decode_file(self.path) if self.e57_image is None else e57.read_image_pixels(self.path, self.e57_image)
        return np.array(src if self.warp is None else self.warp(src))  # a copy: decoded blobs are cached


@dataclass
class Scene:
    """A validated scene.

    Attributes
    ----------
    root : Path
        The scene directory.
    points_path : Path
        The point cloud file.
    cameras : list of Camera
        One pinhole camera per photo, in COLMAP image-id order (or E57 image order, a
        panorama's views in :data:`dmrt.io.panorama.FACES` order); undistorted where the model
        is distorted.
    image_paths : list of Path
        The file holding each photo's source pixels, parallel to ``cameras``: ``root / "images"
        / name`` for a COLMAP scene, the ``.e57`` for its images.
    mesh_path : Path or None
        The reference mesh, if the scene has one.
    origin : (3,) float64 or None
        Scene origin, metres: the point bounding-box centre rounded to whole metres. GPU code
        works in ``x - origin`` so float32 keeps millimetres on UTM-sized coordinates; rounding
        keeps the offset a short, exactly representable number in reports and bundles. None
        (and ``bounds`` None) from ``load_scene(..., bounds=False)`` until :meth:`with_bounds`.
    n_points : int
        Number of points in the cloud (for E57: valid points, records flagged invalid left out).
    bounds : ((3,), (3,)) float64
        The points' bounding box, world metres (lowest and highest corner).
    scanner_positions : (n_scans, 3) float64 or None
        World positions of the scanners, metres, indexed by ``PointCloud.scan_index``; what
        normals should face. Given for E57 (one per scan) and with ``scans.json``, else None.
    photos : list of (PhotoSource or None), or None
        How each photo's pixels are made where they are not its file as it is (None: all are).
    warnings : list of str
        One line per thing in the input that was skipped (an E57 image without a pose, ...).
    scan_structure : ScanStructure or None
        Each point's station and grid cell (:mod:`dmrt.io.stations`): from ``scans.json``, or
        from structured E57 scans; None where the cloud carries none.
    """

    root: Path
    points_path: Path
    cameras: list[Camera]
    image_paths: list[Path]
    mesh_path: Path | None
    origin: np.ndarray
    n_points: int
    scanner_positions: np.ndarray | None = None
    bounds: tuple[np.ndarray, np.ndarray] | None = None
    photos: list[PhotoSource | None] | None = None
    warnings: list[str] = field(default_factory=list)
    scan_structure: stations.ScanStructure | None = None

    def with_bounds(self, lo: np.ndarray, hi: np.ndarray) -> "Scene":
        """This scene with the points' bounding box ``lo``, ``hi`` ((3,) float64 metres each) and
        the origin it gives."""
        lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
        return replace(self, bounds=(lo, hi), origin=np.round((lo + hi) / 2.0))

    def iter_points(self, chunk_size: int = 1_000_000) -> Iterator[PointCloud]:
        """Stream the cloud (world coordinates, float64) in chunks of at most ``chunk_size``."""
        return pointcloud.iter_point_chunks(self.points_path, chunk_size)

    def point_range(self, chunk_size: int = 1_000_000) -> pointcloud.PointRange:
        """The cloud as a picklable chunk source that splits into ranges for worker processes."""
        return pointcloud.point_range(self.points_path, chunk_size)

    def read_points(self) -> PointCloud:
        """The whole cloud in memory (world coordinates, float64)."""
        return pointcloud.read_points(self.points_path)

    def read_image(self, i: int) -> np.ndarray:
        """Photo ``i`` as (height, width, 3) uint8 RGB (greyscale and alpha images converted):
        the pinhole photo of ``cameras[i]``, undistorted or cut from a panorama where needed."""
        source = self.photo_source(i)
        return _decode_file(self.image_paths[i]) if source is None else source.read()

    def photo_source(self, i: int) -> PhotoSource | None:
        """How photo ``i`` is made; None when it is its image file as it is."""
        return None if self.photos is None else self.photos[i]

    def camera_index(self, name: str) -> int:
        """Index of the camera whose image is ``name``."""
        for i, c in enumerate(self.cameras):
            if c.name == name:
                return i
        some = ", ".join(repr(c.name) for c in self.cameras[:5])
        more = ", ..." if len(self.cameras) > 5 else ""
        raise InputError(self.root / "sparse", f"no image named {name!r}; valid names: {some}{more}")


def _model_dir(root: Path) -> Path:
    sparse = root / "sparse"
    if not sparse.is_dir():
        raise InputError(sparse, "COLMAP model directory 'sparse/' is missing")
    # COLMAP's mapper writes sparse/0, sparse/1, ...; accept the common single-model layout.
    if not any((sparse / f).is_file() for f in _MODEL_FILES) and (sparse / "0").is_dir():
        return sparse / "0"
    return sparse


def _check_image(path: Path, cam: Camera) -> None:
    from PIL import Image, UnidentifiedImageError

    if not path.is_file():
        raise InputError(path, f"image file for camera {cam.name!r} is missing")
    try:
        with Image.open(path) as im:  # reads the header only
            size = im.size
    except (UnidentifiedImageError, OSError, ValueError) as e:
        raise InputError(path, f"unreadable or corrupt image: {e}") from None
    if size != (cam.width, cam.height):
        raise InputError(path, f"image is {size[0]}x{size[1]} pixels but its camera says "
                               f"{cam.width}x{cam.height}")


def _check_mesh(path: Path) -> None:
    import trimesh

    try:
        mesh = trimesh.load(path, force="mesh")
    except Exception as e:  # trimesh raises many types for bad files; all mean "unreadable"
        raise InputError(path, f"unreadable reference mesh: {e}") from None
    if len(getattr(mesh, "vertices", ())) == 0 or len(getattr(mesh, "faces", ())) == 0:
        raise InputError(path, "reference mesh is empty (no triangles)")


def _colmap_photos(root: Path, check_images: bool) -> tuple[list[Camera], list[Path], list[PhotoSource | None] | None]:
    """The COLMAP model's pinhole cameras, their image files, and their sources (None where the
    file is the photo; None for all when no camera is distorted)."""
    model = _model_dir(root)
    cameras, distorted = colmap.read_model_lenses(model)
    for c in cameras:
        if not (np.isfinite(c.R).all() and np.isfinite(c.t).all()
                and np.isfinite([c.fx, c.fy, c.cx, c.cy]).all()):
            raise InputError(model, f"camera {c.name!r} has non-finite (NaN/inf) pose or intrinsics")
    images_dir = root / "images"
    image_paths = [images_dir / c.name for c in cameras]
    if check_images:
        if not images_dir.is_dir():
            raise InputError(images_dir, "image directory 'images/' is missing")
        for p, c in zip(image_paths, cameras):
            _check_image(p, c)  # undistortion keeps the size
    if not any(distorted):
        return cameras, image_paths, None
    photos = []
    for path, cam, d in zip(image_paths, cameras, distorted):
        if d is None:
            photos.append(None)
            continue
        given, lens = d
        about = {"source": f"images/{cam.name}", "undistorted_from": {
            "model": lens.model, "fx": given.fx, "fy": given.fy, "cx": given.cx, "cy": given.cy,
            "coefficients": list(lens.coeffs)}}
        photos.append(PhotoSource(path, Undistortion(given, lens, cam), about))
    return cameras, image_paths, photos


def _safe(name: str) -> str:
    return re.sub(r"[^A-Za-z0-9_-]+", "_", name).strip("_")[:40]


def _panorama(image: e57.E57Image) -> tuple[Panorama | None, str | None, str | None]:
    """A spherical or cylindrical ``image``'s projection, or why it is unusable, and a note
    (a warning) on how it was read."""
    n, W, H = image.numbers, image.width, image.height
    if image.representation == "cylindrical":
        return Panorama("cylindrical", W, H, n["pixelWidth"], n["pixelHeight"], n["radius"],
                        n["principalPointY"]), None, None
    pw, ph = n["pixelWidth"], n["pixelHeight"]
    covers = f"its spherical pixels ({pw:g} x {ph:g}) cover {W * pw:.3g} x {H * ph:.3g} rad"
    if W * pw > 2 * np.pi * 1.01 or H * ph > np.pi * 1.01:
        return None, f"{covers}, more than 360 x 180 degrees", None
    if min(W * pw, H * ph) >= _MIN_PANORAMA_ANGLE:
        return Panorama("spherical", W, H, pw, ph), None, None
    if W != 2 * H:
        return None, f"{covers}, not radians: the panorama's field of view is unknown", None
    return (Panorama("spherical", W, H, 2 * np.pi / W, np.pi / H), None,
            f"{covers}, not radians; taken as a full 360 x 180 degree panorama, as its 2:1 size suggests")


def _e57_views(path: Path, image: e57.E57Image, pano: Panorama | None) -> list[tuple[Camera, PhotoSource]]:
    """The pinhole photos of one usable E57 image (world cameras and their sources): a pinhole
    image itself (cropped to its mask's largest valid rectangle), a panorama's cube faces."""
    stem = f"image{image.index:03d}" + (f"-{_safe(image.name)}" if _safe(image.name) else "")
    ext = ".jpg" if image.blob == "jpegImage" else ".png"
    mask = e57.read_image_mask(path, image)
    about = {"source": path.name, "images2D": image.index, "name": image.name,
             "representation": image.representation}
    if pano is None:  # pinhole: E57's camera looks along -z with y up (ASTM E2807 8.4.13)
        n = image.numbers
        local = Camera(stem + ext, image.width, image.height, n["focalLength"] / n["pixelWidth"],
                       n["focalLength"] / n["pixelHeight"], n["principalPointX"], n["principalPointY"],
                       np.diag([1.0, -1.0, -1.0]))
        box = None if mask is None or mask.all() else valid_box(mask_cells(mask), *mask.shape)
        if box is not None:
            r0, c0, r1, c1 = box
            local = replace(local, width=c1 - c0, height=r1 - r0, cx=local.cx - c0, cy=local.cy - r0)
        views = [(local, None if box is None else _Crop(box), about)]
    else:
        views = [(replace(view, name=view.name + ext), PanoramaView(pano, view), {**about, "face": face})
                 for face, view in cube_views(pano, stem, mask)]
    out = []
    for local, warp, a in views:
        R = local.R @ image.rotation.T  # the image's frame -> the world, then -> the camera
        out.append((replace(local, R=R, t=-R @ image.translation), PhotoSource(path, warp, a, image)))
    return out


def _e57_photos(path: Path, check_images: bool) -> tuple[list[Camera], list[PhotoSource], list[str]]:
    """The photos of an E57 file's ``images2D`` (module docstring): pinhole cameras in world
    coordinates, their sources, and one warning line per image skipped or reinterpreted."""
    photos, warnings = [], []
    for image in e57.read_images(path, check_blobs=check_images):
        label = f"{path}: image {image.index} ({image.name!r})"
        pano, problem, note = None, image.problem, None
        if problem is None and image.representation != "pinhole":
            pano, problem, note = _panorama(image)
        if problem is not None:
            warnings.append(f"{label}: {problem}; skipped")
            continue
        if note:
            warnings.append(f"{label}: {note}")
        views = _e57_views(path, image, pano)
        if not views:
            warnings.append(f"{label}: no cube face of it is covered enough to be a photo; skipped")
        photos += views
    return [c for c, _ in photos], [s for _, s in photos], warnings


def cloud_extent(points_path, chunk_size: int = 1_000_000) -> tuple[np.ndarray, np.ndarray, int]:
    """``(lo, hi, n)``: the bounding box ((3,) float64 metres each) and number of the points of
    the cloud file, every point read and validated. chunk_size bounds the memory each reader
    takes; a seekable file is read in ranges on threads (reads and numpy release the GIL)."""
    parts = pointcloud.point_range(points_path, chunk_size).split(len(os.sched_getaffinity(0)))
    with ThreadPoolExecutor(len(parts)) as pool:
        ranges = list(pool.map(lambda part: pointcloud.chunk_bounds(part()), parts))
    return (np.min([r[0] for r in ranges], axis=0), np.max([r[1] for r in ranges], axis=0),
            sum(r[2] for r in ranges))


def load_scene(root, check_images: bool = True, chunk_size: int = 1_000_000, bounds: bool = True) -> Scene:
    """Load and validate a scene directory.

    Parameters
    ----------
    root : path-like
        The scene directory.
    check_images : bool
        Check that every camera's image exists, decodes its header, and matches the camera's size
        (for an E57 scene: that each image's blob header decodes). Off, neither the images nor
        ``images/`` need exist (geometry-only use).
    bounds : bool
        Stream the cloud to find its bounds and validate every point. False, for a binary PLY:
        only its header and size are checked, and ``origin`` and ``bounds`` are None until the
        caller, whose own pass reads every point, gives them (:meth:`Scene.with_bounds`); other
        formats are streamed as with True (their count takes a pass).

    Raises
    ------
    InputError
        Naming the offending file: missing directory / point cloud / model / images, malformed or
        empty or non-finite cloud, bad COLMAP model (a camera model it cannot undistort among
        them), missing / corrupt / wrongly sized image, non-finite camera, unreadable or empty
        mesh, an E57 scene without a usable image.
    """
    root = Path(root)
    if not root.is_dir():
        raise InputError(root, "scene directory does not exist")
    points_path = next((root / f for f in _POINT_FILES if (root / f).is_file()), None)
    if points_path is None:
        raise InputError(root, f"no point cloud: expected one of {', '.join(_POINT_FILES)}")

    photos, warnings = None, []
    if points_path.suffix.lower() == ".e57" and not (root / "sparse").exists():
        cameras, photos, warnings = _e57_photos(points_path, check_images)
        for line in warnings:
            print(f"dmrt: warning: {line}", file=sys.stderr)
        if not cameras:
            raise InputError(root / "sparse", f"COLMAP model directory 'sparse/' is missing, and "
                                              f"{points_path.name} holds no image usable as a photo"
                                              f"{' (see the warnings above)' if warnings else ''}")
        image_paths = [points_path] * len(cameras)
    else:
        cameras, image_paths, photos = _colmap_photos(root, check_images)

    mesh_path = root / "mesh.ply"
    if mesh_path.exists():
        _check_mesh(mesh_path)
    else:
        mesh_path = None

    if pointcloud.count_points(points_path) == 0:
        raise InputError(points_path, "empty point cloud (0 points)")
    n_points = None if bounds else pointcloud.exact_count(points_path)
    extent = None
    if n_points is None:
        # also validates every point (finite, not truncated). Counted here, not taken from the
        # header: E57 readers drop records flagged invalid.
        *extent, n_points = cloud_extent(points_path, chunk_size)
    scanners = structure = None
    if points_path.suffix.lower() == ".e57":
        scanners = e57.scanner_positions(points_path)
        structure = stations.e57_structure(e57.read_scans(points_path))
    elif (root / "scans.json").is_file():
        structure = stations.read_scans_json(root / "scans.json", n_points)
        scanners = structure.positions
    scene = Scene(root, points_path, cameras, image_paths, mesh_path, None, n_points, scanners, None,
                  photos, warnings, structure)
    return scene if extent is None else scene.with_bounds(*extent)

