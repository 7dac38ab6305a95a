"""Resources per preprocessing phase: peak anonymous memory (what ``--memory-limit-mb`` governs)
and CPU seconds, both of this process and its worker processes together.

``ru_maxrss`` (and ``/usr/bin/time``'s maximum resident set) also counts the file-backed pages of
memory-mapped arrays - the out-of-core phases write and read normals, radii and octree levels
through ``np.memmap`` - which the kernel drops under memory pressure. The anonymous part
(``RssAnon`` of ``/proc/<pid>/status``, Linux) is the memory the process needs; a thread samples it,
summed with that of the local worker processes (:class:`dmrt.preprocess.parallel.ProcessPool`),
which share the machine's memory.
"""

from __future__ import annotations

import multiprocessing
import os
import threading
from pathlib import Path


def _own_anon_mb(pid: int | str = "self") -> float | None:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) / 1024
    except OSError:  # no /proc, or the child has just exited
        pass
    return None


def anon_rss_mb() -> float | None:
    """Current anonymous resident memory of this process and its live multiprocessing children,
    MiB (None where /proc has no RssAnon)."""
    own = _own_anon_mb()
    if own is None:
        return None
    return own + sum(_own_anon_mb(c.pid) or 0.0 for c in multiprocessing.active_children())


def cpu_seconds() -> float:
    """User + system CPU seconds of this process, its finished children and its live
    multiprocessing children (whose time the kernel adds to ours only when they are reaped)."""
    t = os.times()
    total = t.user + t.system + t.children_user + t.children_system
    tick = os.sysconf("SC_CLK_TCK") if hasattr(os, "sysconf") else 100
    for c in multiprocessing.active_children():
        try:
            fields = Path(f"/proc/{c.pid}/stat").read_text().rsplit(")", 1)[1].split()
            total += (int(fields[11]) + int(fields[12])) / tick  # utime, stime (fields 14, 15)
        except (OSError, IndexError, ValueError):
            pass
    return total


class AnonPeak:
    """Samples :func:`anon_rss_mb` every ``interval`` seconds on a daemon thread while running;
    :meth:`take` returns the peak since the previous :meth:`take` (None without /proc)."""

    def __init__(self, interval: float = 0.05):
        self.interval = interval
        self._peak = anon_rss_mb()
        self._lock = threading.Lock()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="dmrt-anon-rss", daemon=True)

    def _sample(self) -> None:
        now = anon_rss_mb()
        if now is not None:
            with self._lock:
                self._peak = max(self._peak or 0.0, now)

    def _run(self) -> None:
        while not self._stop.wait(self.interval):
            self._sample()

    def __enter__(self) -> "AnonPeak":
        if self._peak is not None:
            self._thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self._stop.set()

    def take(self) -> float | None:
        self._sample()
        with self._lock:
            peak, self._peak = self._peak, anon_rss_mb()
        return None if peak is None else round(peak, 1)
