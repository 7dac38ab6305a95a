"""Peak anonymous memory per preprocessing phase: what ``--memory-limit-mb`` governs.

``ru_maxrss`` (and ``/usr/bin/time``'s maximum resident set) also counts the file-backed pages of
memory-mapped arrays - the out-of-core phases write and read normals, radii and octree levels
through ``np.memmap`` - which the kernel drops under memory pressure. The anonymous part
(``RssAnon`` of ``/proc/self/status``, Linux) is the memory the process needs; a thread samples it.
"""

from __future__ import annotations

import threading
from pathlib import Path

_STATUS = Path("/proc/self/status")


def anon_rss_mb() -> float | None:
    """Current anonymous resident memory of this process, MiB (None where /proc has no RssAnon)."""
    try:
        for line in _STATUS.read_text().splitlines():
            if line.startswith("RssAnon:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return None


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
