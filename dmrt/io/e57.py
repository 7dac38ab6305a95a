"""E57 point clouds (ASTM E2807, the laser-scanning exchange format) through pye57 / libE57Format.

Every ``data3D`` scan of the file is read, in Cartesian or spherical coordinates, and moved into
world coordinates with its pose. Scans are streamed through fixed-size buffers of libE57Format's
``CompressedVectorReader``, so a scan larger than memory costs one chunk of memory at a time.
Points whose ``cartesianInvalidState`` / ``sphericalInvalidState`` is not 0 are dropped: state 1
keeps only a direction (no range), state 2 nothing, so neither is a surface point.

The ``images2D`` entries (the scanner's photographs and panoramas) are read as headers
(:func:`read_images`) and decoded on demand (:func:`read_image_pixels`); :mod:`dmrt.io.scene`
makes them photos.

Every failure is an ``InputError`` naming the file with a one-line message; libE57Format's own
messages carry multi-line debug dumps, of which only the first line is kept.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Literal

import numpy as np

from dmrt.errors import InputError
from dmrt.io.pointcloud import PointCloud, _validated

_SIGNATURE = b"ASTM-E57"
_HEADER_BYTES = 48
_CARTESIAN = ("cartesianX", "cartesianY", "cartesianZ")
_SPHERICAL = ("sphericalRange", "sphericalAzimuth", "sphericalElevation")
_COLORS = ("colorRed", "colorGreen", "colorBlue")
_GRID = ("rowIndex", "columnIndex")


@dataclass
class E57Scan:
    """What one ``data3D`` scan's header says (no point is read).

    Attributes
    ----------
    index : int
        Position in the file's ``data3D`` vector.
    name : str
        The scan's ``name`` ("" if it has none).
    n_records : int
        Records in the scan's ``points``, invalid ones included.
    coordinates : {"cartesian", "spherical"}
        Which coordinate fields are read (Cartesian when the scan has both).
    rotation : (3, 3) float64
        Scan-to-world rotation from the pose quaternion (normalised); identity without a pose.
    translation : (3,) float64
        Scan-to-world translation, metres; the scanner position in world coordinates.
    fields : tuple of str
        Every field of the scan's point prototype.
    color_limits : (3, 2) float64 or None
        Per channel (red, green, blue) the value range that maps to 0..255.
    grid_size : (rows, columns) or None
        The scan's ``indexBounds`` maxima (``rowMaximum``, ``columnMaximum``), when given.
    """

    index: int
    name: str
    n_records: int
    coordinates: Literal["cartesian", "spherical"]
    rotation: np.ndarray
    translation: np.ndarray
    fields: tuple[str, ...]
    color_limits: np.ndarray | None
    grid_size: tuple[int, int] | None = None

    @property
    def has_colors(self) -> bool:
        return self.color_limits is not None

    @property
    def structured(self) -> bool:
        """Its points give their cell in the scan's grid of beams (``rowIndex``, ``columnIndex``)."""
        return all(f in self.fields for f in _GRID)

    @property
    def has_intensity(self) -> bool:
        return "intensity" in self.fields


def _libe57():
    try:
        from pye57 import libe57
    except ImportError:  # pragma: no cover - pye57 is a declared dependency
        raise ImportError("reading E57 needs pye57: pip install pye57") from None
    return libe57


def _first_line(e: Exception) -> str:
    lines = str(e).strip().splitlines()
    return lines[0].strip() if lines else type(e).__name__


def _check_file_header(path: Path) -> None:
    """Catch the commonest bad inputs (not E57, truncated) before libE57Format's terse codes."""
    if not path.is_file():
        raise InputError(path, "point cloud file does not exist")
    with open(path, "rb") as f:
        head = f.read(_HEADER_BYTES)
    if len(head) < _HEADER_BYTES or head[:8] != _SIGNATURE:
        raise InputError(path, "not an E57 file (no 'ASTM-E57' signature in the first 8 bytes)")
    declared = int.from_bytes(head[16:24], "little")
    actual = path.stat().st_size
    if actual < declared:
        raise InputError(path, f"E57 file truncated: its header declares {declared} bytes but "
                               f"only {actual} are present")


