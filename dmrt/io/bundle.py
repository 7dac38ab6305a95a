"""The scene bundle: what preprocessing writes and every renderer reads.

Layout (DESIGN.md)::

    BUNDLE/bundle.json            schema version, scene origin, cameras, file lists, parameters,
                                  timings, counts, the command that made it
    BUNDLE/depthmaps/<stem>.exr   one float32 depth map per photo (channel Z, camera z, 0 = empty)
    BUNDLE/proxy.npz              positions (n,3) float32 (relative to the origin), normals (n,3)
                                  float32, radii (n,) float32 metres, labels (n,) int32, and
                                  hd_radii (n,) float32: the points' splat radii in P_HD
    BUNDLE/images/<name>          the photographs (hard links to the scene's when possible)
    BUNDLE/images_low/<stem>.png  low-resolution copies (paper: 256x171)

A bundle is assembled in ``<BUNDLE>.partial`` and renamed when complete, so an interrupted run
never leaves a directory that looks like a bundle.
"""

from __future__ import annotations

import json
import os
import shutil
import threading
import zipfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dmrt.camera import Camera
from dmrt.errors import InputError
from dmrt.io.atomic import atomic_dir
from dmrt.io.exr import read_depth_exr

SCHEMA = "dmrt-bundle"
SCHEMA_VERSION = 1
PROXY_ARRAYS = {"positions": (np.float32, 3), "normals": (np.float32, 3), "radii": (np.float32, None),
                "labels": (np.int32, None)}


def camera_to_json(c: Camera) -> dict:
    return {"name": c.name, "width": c.width, "height": c.height, "fx": c.fx, "fy": c.fy, "cx": c.cx,
            "cy": c.cy, "R": c.R.tolist(), "t": c.t.tolist()}


CAMERA_FIELDS = ("name", "width", "height", "fx", "fy", "cx", "cy", "R", "t")


def read_json(path, kind: str, hint: str):
    """The JSON document in file ``path``, a ``kind`` file (e.g. "camera pose"); one-line
    :class:`InputError` naming the file when it is missing, a folder or not JSON (``hint`` says
    what the file should be)."""
    path = Path(path)
    if path.is_dir():
        raise InputError(path, f"is a folder, not a {kind} file ({hint})")
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise InputError(path, f"{kind} file not found") from None
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(path, f"not a {kind}: not valid JSON ({exc})") from None


