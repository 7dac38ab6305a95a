"""Per-stage GPU timings from OpenGL timer queries (``GL_TIME_ELAPSED``).

Usage::

    timer = GpuTimer(ctx)
    with timer.section("visibility"):
        ...  # draws / dispatches
    timer.ms  # {"visibility": 0.41}, summed over every use of the section
    with timer.section("image_management:histogram"):
        ...  # a part of a stage: counted in ``ms["image_management"]``, alone in ``part_ms``

A *frame* is what is timed between two :meth:`GpuTimer.reset` calls. How its times are read:

* ``wait=True`` (the default: a stopwatch around some work): :attr:`GpuTimer.ms` is this frame's,
  and reading it waits for the GPU to finish the timed work.
* ``wait=False`` (a render loop: the renderers' timers): nothing ever waits. Closed frames stay in
  a ring of pending query sets; :attr:`GpuTimer.ms` is the newest *earlier* frame whose queries the
  GPU has answered, :attr:`GpuTimer.lag` says how many frames back it is (None: none answered
  yet). Waiting for a frame's own queries left the GPU idle between frames: a loop of
  ``Renderer.render(cam, readback=False)`` at 1280x720 ran 1.40-1.53 ms a frame on an H200 with
  them, 0.96 ms with the timer off.
* :attr:`GpuTimer.deferred`: nothing is read until :meth:`GpuTimer.collect`, which reads every
  frame's sections after a run of frames back to back.

A time that was not measured is NaN ("unavailable"), never a number:

* on a software rasterizer (:attr:`GpuTimer.reliable` False) every time: Mesa llvmpipe (CI) times
  only its tile rasterizer, so a compute dispatch reads as 1 ns (``dmrt render`` printed 0.00 ms
  for every stage) and a draw can read as garbage (448 s for a 16.7 s DMT frame, measured);
* a time longer than the wall clock between the section's start and the moment its result was
  read (the GPU cannot have run longer than that): garbage of any driver.

Results are read as 64-bit nanoseconds (``glGetQueryObjectui64v``). moderngl's ``Query.elapsed``
reads 32 bits, which saturates at 2^32 - 1 ns: the "4294.97 ms" that DMT's stages printed on Mesa.
moderngl also cannot ask whether a result is available (``GL_QUERY_RESULT_AVAILABLE``) nor delete a
query, so the queries are made and read through ctypes (:func:`dmrt.gl.mapped.entry_points`).
GL forbids nested ``GL_TIME_ELAPSED`` queries, so sections cannot nest (:class:`RuntimeError`).
"""

from __future__ import annotations

import ctypes
import math
import time
from collections import deque
from contextlib import contextmanager, nullcontext
from functools import lru_cache

import moderngl

from dmrt.gl.context import renderer_info
from dmrt.gl.mapped import entry_points

UNAVAILABLE = math.nan  # a time that was not measured
_TIME_ELAPSED, _QUERY_RESULT, _QUERY_RESULT_AVAILABLE = 0x88BF, 0x8866, 0x8867
# Closed frames whose queries the GPU has not answered, at most: GL drivers queue a few frames, so
# the ring only fills when nothing reads the timer; then the oldest frame is waited for.
MAX_PENDING_FRAMES = 8
# A result may exceed the wall clock that bounds it by clock-rate differences and timer
# granularity only: 1% and 0.1 ms are both far above either.
_WALL_SLACK, _WALL_SLACK_NS = 1.01, 100_000

_u = ctypes.c_uint
_SIGNATURES = {  # name: (result, arguments)
    "glGenQueries": (None, [ctypes.c_int, ctypes.POINTER(_u)]),
    "glDeleteQueries": (None, [ctypes.c_int, ctypes.POINTER(_u)]),
    "glBeginQuery": (None, [_u, _u]),
    "glEndQuery": (None, [_u]),
    "glGetQueryObjectiv": (None, [_u, _u, ctypes.POINTER(ctypes.c_int)]),
    "glGetQueryObjectui64v": (None, [_u, _u, ctypes.POINTER(ctypes.c_uint64)]),
}