def _open(path: Path):
    _check_file_header(path)
    libe57 = _libe57()
    try:
        return libe57.ImageFile(str(path), "r")
    except Exception as e:  # libE57Format reports every defect as E57Exception (or RuntimeError)
        raise InputError(path, f"not a readable E57 file: {_first_line(e)}") from None


def _number(node) -> float:
    """Value of an Integer, ScaledInteger or Float node (the standard allows any for numbers)."""
    libe57 = _libe57()
    if isinstance(node, libe57.ScaledIntegerNode):
        return float(node.scaledValue())
    return float(node.value())


def _child_names(node) -> list[str]:
    return [node.get(i).elementName() for i in range(node.childCount())]


def _quaternion_matrix(path: Path, what: str, q: np.ndarray) -> np.ndarray:
    norm = float(np.linalg.norm(q))
    if not np.isfinite(q).all() or norm == 0.0:
        raise InputError(path, f"{what}: pose rotation quaternion {q.tolist()} is zero or non-finite")
    # The standard requires a unit quaternion, but writers store rounded or unnormalised ones
    # (cry-inc's test file has w=0.5, x=1): normalising gives the rotation they meant.
    w, x, y, z = q / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


def _pose(path: Path, what: str, node) -> tuple[np.ndarray, np.ndarray]:
    """``node``'s pose (local -> file-level): rotation (3, 3) and translation (3,) float64;
    the identity without one. ``what`` ("scan 3") starts the error messages."""
    rotation, translation = np.eye(3), np.zeros(3)
    if not node.isDefined("pose"):
        return rotation, translation
    pose = node["pose"]
    try:
        if pose.isDefined("rotation"):
            r = pose["rotation"]
            q = np.array([_number(r[c]) for c in "wxyz"], dtype=np.float64)
            rotation = _quaternion_matrix(path, what, q)
        if pose.isDefined("translation"):
            t = pose["translation"]
            translation = np.array([_number(t[c]) for c in "xyz"], dtype=np.float64)
    except InputError:
        raise
    except Exception as e:
        raise InputError(path, f"{what}: malformed pose: {_first_line(e)}") from None
    if not np.isfinite(translation).all():
        raise InputError(path, f"{what}: pose translation {translation.tolist()} is non-finite")
    return rotation, translation


def _color_limits(scan, proto) -> np.ndarray:
    """Per-channel (min, max): the scan's ``colorLimits`` if given, else the prototype's range."""
    limits = np.empty((3, 2))
    given = scan["colorLimits"] if scan.isDefined("colorLimits") else None
    for k, (field, short) in enumerate(zip(_COLORS, ("Red", "Green", "Blue"))):
        if given is not None and given.isDefined(f"color{short}Minimum") \
                and given.isDefined(f"color{short}Maximum"):
            lo = _number(given[f"color{short}Minimum"])
            hi = _number(given[f"color{short}Maximum"])
        else:
            node = proto[field]
            if hasattr(node, "scaledMinimum"):  # ScaledInteger: minimum() is the raw integer
                lo, hi = float(node.scaledMinimum()), float(node.scaledMaximum())
            else:
                lo, hi = float(node.minimum()), float(node.maximum())
        limits[k] = lo, hi
    return limits


def read_scans(path) -> list[E57Scan]:
    """The file's scans as its XML section describes them (headers only, no points read).

    Parameters
    ----------
    path : path-like
        An ``.e57`` file.

    Returns
    -------
    list of E57Scan
        One per ``data3D`` entry, in file order.

    Raises
    ------
    InputError
        Not an E57 file, truncated, no scans, or a scan without a complete set of Cartesian
        (``cartesianX/Y/Z``) or spherical (``sphericalRange/Azimuth/Elevation``) coordinates.
    """
    path = Path(path)
    imf = _open(path)
    try:
        return _scans(path, imf)
    finally:
        imf.close()