def camera_from_json(d: dict, path=None, where: str = "") -> Camera:
    """A :class:`Camera` from its JSON object (:func:`camera_to_json`), every field checked.

    Parameters
    ----------
    d : the parsed JSON object.
    path : the file it came from, named by the error.
    where : what it is within that file (e.g. ``"cameras[3]"``), named by the error.

    Raises
    ------
    InputError
        ``"<path>: <where>: field 'R' must be 3x3, got shape (2, 3)"`` and the like: not an
        object, a field missing, sizes that are not whole numbers >= 1, focal lengths <= 0,
        non-finite numbers, ``R`` not a rotation.
    """
    prefix = f"{where}: " if where else ""

    def bad(message: str) -> InputError:
        return InputError(path, prefix + message)

    if not isinstance(d, dict):
        raise bad(f"expected a JSON object with {', '.join(CAMERA_FIELDS)}, got {type(d).__name__}")
    missing = [k for k in CAMERA_FIELDS if k not in d]
    if missing:
        raise bad(f"field{'s' if len(missing) > 1 else ''} {', '.join(repr(k) for k in missing)} missing")
    if not isinstance(d["name"], str) or not d["name"]:
        raise bad(f"field 'name' must be a non-empty string, not {d['name']!r}")
    for key in ("width", "height"):
        v = d[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not float(v).is_integer() or v < 1:
            raise bad(f"field '{key}' must be a whole number of pixels >= 1, not {v!r}")
    for key in ("fx", "fy", "cx", "cy"):
        v = d[key]
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not np.isfinite(v):
            raise bad(f"field '{key}' must be a finite number, not {v!r}")
        if key in ("fx", "fy") and v <= 0:
            raise bad(f"field '{key}' must be > 0 (pixels), not {v!r}")
    arrays = {}
    for key, shape in (("R", (3, 3)), ("t", (3,))):
        try:
            a = np.asarray(d[key], dtype=np.float64)
        except (TypeError, ValueError):
            raise bad(f"field '{key}' must be {'a 3x3 array of' if key == 'R' else '3'} "
                      f"numbers, not {str(d[key])[:60]}") from None
        if a.shape != shape:
            raise bad(f"field '{key}' must be {'x'.join(map(str, shape)) if key == 'R' else '3 numbers'}, "
                      f"got shape {a.shape}")
        if not np.isfinite(a).all():
            raise bad(f"field '{key}' holds NaN or infinite values")
        arrays[key] = a
    R = arrays["R"]
    err = float(np.abs(R @ R.T - np.eye(3)).max())
    if err > 1e-3 or np.linalg.det(R) < 0:
        raise bad(f"field 'R' is not a rotation matrix (max |R R^T - I| = {err:.3g}, det {np.linalg.det(R):.3g})")
    return Camera(d["name"], d["width"], d["height"], d["fx"], d["fy"], d["cx"], d["cy"], R, arrays["t"])


@dataclass
class Bundle:
    """A preprocessed scene, read back from disk.

    Attributes
    ----------
    root : Path
    origin : (3,) float64, the scene origin (world metres) that GPU-side coordinates are relative to.
    cameras : list of Camera in world coordinates.
    meta : the parsed ``bundle.json``.
    """

    root: Path
    origin: np.ndarray
    cameras: list[Camera]
    meta: dict
    _proxy: dict | None = field(default=None, repr=False)

    def path(self, key: str, i: int) -> Path:
        """File ``i`` of list ``key`` (``images``, ``images_low`` or ``depthmaps``)."""
        return self.root / self.meta[key][i]

    def depth_map(self, i: int) -> np.ndarray:
        """(h, w) float32 camera z of photo ``i``'s depth map, 0 = empty.

        Raises :class:`InputError` naming the file when it is unreadable or not the size
        ``bundle.json``'s ``depthmap_sizes`` gives.
        """
        path = self.path("depthmaps", i)
        m = read_depth_exr(path)
        sizes = self.meta.get("depthmap_sizes")
        if sizes is not None and tuple(m.shape[::-1]) != tuple(sizes[i]):
            raise InputError(path, f"depth map is {m.shape[1]}x{m.shape[0]} but bundle.json "
                                   f"'depthmap_sizes' says {sizes[i][0]}x{sizes[i][1]}")
        return m

    def image(self, i: int, low: bool = False) -> np.ndarray:
        """(h, w, 3) uint8 RGB: photo ``i``, or its low-resolution copy."""
        from PIL import Image

        p = self.path("images_low" if low else "images", i)
        if not p.is_file():
            raise InputError(p, f"listed in bundle.json '{'images_low' if low else 'images'}' but missing")
        try:
            with Image.open(p) as im:
                return np.asarray(im.convert("RGB"))
        except (OSError, ValueError) as exc:
            raise InputError(p, f"cannot read image ({exc})") from exc

    @property
    def photo_gains(self) -> np.ndarray:
        """(n_photos, 3) float32: each photo's RGB colour gain from preprocessing's photometric
        adjustment (:mod:`dmrt.preprocess.photometric`; bundle.json ``photo_gains``), all 1 when
        the bundle has none (made before it). Raises :class:`InputError` naming bundle.json when
        the field is not n_photos rows of 3 finite numbers > 0."""
        n = len(self.cameras)
        gains = self.meta.get("photo_gains")
        if gains is None:
            return np.ones((n, 3), np.float32)
        try:
            a = np.asarray(gains, np.float64)
        except (TypeError, ValueError):
            a = np.zeros(0)
        if a.shape != (n, 3) or not np.isfinite(a).all() or (a <= 0).any():
            raise InputError(self.root / "bundle.json", f"field 'photo_gains' must list 3 finite gains > 0 for each "
                                                        f"of the {n} photos (got shape {a.shape})")
        return a.astype(np.float32)

    @property
    def proxy(self) -> dict:
        """The proxy points P_LD: dict of ``positions``, ``normals``, ``radii``, ``labels``."""
        if self._proxy is None:
            self._proxy = _read_proxy(self.root / "proxy.npz", len(self.cameras))
        return self._proxy


def _read_proxy(path: Path, n_photos: int | None = None) -> dict:
    """The arrays of ``proxy.npz``, checked against :data:`PROXY_ARRAYS` (names, dtypes, shapes,
    equal lengths, finite values, labels in ``-1..n_photos-1``); an :class:`InputError` naming
    the file and the array otherwise."""
    import zlib

    if not path.is_file():
        raise InputError(path, "missing")
    if not zipfile.is_zipfile(path):
        raise InputError(path, "cannot read proxy points: not an .npz (zip) archive, or truncated")
    try:
        z = np.load(path, allow_pickle=False)
        if not isinstance(z, np.lib.npyio.NpzFile):  # a plain .npy array, not an archive
            raise InputError(path, "cannot read proxy points: a single .npy array, not an .npz archive")
        with z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, KeyError, zipfile.BadZipFile, EOFError, zlib.error) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(path, f"cannot read proxy points: not a complete .npz file ({exc})") from None
    n = None
    for key, (dtype, width) in PROXY_ARRAYS.items():
        if key not in arrays:
            raise InputError(path, f"missing array '{key}' (has: {', '.join(sorted(arrays)) or 'none'})")
        a = arrays[key]
        shape_ok = a.ndim == (2 if width else 1) and (width is None or a.shape[1] == width)
        if not shape_ok or a.dtype != dtype:
            raise InputError(path, f"array '{key}' has shape {a.shape} dtype {a.dtype}, expected "
                                   f"{'(n, %d)' % width if width else '(n,)'} {np.dtype(dtype)}")
        if n is not None and len(a) != n:
            raise InputError(path, f"array '{key}' has {len(a)} rows, 'positions' has {n}")
        if a.dtype.kind == "f" and not np.isfinite(a).all():
            raise InputError(path, f"array '{key}' holds NaN or infinite values")
        n = len(a)
    if n == 0:
        raise InputError(path, "no proxy points (arrays of length 0)")
    labels = arrays["labels"]
    top = n_photos if n_photos is not None else np.iinfo(np.int32).max
    if labels.min() < -1 or labels.max() >= top:
        bad = int(labels.min() if labels.min() < -1 else labels.max())
        raise InputError(path, f"array 'labels' holds photo index {bad}; labels are -1 (none) or "
                               f"0..{top - 1} (the bundle has {n_photos} photos)")
    return arrays