@lru_cache(maxsize=None)  # once a process: glvnd's entry points dispatch to the current context
def _gl():
    return entry_points(_SIGNATURES, "timer queries need GL 3.3")


def require_gpu_work(ms: dict, what: str) -> None:
    """Raise if every timed section of a hardware GPU took 0 ns: the context has stopped executing
    commands. Seen on an H200 (NVIDIA 580) after a fault, with no GL error reported, while buffers
    kept returning the last good frame; without this check such frames look like results.

    Parameters
    ----------
    ms : {section: GPU milliseconds} of one frame (:attr:`GpuTimer.ms`); NaN = unavailable.
    what : what was being done, for the message.
    """
    if ms and not any(ms.values()):
        raise RuntimeError(f"the GPU executed none of the work while {what} (every timed section took "
                           f"0 ns): the GL context stopped executing commands and its buffers are stale")


def is_measured(ms) -> bool:
    """True for a number of milliseconds, False for None or NaN (unavailable)."""
    return ms is not None and not math.isnan(ms)


def format_ms(ms) -> str:
    """``"0.41 ms"``, or ``"n/a"`` for a time that was not measured (None or NaN)."""
    return f"{ms:.2f} ms" if is_measured(ms) else "n/a"


def format_timings(timings: dict) -> str:
    """A frame's ``timings`` on one line: ``"visibility 0.41 ms, ..."``, or ``"GPU times
    unavailable"`` when no stage's time was measured (a software rasterizer, the first frame of a
    timer that does not wait; stages that did no work read 0)."""
    if not any(is_measured(v) and v > 0 for v in timings.values()):
        return "GPU times unavailable"
    return ", ".join(f"{k} {format_ms(v)}" for k, v in timings.items())


def stage_sums(part_ms: dict) -> dict[str, float]:
    """``{stage: ms}`` from ``{section: ms}``: a section ``"stage:part"`` counts toward ``stage``."""
    out: dict[str, float] = {}
    for name, v in part_ms.items():
        stage = name.split(":", 1)[0]
        out[stage] = out.get(stage, 0.0) + v
    return out