def _scans(path: Path, imf) -> list[E57Scan]:
    libe57 = _libe57()
    try:
        root = imf.root()
        if not root.isDefined("data3D"):
            raise InputError(path, "E57 file has no 'data3D' section (no scans)")
        data3d = root["data3D"]
        if len(data3d) == 0:
            raise InputError(path, "E57 file has no scans (its 'data3D' section is empty)")
        scans = []
        for i in range(len(data3d)):
            scan = data3d[i]
            if not scan.isDefined("points"):
                raise InputError(path, f"scan {i} has no 'points'")
            points = scan["points"]
            proto = libe57.StructureNode(points.prototype())
            fields = tuple(_child_names(proto))
            if all(f in fields for f in _CARTESIAN):
                coordinates = "cartesian"
            elif all(f in fields for f in _SPHERICAL):
                coordinates = "spherical"
            else:
                raise InputError(path, f"scan {i} has neither cartesianX/Y/Z nor sphericalRange/"
                                       f"Azimuth/Elevation coordinates (fields: {', '.join(fields)})")
            rotation, translation = _pose(path, f"scan {i}", scan)
            name = scan["name"].value() if scan.isDefined("name") else ""
            limits = _color_limits(scan, proto) if all(c in fields for c in _COLORS) else None
            scans.append(E57Scan(i, name, int(points.childCount()), coordinates, rotation,
                                 translation, fields, limits, _grid_size(scan)))
        return scans
    except InputError:
        raise
    except Exception as e:
        raise InputError(path, f"malformed E57 XML section: {_first_line(e)}") from None


def _grid_size(scan) -> tuple[int, int] | None:
    """``(rowMaximum, columnMaximum)`` of the scan's ``indexBounds``, None without them."""
    if not scan.isDefined("indexBounds"):
        return None
    b = scan["indexBounds"]
    if not (b.isDefined("rowMaximum") and b.isDefined("columnMaximum")):
        return None
    return int(_number(b["rowMaximum"])), int(_number(b["columnMaximum"]))


def count_points(path) -> int:
    """Records in all scans together, as the headers declare them (invalid records included)."""
    return sum(s.n_records for s in read_scans(path))


def scanner_positions(path) -> np.ndarray:
    """Scanner positions: (n_scans, 3) float64, world metres, in scan order.

    A scan's local origin is its scanner's centre, so its position in the world is the pose's
    translation (the origin for a scan without a pose).
    """
    return np.array([s.translation for s in read_scans(path)], dtype=np.float64).reshape(-1, 3)


def iter_chunks(path, chunk_size: int = 1_000_000) -> Iterator[PointCloud]:
    """Stream every scan's valid points in world coordinates, at most ``chunk_size`` per chunk.

    A chunk never spans two scans, so chunks at a scan's end (and chunks from which invalid
    points were dropped) are shorter; empty chunks are not yielded.

    Yields
    ------
    PointCloud
        ``positions`` (n, 3) float64 world metres (``R @ p + t`` of the scan's pose);
        ``colors`` (n, 3) uint8, scaled from the scan's colour limits, if every scan has colour
        (``isColorInvalid`` points get 0); ``intensity`` (n,) float32 as stored, if every scan has
        it (``isIntensityInvalid`` points get NaN); ``scan_index`` (n,) int32, the scan each point
        comes from (index into ``scanner_positions``); ``grid`` (n, 2) int32 (``rowIndex``,
        ``columnIndex``), if every scan is structured; ``normals`` None.

    Raises
    ------
    InputError
        Everything ``read_scans`` checks, plus corrupt or truncated point data, non-finite
        coordinates, and a file without any valid point.
    """
    path = Path(path)
    if chunk_size < 1:
        raise ValueError("chunk_size must be >= 1")
    imf = _open(path)
    try:
        scans = _scans(path, imf)
        # One layout for every chunk: a PLY writer or concatenation downstream needs it, and
        # inventing black colours / zero intensity for scans without them would be wrong data.
        colors = all(s.has_colors for s in scans)
        intensity = all(s.has_intensity for s in scans)
        grid = all(s.structured for s in scans)
        start = n_valid = 0
        for s in scans:
            for chunk in _scan_chunks(path, imf, s, chunk_size, colors, intensity, grid):
                n_valid += len(chunk)
                yield _validated(path, chunk, start)
                start += len(chunk)
    finally:
        imf.close()
    if n_valid == 0:
        total = sum(s.n_records for s in scans)
        raise InputError(path, f"empty point cloud: none of its {total} records is a valid point")