def _partial_hint(root: Path) -> str:
    partial = root.with_name(root.name + ".partial")
    return (f" ({partial.name} is left from an interrupted preprocessing: run dmrt preprocess again)"
            if partial.exists() else "")


def read_bundle(path) -> Bundle:
    """Open a bundle, checking the schema, the fields and that every listed file exists.

    Raises
    ------
    InputError
        Naming ``bundle.json`` and the field, or the missing file.
    """
    root = Path(path)
    meta_path = root / "bundle.json"
    if root.name.endswith(".partial"):
        raise InputError(root, "an unfinished bundle left by an interrupted preprocessing "
                               "(.partial): run dmrt preprocess again")
    if not root.exists():
        raise InputError(root, "bundle directory not found" + _partial_hint(root))
    if not root.is_dir():
        raise InputError(root, "not a bundle: a file, not a directory")
    if not meta_path.is_file():
        raise InputError(meta_path, "not a bundle: bundle.json missing" + _partial_hint(root))
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(meta_path, f"not valid JSON ({exc})") from None
    if not isinstance(meta, dict):
        raise InputError(meta_path, f"not a bundle description: a JSON {type(meta).__name__}, not an object")
    if meta.get("schema") != SCHEMA:
        raise InputError(meta_path, f"field 'schema' is {meta.get('schema')!r}, expected {SCHEMA!r}")
    if meta.get("version") != SCHEMA_VERSION:
        raise InputError(meta_path, f"field 'version' is {meta.get('version')!r}; this suite reads "
                                    f"version {SCHEMA_VERSION}: preprocess the scene again")
    for key in ("origin", "cameras", "images", "images_low", "depthmaps"):
        if key not in meta:
            raise InputError(meta_path, f"field '{key}' missing")
    try:
        origin = np.asarray(meta["origin"], np.float64)
    except (TypeError, ValueError):
        origin = None
    if origin is None or origin.shape != (3,) or not np.isfinite(origin).all():
        raise InputError(meta_path, f"field 'origin' must be 3 finite numbers, not {str(meta['origin'])[:60]}")
    if not isinstance(meta["cameras"], list) or not meta["cameras"]:
        raise InputError(meta_path, "field 'cameras' must be a non-empty list of cameras")
    cameras = [camera_from_json(c, meta_path, f"cameras[{i}]") for i, c in enumerate(meta["cameras"])]
    for key in ("images", "images_low", "depthmaps"):
        files = meta[key]
        if not isinstance(files, list) or not all(isinstance(f, str) for f in files):
            raise InputError(meta_path, f"field '{key}' must be a list of file names")
        if len(files) != len(cameras):
            raise InputError(meta_path, f"field '{key}' lists {len(files)} files for {len(cameras)} cameras")
        for rel in files:
            if not (root / rel).is_file():
                raise InputError(root / rel, f"listed in bundle.json '{key}' but missing")
    sizes = meta.get("depthmap_sizes")
    if sizes is not None and (not isinstance(sizes, list) or len(sizes) != len(cameras) or not all(
            isinstance(s, list) and len(s) == 2 and all(isinstance(v, int) and v > 0 for v in s) for s in sizes)):
        raise InputError(meta_path, f"field 'depthmap_sizes' must list [width, height] for each of the "
                                    f"{len(cameras)} cameras")
    if not (root / "proxy.npz").is_file():
        raise InputError(root / "proxy.npz", "missing")
    return Bundle(root, origin, cameras, meta)


