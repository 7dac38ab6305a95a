"""Atomic writes: every file and folder the suite writes appears under its final name only when
complete, so an interrupted run never leaves output that looks whole.

A file is written to a hidden temporary file beside it (same suffix, so writers that choose the
format by suffix still work) and renamed over the final name; a folder is assembled in
``<name>.partial`` and renamed into place, an existing one being replaced only when asked.
"""

from __future__ import annotations

import json
import math
import os
import shutil
import signal
import tempfile
import threading
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

from dmrt.errors import InputError


@contextmanager
def atomic_file(path) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; rename it to ``path`` when the block succeeds.

    Parameters
    ----------
    path : str or Path
        The final file; its folder is created if missing.

    Yields
    ------
    Path
        Where to write (same folder and suffix as ``path``); removed if the block raises.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    tmp = Path(tmp)
    try:
        yield tmp
        # mkstemp makes the file private (0600); give it the mode a plain open() would have
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    finally:
        tmp.unlink(missing_ok=True)


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_text(path, text: str) -> Path:
    """Write ``text`` to ``path`` atomically; returns ``Path(path)``."""
    with atomic_file(path) as tmp:
        tmp.write_text(text)
    return Path(path)


def json_text(doc, indent: int | None = 1) -> str:
    """``doc`` as strict JSON: a float that is not a number (NaN: a time that was not measured) or
    infinite is ``null``, where Python's ``json`` would write ``NaN``, which JSON readers refuse.
    numpy scalars and arrays are written as numbers and lists."""

    def plain(v):
        if isinstance(v, dict):
            return {k: plain(x) for k, x in v.items()}
        if isinstance(v, (list, tuple)):
            return [plain(x) for x in v]
        if hasattr(v, "tolist"):  # numpy scalars and arrays
            return plain(v.tolist())
        if isinstance(v, float) and not math.isfinite(v):
            return None
        return v

    return json.dumps(plain(doc), indent=indent, allow_nan=False)


def write_json(path, doc) -> Path:
    """Write ``doc`` to ``path`` atomically as strict JSON (:func:`json_text`); returns ``Path(path)``."""
    return write_text(path, json_text(doc))


def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns ``Path(path)``."""
    with atomic_file(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


def partial_dir(path) -> Path:
    """The folder :func:`atomic_dir` assembles ``path`` in: ``<path>.partial``."""
    path = Path(path)
    return path.with_name(path.name + ".partial")


@contextmanager
def atomic_dir(path, force: bool = True, what: str = "output") -> Iterator[Path]:
    """Yield an empty folder ``<path>.partial``; rename it to ``path`` when the block succeeds.

    Parameters
    ----------
    path : str or Path
        The final folder.
    force : bool
        Replace an existing ``path``; False refuses with an :class:`InputError` before any work.
    what : str
        What the folder is, for that message (e.g. ``"bundle"``).

    Yields
    ------
    Path
        The folder to fill; removed with everything in it if the block raises.
    """
    path = Path(path)
    if path.exists() and not force:
        raise InputError(path, f"{what} already exists (use --force to replace it)")
    tmp = partial_dir(path)
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        yield tmp
        old = path.with_name(f".{path.name}.old-{os.getpid()}")
        try:
            with _uninterrupted():
                # the old one renamed aside first: the new one appears in one rename, never half-copied
                if path.exists():
                    os.replace(path, old)
                try:
                    os.replace(tmp, path)
                except OSError:
                    if old.exists():
                        os.replace(old, path)
                    raise
        finally:  # also when Ctrl-C, held during the renames, is raised after them
            shutil.rmtree(old, ignore_errors=True)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


@contextmanager
def _uninterrupted():
    """Hold Ctrl-C (SIGINT) back for the block and deliver it after: between the two renames of
    :func:`atomic_dir` it would leave neither the old folder nor the new one under the name.
    (Python runs signal handlers in the main thread only; elsewhere the block runs as it is.)"""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    caught = []
    previous = signal.signal(signal.SIGINT, lambda *received: caught.append(received))
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        if caught and callable(previous):
            previous(*caught[0])  # Python's default handler raises KeyboardInterrupt
        elif caught and previous == signal.SIG_DFL:
            raise KeyboardInterrupt
