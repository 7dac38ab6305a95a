"""Depth maps on disk: OpenEXR, one float32 channel ``Z`` (camera z in metres, 0 = no surface),
written atomically (:mod:`dmrt.io.atomic`)."""

from __future__ import annotations

import os
import sys
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

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


_STDERR_LOCK = threading.Lock()


@contextmanager
def library_stderr() -> Iterator[list]:
    """Hold back what C libraries (OpenEXR reports a corrupt file on file descriptor 2 before it
    raises) write to stderr inside the block: yields a list that receives the text, so that a
    reader can fold it into its one-line error. Text written by a block that succeeds is passed
    on to stderr unchanged. File descriptor 2 belongs to the process: blocks on several threads
    (the renderer's depth-map loads) take turns."""
    with _STDERR_LOCK:
        sys.stderr.flush()
        saved = os.dup(2)
        with tempfile.TemporaryFile() as buf:
            os.dup2(buf.fileno(), 2)
            held: list = []
            ok = False
            try:
                yield held
                ok = True
            finally:
                os.dup2(saved, 2)
                os.close(saved)
                buf.seek(0)
                text = buf.read().decode(errors="replace")
                held.append(text)
                if ok and text:
                    sys.stderr.write(text)


def _first_line(text: str, path: Path) -> str:
    """The library's first message line, without the file name it repeats."""
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return lines[0].replace(f" '{path}'", "").replace(f"{path}: ", "").replace(str(path), "the file") if lines else ""


def read_exr_channels(path) -> dict:
    """``{name: pixels}`` of an OpenEXR file, or an :class:`InputError` naming it (with the
    library's reason, on one line) when it is not readable: not OpenEXR, truncated, corrupt."""
    import OpenEXR

    path = Path(path)
    try:
        with library_stderr() as held:
            return {k: v.pixels for k, v in OpenEXR.File(str(path)).channels().items()}
    except Exception as exc:  # OpenEXR raises RuntimeError with the library's message
        reason = _first_line(held[0] if held else "", path) or str(exc).replace(str(path), "the file")
        raise InputError(path, f"not a readable OpenEXR file, truncated or corrupt ({reason})") from None


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
    path = Path(path)
    if not path.is_file():
        raise InputError(path, "depth map not found")
    channels = read_exr_channels(path)
    if "Z" not in channels:
        raise InputError(path, f"no 'Z' channel (channels: {', '.join(sorted(channels)) or 'none'})")
    z = np.asarray(channels["Z"])
    if z.ndim != 2 or z.dtype.kind != "f":
        raise InputError(path, f"channel 'Z' must be one float per pixel, got {z.dtype} {z.shape}")
    z = z.astype(np.float32, copy=False)
    if not np.isfinite(z).all() or (z < 0).any():
        raise InputError(path, "channel 'Z' holds non-finite or negative depths (0 = no surface)")
    return z
