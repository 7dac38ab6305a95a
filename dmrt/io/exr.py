"""Depth maps on disk: OpenEXR, one float32 channel ``Z`` (camera z in metres, 0 = no surface),
written atomically (:mod:`dmrt.io.atomic`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from dmrt.errors import InputError
from dmrt.io.atomic import atomic_file


def write_depth_exr(path, depth: np.ndarray) -> None:
    """Write a depth map as OpenEXR, one float32 channel ``Z`` (ZIP compressed, scanlines).

    Written to a temporary file beside ``path`` and renamed, so an interrupted write never leaves
    a truncated map under the final name.

    Parameters
    ----------
    path : str or Path
    depth : (height, width) float32
        Camera z in metres, 0.0 = no surface.
    """
    import OpenEXR

    path = Path(path)
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"a depth map is (height, width), got shape {depth.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with atomic_file(path) as tmp:
        OpenEXR.File(header, {"Z": depth}).write(str(tmp))


def read_depth_exr(path) -> np.ndarray:
    """Read a depth map written by :func:`write_depth_exr`.

    Returns
    -------
    depth : (height, width) float32
        Camera z in metres, 0.0 = no surface.

    Raises
    ------
    InputError
        The file is missing, not OpenEXR, has no ``Z`` channel, or holds non-depth values
        (non-float, non-finite or negative); the message names the file.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "depth map not found")
    try:
        channels = OpenEXR.File(str(path)).channels()
    except Exception as exc:  # OpenEXR raises RuntimeError with the library's message
        raise InputError(path, f"not a readable OpenEXR file ({exc})") from None
    if "Z" not in channels:
        raise InputError(path, f"no 'Z' channel (channels: {', '.join(sorted(channels)) or 'none'})")
    z = np.asarray(channels["Z"].pixels)
    if z.ndim != 2 or z.dtype.kind != "f":
        raise InputError(path, f"channel 'Z' must be one float per pixel, got {z.dtype} {z.shape}")
    z = z.astype(np.float32, copy=False)
    if not np.isfinite(z).all() or (z < 0).any():
        raise InputError(path, "channel 'Z' holds non-finite or negative depths (0 = no surface)")
    return z
