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


def camera_from_json(d: dict) -> Camera:
    return Camera(d["name"], d["width"], d["height"], d["fx"], d["fy"], d["cx"], d["cy"],
                  np.array(d["R"]), np.array(d["t"]))


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
        """(h, w) float32 camera z of photo ``i``'s depth map, 0 = empty."""
        return read_depth_exr(self.path("depthmaps", i))

    def image(self, i: int, low: bool = False) -> np.ndarray:
        """(h, w, 3) uint8 RGB: photo ``i``, or its low-resolution copy."""
        from PIL import Image

        p = self.path("images_low" if low else "images", i)
        try:
            with Image.open(p) as im:
                return np.asarray(im.convert("RGB"))
        except (OSError, ValueError) as exc:
            raise InputError(p, f"cannot read image ({exc})") from exc

    @property
    def proxy(self) -> dict:
        """The proxy points P_LD: dict of ``positions``, ``normals``, ``radii``, ``labels``."""
        if self._proxy is None:
            self._proxy = _read_proxy(self.root / "proxy.npz")
        return self._proxy


def _read_proxy(path: Path) -> dict:
    try:
        with np.load(path) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise InputError(path, f"cannot read proxy points ({exc})") from exc
    n = None
    for key, (dtype, width) in PROXY_ARRAYS.items():
        if key not in arrays:
            raise InputError(path, f"missing array '{key}'")
        a = arrays[key]
        shape_ok = a.ndim == (2 if width else 1) and (width is None or a.shape[1] == width)
        if not shape_ok or a.dtype != dtype:
            raise InputError(path, f"array '{key}' has shape {a.shape} dtype {a.dtype}, expected "
                                   f"{'(n, %d)' % width if width else '(n,)'} {np.dtype(dtype)}")
        if n is not None and len(a) != n:
            raise InputError(path, f"array '{key}' has {len(a)} rows, 'positions' has {n}")
        n = len(a)
    return arrays


def read_bundle(path) -> Bundle:
    """Open a bundle, checking the schema and that every listed file exists."""
    root = Path(path)
    meta_path = root / "bundle.json"
    if not root.is_dir():
        raise InputError(root, "bundle directory not found")
    if not meta_path.is_file():
        partial = root.with_name(root.name + ".partial")
        hint = " (an interrupted preprocessing left a .partial folder)" if partial.exists() else ""
        raise InputError(meta_path, f"not a bundle: bundle.json missing{hint}")
    try:
        meta = json.loads(meta_path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(meta_path, f"not valid JSON ({exc})") from exc
    if meta.get("schema") != SCHEMA:
        raise InputError(meta_path, f"field 'schema' is {meta.get('schema')!r}, expected {SCHEMA!r}")
    if meta.get("version") != SCHEMA_VERSION:
        raise InputError(meta_path, f"field 'version' is {meta.get('version')!r}; this suite reads "
                                    f"version {SCHEMA_VERSION}: preprocess the scene again")
    for key in ("origin", "cameras", "images", "images_low", "depthmaps"):
        if key not in meta:
            raise InputError(meta_path, f"field '{key}' missing")
    try:
        cameras = [camera_from_json(c) for c in meta["cameras"]]
    except (KeyError, TypeError, ValueError) as exc:
        raise InputError(meta_path, f"field 'cameras' malformed ({exc})") from exc
    for key in ("images", "images_low", "depthmaps"):
        if len(meta[key]) != len(cameras):
            raise InputError(meta_path, f"field '{key}' lists {len(meta[key])} files for {len(cameras)} cameras")
        for rel in meta[key]:
            if not (root / rel).is_file():
                raise InputError(root / rel, f"listed in bundle.json '{key}' but missing")
    if not (root / "proxy.npz").is_file():
        raise InputError(root / "proxy.npz", "missing")
    return Bundle(root, np.asarray(meta["origin"], np.float64), cameras, meta)


class BundleWriter:
    """Assembles a bundle in ``<out>.partial`` (:func:`dmrt.io.atomic.atomic_dir`); it is renamed to
    ``out`` when the ``with`` block that called :meth:`finish` ends without an error.

    ``force`` replaces an existing bundle; otherwise an existing ``out`` is refused up front.
    """

    def __init__(self, out, force: bool = False):
        self.out = Path(out)
        self._dir = atomic_dir(self.out, force=force, what="bundle")
        self._finished = False

    def __enter__(self) -> "BundleWriter":
        self.tmp = self._dir.__enter__()
        for sub in ("depthmaps", "images", "images_low"):
            (self.tmp / sub).mkdir(parents=True)
        return self

    def add_image(self, src: Path, name: str) -> str:
        """Link (or copy) a photo into the bundle; returns its path relative to the bundle."""
        dst = self.tmp / "images" / name
        dst.parent.mkdir(parents=True, exist_ok=True)
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

    def finish(self, meta: dict) -> Path:
        """Write ``bundle.json`` (the last file: a folder without it is no bundle); returns ``out``."""
        meta = {"schema": SCHEMA, "version": SCHEMA_VERSION, **meta}
        (self.tmp / "bundle.json").write_text(json.dumps(meta, indent=1))
        self._finished = True
        return self.out

    def __exit__(self, exc_type, exc, tb) -> None:
        if exc_type is None and not self._finished:
            exc_type = RuntimeError  # a block that never finished leaves no bundle
        self._dir.__exit__(exc_type, exc, tb)