def _scan_chunks(path: Path, imf, scan: E57Scan, chunk_size: int, colors: bool,
                 intensity: bool, grid: bool = False) -> Iterator[PointCloud]:
    if scan.n_records == 0:
        return
    libe57 = _libe57()
    coords = _CARTESIAN if scan.coordinates == "cartesian" else _SPHERICAL
    state = "cartesianInvalidState" if scan.coordinates == "cartesian" else "sphericalInvalidState"
    wanted = list(coords) + [f for f in (state,) if f in scan.fields]
    if colors:
        wanted += list(_COLORS) + [f for f in ("isColorInvalid",) if f in scan.fields]
    if intensity:
        wanted += ["intensity"] + [f for f in ("isIntensityInvalid",) if f in scan.fields]
    if grid:
        wanted += list(_GRID)

    capacity = min(chunk_size, scan.n_records)
    # float64 for every field: the wrapper only takes some integer typecodes (int32 'i' is
    # refused, and 'l' is taken as 32-bit), while doubles hold any E57 integer up to 2**53
    # exactly; with conversion and scaling on, libE57Format hands over metres, radians, counts.
    arrays = {f: np.empty(capacity, np.float64) for f in wanted}
    try:
        node = imf.root()["data3D"][scan.index]["points"]
        buffers = libe57.VectorSourceDestBuffer()
        for f, a in arrays.items():
            buffers.append(libe57.SourceDestBuffer(imf, f, a, capacity, True, True))
        reader = node.reader(buffers)
    except Exception as e:
        raise InputError(path, f"scan {scan.index}: cannot read points: {_first_line(e)}") from None
    done = 0
    try:
        while done < scan.n_records:
            try:
                n = int(reader.read())
            except Exception as e:
                raise InputError(path, f"scan {scan.index}: corrupt point data after record "
                                       f"{done}: {_first_line(e)}") from None
            if n == 0:
                break
            done += n
            chunk = _to_cloud(scan, {f: a[:n] for f, a in arrays.items()}, state, colors, intensity, grid)
            if len(chunk):
                yield chunk
    finally:
        reader.close()
    if done < scan.n_records:
        raise InputError(path, f"scan {scan.index}: point data truncated: its header declares "
                               f"{scan.n_records} records but only {done} could be read")


def _to_cloud(scan: E57Scan, a: dict[str, np.ndarray], state: str, colors: bool,
              intensity: bool, grid: bool = False) -> PointCloud:
    keep = a[state] == 0 if state in a else slice(None)
    if scan.coordinates == "cartesian":
        local = np.stack([a[f][keep] for f in _CARTESIAN], axis=1)
    else:
        r, az, el = (a[f][keep] for f in _SPHERICAL)
        # E57 spherical: azimuth from +x towards +y in the xy plane, elevation up from that plane
        local = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az),
                          r * np.sin(el)], axis=1)
    positions = local @ scan.rotation.T + scan.translation
    rgb = None
    if colors:
        raw = np.stack([a[f][keep] for f in _COLORS], axis=1)
        lo, hi = scan.color_limits[:, 0], scan.color_limits[:, 1]
        ok = np.isfinite(hi - lo) & (hi > lo)
        # A channel without usable limits (an unbounded Float prototype) is taken as 0..255.
        offset = np.where(ok, lo, 0.0)
        scale = 255.0 / np.where(ok, hi - lo, 255.0)
        rgb = np.clip(np.rint((raw - offset) * scale), 0, 255).astype(np.uint8)
        if "isColorInvalid" in a:
            rgb[a["isColorInvalid"][keep] != 0] = 0
    inten = None
    if intensity:
        inten = a["intensity"][keep].astype(np.float32)
        if "isIntensityInvalid" in a:
            inten[a["isIntensityInvalid"][keep] != 0] = np.nan
    scan_index = np.full(len(positions), scan.index, dtype=np.int32)
    cells = np.stack([a[f][keep] for f in _GRID], axis=1).astype(np.int32) if grid else None
    return PointCloud(positions, None, rgb, intensity=inten, scan_index=scan_index, grid=cells)


