"""Atomic writes: every file and folder the suite writes appears under its final name only when
complete, so an interrupted run never leaves output that looks whole.

A file is written to a hidden temporary file beside it (same suffix, so writers that choose the
format by suffix still work) and renamed over the final name; a folder is assembled in
``<name>.partial`` and renamed into place, an existing one being replaced only when asked.
"""

from __future__ import annotations

import os
import shutil
import tempfile
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


def write_bytes(path, data: bytes) -> Path:
    """Write ``data`` to ``path`` atomically; returns ``Path(path)``."""
    with atomic_file(path) as tmp:
        tmp.write_bytes(data)
    return Path(path)


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
    tmp = path.with_name(path.name + ".partial")
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    try:
        yield tmp
        if path.exists():
            # rename the old one aside first: the new one appears in one rename, never half-copied
            old = path.with_name(f".{path.name}.old-{os.getpid()}")
            os.replace(path, old)
            os.replace(tmp, path)
            shutil.rmtree(old, ignore_errors=True)
        else:
            os.replace(tmp, path)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