class GpuTimer:
    """Accumulates GPU milliseconds per stage name (see the module doc for how they are read).

    Parameters
    ----------
    ctx : moderngl.Context (current on this thread)
    wait : bool
        True: :attr:`ms` is this frame's and waits for it. False: :attr:`ms` is the newest earlier
        frame's that is answered, never waiting (:attr:`lag`).

    Attributes
    ----------
    reliable : bool
        False on software rasterizers, whose query results do not measure the work: every time
        reads as unavailable (NaN).
    wait : bool
        As the parameter; may be switched between frames (a benchmark that needs every frame's
        own times sets it on a renderer's timer).
    frame : int
        Frames closed so far (:meth:`reset` calls).
    enabled : bool
        False: sections issue no queries and :attr:`ms` stays empty, so that nothing waits for the
        GPU - frames rendered back to back for a sustained wall-clock time.
    fenced : bool
        True: each section starts and ends with ``glFinish``, so no earlier work finishes inside it.
        Without the fence a section can take in the end of the work issued before it: the stages'
        sum is right, their split only approximate. Fenced frames are slower, and light ones let
        the clocks fall (an H200 at 1425 MHz for 720p frames); for profiling only.
    passes : bool
        True: a stage made of several dispatches times each as a part of its own where it names
        them (the tile lists: ``visibility:lists_clear``, ``_count``, ``_count_large``, ``_scan``,
        ``_scatter``, ``_scatter_large`` in place of ``visibility:tile_lists``). Each section adds
        a little GPU time (~0.01 ms at 1280x720 on an H200); for profiling only.
    deferred : bool
        True: nothing is read until :meth:`collect`; each :meth:`reset` closes a frame, and
        :attr:`ms` stays empty meanwhile. Waiting for each frame's queries leaves the GPU idle
        between frames and its clocks fall; deferred, the stage times are those of frames rendered
        back to back (what a viewer gets).
    """

    def __init__(self, ctx: moderngl.Context, wait: bool = True):
        self.ctx = ctx
        self.reliable = not renderer_info(ctx)["is_software"]
        self.wait = wait
        self.enabled = True
        self.fenced = False
        self.passes = False
        self.deferred = False
        self.frame = 0
        try:
            self._gl = _gl()
        except RuntimeError as exc:
            raise RuntimeError(f"this OpenGL context has no timer queries: {exc}") from exc
        self._free: list[int] = []  # query names to reuse
        self._open: str | None = None
        # this frame: its sections not read yet (name, query, perf_counter at the start), the
        # times read of it (wait=True) and its section uses
        self._current: list[tuple[str, int, float]] = []
        self._ms: dict[str, float] = {}
        self._counts: dict[str, int] = {}
        self._ring: deque[tuple[int, list]] = deque()  # closed frames not answered yet (wait=False)
        self._latest: tuple[int, dict[str, float]] | None = None  # newest answered closed frame
        self._frames: list[list] = []  # deferred frames' sections

    # -- timing -----------------------------------------------------------------------------
    @contextmanager
    def section(self, name: str):
        """Time the GL commands issued inside the ``with`` block under ``name``."""
        if self._open is not None:
            raise RuntimeError(f"GpuTimer sections cannot nest ({name!r} inside {self._open!r})")
        if not self.enabled:
            yield self
            return
        query = self._free.pop() if self._free else self._new_query()
        self._open = name
        if self.fenced:
            self.ctx.finish()
        start = time.perf_counter()
        self._gl.glBeginQuery(_TIME_ELAPSED, query)
        try:
            yield self
        finally:
            if self.fenced:
                self.ctx.finish()
            self._gl.glEndQuery(_TIME_ELAPSED)
            self._open = None
            self._current.append((name, query, start))
            self._counts[name] = self._counts.get(name, 0) + 1

    def reset(self) -> None:
        """Close this frame and start the next: its times are forgotten (wait=True), kept in the
        ring for :attr:`ms` of later frames (wait=False) or for :meth:`collect` (deferred). Never
        waits, unless :data:`MAX_PENDING_FRAMES` frames are unanswered."""
        if self._current:
            (self._frames.append if self.deferred else self._ring.append)((self.frame, self._current))
            self._current = []
        self._ms.clear()
        self._counts.clear()
        self.frame += 1
        self._poll()
        while len(self._ring) > MAX_PENDING_FRAMES:
            self._answer(*self._ring.popleft())

    # -- reading ----------------------------------------------------------------------------
    @property
    def part_ms(self) -> dict[str, float]:
        """``{section name: GPU milliseconds}`` of the frame :attr:`lag` names, parts of stages
        (``"stage:part"``) apart; NaN where not measured; ``{}`` when no frame is answered."""
        if self.deferred:
            return {}
        if self.wait:
            for name, v in self._read(self._current).items():
                self._ms[name] = self._ms.get(name, 0.0) + v
            self._current = []
            return dict(self._ms)
        self._poll()
        return dict(self._latest[1]) if self._latest else {}

    @property
    def ms(self) -> dict[str, float]:
        """``{stage name: accumulated GPU milliseconds}`` (a section ``"stage:part"`` counts toward
        ``stage``) of the frame :attr:`lag` names; see :attr:`part_ms`."""
        return stage_sums(self.part_ms)

    @property
    def lag(self) -> int | None:
        """How many frames before this one the frame of :attr:`ms` is: 0 with ``wait`` (this
        frame's own), 1 or more without; None when no frame's times are available (deferred, or
        none answered yet)."""
        if self.deferred:
            return None
        if self.wait:
            return 0
        self._poll()
        return None if self._latest is None else self.frame - self._latest[0]

    @property
    def counts(self) -> dict[str, int]:
        """``{section name: number of timed uses}`` in this frame (known without the GPU)."""
        return dict(self._counts)

    def frame_timings(self, stages) -> dict:
        """A rendered frame's times, as the renderers' frame dicts carry them.

        Parameters
        ----------
        stages : the renderer's stage names, in order.

        Returns
        -------
        dict
            ``timings`` {stage: GPU ms} (0.0 for a stage that issued no work in the frame timed,
            e.g. leveling when off; NaN where not measured: every stage with work when no frame is
            available, all of them when the timer is off), ``part_timings`` {``stage:part``: GPU
            ms}, ``timings_lag`` (:attr:`lag`: 0 = this frame's own, k = the frame k before, None =
            none).
        """
        lag = self.lag if self.enabled else None
        if lag is None:
            issued = stage_sums(self._counts) if self.enabled else dict.fromkeys(stages)
            return {"timings": {s: UNAVAILABLE if s in issued else 0.0 for s in stages}, "part_timings": {},
                    "timings_lag": None}
        part = self.part_ms
        ms = stage_sums(part)
        return {"timings": {s: ms.get(s, 0.0) for s in stages},
                "part_timings": {k: v for k, v in part.items() if ":" in k}, "timings_lag": lag}

    def check_executed(self, what: str) -> None:
        """:func:`require_gpu_work` on the times of :attr:`ms` (hardware GPUs only: a software
        rasterizer's times do not measure the work)."""
        if self.reliable:
            require_gpu_work(self.ms, what)

    def collect(self) -> list[dict[str, float]]:
        """The sections of every frame timed while :attr:`deferred` (waits for the GPU).

        Returns
        -------
        list of {section name: GPU ms (NaN where not measured)}, one per frame (per
        :meth:`reset`), oldest first.
        """
        if self._current:
            self._frames.append((self.frame, self._current))
            self._current = []
        out = [self._read(sections) for _, sections in self._frames]
        self._frames = []
        if self.reliable:
            for ms in out:
                require_gpu_work(ms, "timing deferred frames")
        return out

    def release(self) -> None:
        """Delete this timer's queries (waiting for the unanswered ones first)."""
        for _, sections in [*self._ring, *self._frames, (0, self._current)]:
            self._read(sections)
        self._ring.clear()
        self._frames, self._current = [], []
        if self._free:
            names = (_u * len(self._free))(*self._free)
            self._gl.glDeleteQueries(len(self._free), names)
            self._free = []

    # -- internals --------------------------------------------------------------------------
    def _new_query(self) -> int:
        name = _u(0)
        self._gl.glGenQueries(1, ctypes.byref(name))
        if not name.value:
            raise RuntimeError("glGenQueries failed: the GL context is lost")
        return name.value

    def _available(self, query: int) -> bool:
        flag = ctypes.c_int(0)
        self._gl.glGetQueryObjectiv(query, _QUERY_RESULT_AVAILABLE, ctypes.byref(flag))
        return bool(flag.value)

    def _read(self, sections) -> dict[str, float]:
        """``{name: ms}`` summed over ``sections`` (waits for each result); their queries are
        freed. A result longer than the wall clock since its section began is not a time."""
        out: dict[str, float] = {}
        ns = ctypes.c_uint64(0)
        for name, query, start in sections:
            self._gl.glGetQueryObjectui64v(query, _QUERY_RESULT, ctypes.byref(ns))
            bound = (time.perf_counter() - start) * 1e9 * _WALL_SLACK + _WALL_SLACK_NS
            ok = self.reliable and ns.value <= bound
            out[name] = out.get(name, 0.0) + (ns.value / 1e6 if ok else UNAVAILABLE)
            self._free.append(query)
        return out

    def _answer(self, frame: int, sections) -> None:
        """Read closed frame ``frame``; it becomes :attr:`ms` if newer than the one there."""
        ms = self._read(sections)
        if self._latest is None or frame > self._latest[0]:
            self._latest = (frame, ms)

    def _poll(self) -> None:
        """Read every closed frame the GPU has answered (no waiting)."""
        pending = deque()
        for frame, sections in self._ring:
            # the last query first: a frame whose end is unanswered needs no more checks
            if self._available(sections[-1][1]) and all(self._available(q) for _, q, _ in sections[:-1]):
                self._answer(frame, sections)
            else:
                pending.append((frame, sections))
        self._ring = pending


def timed(timer: "GpuTimer | None", name: str):
    """``timer.section(name)``, or nothing to time without a timer."""
    return nullcontext() if timer is None else timer.section(name)