# -- images2D: the scanner's photographs and panoramas ---------------------------------------------
_PROJECTIONS = {"pinholeRepresentation": "pinhole", "sphericalRepresentation": "spherical",
                "cylindricalRepresentation": "cylindrical"}
_NUMBERS = {"pinhole": ("focalLength", "pixelWidth", "pixelHeight", "principalPointX", "principalPointY"),
            "spherical": ("pixelWidth", "pixelHeight"),
            "cylindrical": ("pixelWidth", "pixelHeight", "radius", "principalPointY")}
_HEADER_BYTES_READ = 1 << 18  # a JPEG's or PNG's header (and size) lies in its first bytes


@dataclass(eq=False)  # hashed by identity: a cache key
class E57Image:
    """What one ``images2D`` entry says (headers only; :func:`read_image_pixels` decodes it).

    Attributes
    ----------
    index : int
        Position in the file's ``images2D`` vector.
    name : str
        The image's ``name`` ("" if it has none).
    representation : {"pinhole", "spherical", "cylindrical", "visual"}
        Its projection; "visual" for a visual reference image (no projection).
    width, height : int
        The representation's ``imageWidth`` and ``imageHeight``, pixels (0 if absent).
    blob : {"jpegImage", "pngImage"} or None
        The blob that holds its pixels.
    has_mask : bool
        An ``imageMask`` is given (non-zero = valid pixel).
    rotation : (3, 3) float64 or None
        Image-local -> file-level rotation of its pose; None without a pose.
    translation : (3,) float64
        The pose's translation, metres: the centre of projection in the file's frame.
    numbers : dict of str -> float
        The representation's fields (``focalLength``, ``pixelWidth``, ...; see ASTM E2807 8.4.13-15).
    problem : str or None
        Why it cannot be a photo (no pose, visual reference only, no decodable blob, ...); None if
        it can.
    """

    index: int
    name: str
    representation: Literal["pinhole", "spherical", "cylindrical", "visual"]
    width: int
    height: int
    blob: str | None
    has_mask: bool
    rotation: np.ndarray | None
    translation: np.ndarray
    numbers: dict
    problem: str | None = None

    @property
    def node_name(self) -> str:
        """The representation's element name (``sphericalRepresentation``)."""
        return f"{self.representation}{'Reference' if self.representation == 'visual' else ''}Representation"


def _read_blob(node, limit: int | None = None) -> bytes:
    n = int(node.byteCount()) if limit is None else min(limit, int(node.byteCount()))
    buf = np.empty(n, np.uint8)
    if n:
        node.read(buf, 0, n)
    return buf.tobytes()


def _blob_problem(node, blob: str, width: int, height: int) -> str | None:
    """Why the blob is not a ``width`` x ``height`` image, from its header (None if it is)."""
    import io

    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(io.BytesIO(_read_blob(node, _HEADER_BYTES_READ))) as im:
            size = im.size
    except (UnidentifiedImageError, OSError, ValueError) as e:
        return f"its {blob} blob ({int(node.byteCount())} bytes) is not a decodable image ({_first_line(e)})"
    if size != (width, height):
        return f"its {blob} is {size[0]}x{size[1]} pixels but the header says {width}x{height}"
    return None


def _fields_problem(rep_name: str, blob: str | None, size: list[int], numbers: dict, kind: str) -> str | None:
    """Why a projection's fields cannot make a photo (None if they can)."""
    if blob is None:
        return f"its {rep_name} has no jpegImage or pngImage blob"
    if min(size) <= 0:
        return f"its {rep_name} gives no positive imageWidth/imageHeight"
    missing = [k for k in _NUMBERS[kind] if k not in numbers]
    if missing:
        return f"its {rep_name} lacks {', '.join(missing)}"
    bad = [k for k, v in numbers.items() if not (np.isfinite(v) and (v > 0 or k.startswith("principalPoint")))]
    return f"its {rep_name} has non-positive or non-finite {', '.join(bad)}" if bad else None