class BundleWriter:
    """Assembles a bundle in ``<out>.partial`` (:func:`dmrt.io.atomic.atomic_dir`); it is renamed to
    ``out`` when the ``with`` block that called :meth:`finish` ends without an error.

    ``force`` replaces an existing bundle; otherwise an existing ``out`` is refused up front.
    Work files made beside the bundle's are deleted on a thread (:meth:`discard`).
    """

    def __init__(self, out, force: bool = False):
        self.out = Path(out)
        self._dir = atomic_dir(self.out, force=force, what="bundle")
        self._finished = False
        # where discarded folders wait for their deletion: beside <out>.partial, on its file system
        self._trash = self.out.with_name(f".{self.out.name}.discarded")
        self._deleting: list[threading.Thread] = []

    def __enter__(self) -> "BundleWriter":
        shutil.rmtree(self._trash, ignore_errors=True)  # left by a run that was killed
        self.tmp = self._dir.__enter__()
        for sub in ("depthmaps", "images", "images_low"):
            (self.tmp / sub).mkdir(parents=True)
        return self

    def add_image(self, src: Path, name: str, pixels: np.ndarray | None = None) -> str:
        """Link (or copy) the photo file ``src`` into the bundle as ``images/<name>``, or, given
        ``pixels`` ((h, w, 3) uint8 RGB: a photo preprocessing made, undistorted or cut from a
        panorama), encode them there in the format the name's suffix gives (JPEG at quality 95;
        PNG, with ``.png`` appended, for a suffix PIL cannot write). Returns the path relative to
        the bundle."""
        dst = self.tmp / "images" / name
        dst.parent.mkdir(parents=True, exist_ok=True)
        if pixels is not None:
            from PIL import Image

            try:
                Image.fromarray(pixels).save(dst, quality=95)
            except (ValueError, KeyError):  # PIL has no writer for this suffix
                dst.unlink(missing_ok=True)
                dst = dst.with_name(dst.name + ".png")
                Image.fromarray(pixels).save(dst)
            return dst.relative_to(self.tmp).as_posix()
        try:
            os.link(src, dst)
        except OSError:  # another file system: copy
            shutil.copy2(src, dst)
        return f"images/{name}"

    def write_proxy(self, **arrays) -> None:
        """Write ``proxy.npz``; arrays as in :data:`PROXY_ARRAYS` (and any extra ones)."""
        for key, (dtype, _) in PROXY_ARRAYS.items():
            arrays[key] = np.ascontiguousarray(arrays[key], dtype=dtype)
        np.savez(self.tmp / "proxy.npz", **arrays)

    def discard(self, folder) -> None:
        """Delete ``folder`` (work files under :attr:`tmp`) while the caller goes on: it leaves the
        bundle at once (renamed aside) and is unlinked on a thread (tens of GB of files take
        seconds). :meth:`wait_discarded`, and the ``with`` block's end, wait for it."""
        self._trash.mkdir(exist_ok=True)
        gone = self._trash / str(len(self._deleting))
        os.replace(folder, gone)
        thread = threading.Thread(target=shutil.rmtree, args=(gone,), kwargs={"ignore_errors": True},
                                  name="dmrt-discard")
        thread.start()
        self._deleting.append(thread)

    def wait_discarded(self) -> None:
        """Return once every folder given to :meth:`discard` is deleted."""
        for thread in self._deleting:
            thread.join()
        shutil.rmtree(self._trash, ignore_errors=True)

    def finish(self, meta: dict) -> Path:
        """Write ``bundle.json`` (the last file: a folder without it is no bundle); returns ``out``."""
        meta = {"schema": SCHEMA, "version": SCHEMA_VERSION, **meta}
        (self.tmp / "bundle.json").write_text(json.dumps(meta, indent=1))
        self._finished = True
        return self.out

    def __exit__(self, exc_type, exc, tb) -> None:
        self.wait_discarded()
        if exc_type is None and not self._finished:
            exc_type = RuntimeError  # a block that never finished leaves no bundle
        self._dir.__exit__(exc_type, exc, tb)