def _image(path: Path, index: int, node, check_blobs: bool) -> E57Image:
    name = node["name"].value() if node.isDefined("name") else ""
    rep_name = next((k for k in _PROJECTIONS if node.isDefined(k)), "visualReferenceRepresentation")
    kind = _PROJECTIONS.get(rep_name, "visual")
    rep = node[rep_name] if node.isDefined(rep_name) else None
    has = (lambda k: rep is not None and rep.isDefined(k))  # noqa: E731
    blob = next((b for b in ("jpegImage", "pngImage") if has(b)), None)
    size = [int(rep[k].value()) if has(k) else 0 for k in ("imageWidth", "imageHeight")]
    numbers = {k: _number(rep[k]) for k in _NUMBERS.get(kind, ()) if has(k)}
    image = E57Image(index, name, kind, size[0], size[1], blob, has("imageMask"), None, np.zeros(3), numbers)
    if kind == "visual":
        image.problem = "a visual reference image only (no pinhole, spherical or cylindrical representation)"
    elif not node.isDefined("pose"):
        image.problem = "it has no pose"
    else:
        try:
            image.rotation, image.translation = _pose(path, f"image {index}", node)
        except InputError as e:
            image.problem = e.message
    if image.problem is None:
        image.problem = _fields_problem(rep_name, blob, size, numbers, kind)
    if image.problem is None and check_blobs:
        image.problem = _blob_problem(rep[blob], blob, *size)
    return image


def read_images(path, check_blobs: bool = True) -> list[E57Image]:
    """The file's ``images2D`` entries as its XML section describes them.

    Parameters
    ----------
    path : path-like
        An ``.e57`` file.
    check_blobs : bool
        Read each usable image's blob header: one that does not decode as an image of the
        header's size gets a ``problem``.

    Returns
    -------
    list of E57Image
        One per entry, in file order (empty without ``images2D``); each either usable as a photo
        or with its ``problem``.

    Raises
    ------
    InputError
        Not an E57 file, truncated, or a malformed XML section.
    """
    path = Path(path)
    imf = _open(path)
    try:
        root = imf.root()
        if not root.isDefined("images2D"):
            return []
        images = root["images2D"]
        return [_image(path, i, images[i], check_blobs) for i in range(len(images))]
    except InputError:
        raise
    except Exception as e:
        raise InputError(path, f"malformed images2D section: {_first_line(e)}") from None
    finally:
        imf.close()


def _decode_blob(path: Path, image: E57Image, blob: str, mode: str) -> np.ndarray:
    """The ``blob`` of ``image`` decoded by PIL and converted to ``mode`` ("RGB", "L")."""
    import io

    from PIL import Image

    imf = _open(path)
    try:
        data = _read_blob(imf.root()["images2D"][image.index][image.node_name][blob])
        with Image.open(io.BytesIO(data)) as im:
            return np.asarray(im.convert(mode), dtype=np.uint8)
    except Exception as e:  # libE57Format's errors, and PIL's for an undecodable blob
        raise InputError(path, f"image {image.index} ({image.name!r}): cannot decode its {blob}: "
                               f"{_first_line(e)}") from None
    finally:
        imf.close()


@functools.lru_cache(maxsize=2)  # the views of one panorama are read one after another
def _cached_rgb(path: Path, mtime_ns: int, image: E57Image) -> np.ndarray:
    rgb = _decode_blob(path, image, image.blob, "RGB")
    rgb.flags.writeable = False  # shared by the cache
    return rgb


def read_image_pixels(path, image: E57Image) -> np.ndarray:
    """``image``'s pixels: (height, width, 3) uint8 RGB, read-only (the last two are cached)."""
    path = Path(path)
    return _cached_rgb(path, path.stat().st_mtime_ns, image)


def read_image_mask(path, image: E57Image) -> np.ndarray | None:
    """(height, width) bool: ``image``'s ``imageMask`` (True = valid pixel), None without one."""
    if not image.has_mask:
        return None
    path = Path(path)
    mask = _decode_blob(path, image, "imageMask", "L") > 0
    if mask.shape != (image.height, image.width):
        raise InputError(path, f"image {image.index} ({image.name!r}): its imageMask is "
                               f"{mask.shape[1]}x{mask.shape[0]}, the image {image.width}x{image.height}")
    return mask
