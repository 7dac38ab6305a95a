"""Per-stage GPU timings from OpenGL timer queries (``GL_TIME_ELAPSED``).

Usage::

    timer = GpuTimer(ctx)
    with timer.section("visibility"):
        ...  # draws / dispatches
    timer.ms  # {"visibility": 0.41}, summed over every use of the section
    with timer.section("image_management:histogram"):
        ...  # a part of a stage: counted in ``ms["image_management"]``, alone in ``part_ms``

Results are read lazily (reading :attr:`ms` waits for the GPU), so timing a frame does not stall it.
With :attr:`GpuTimer.deferred` they are not read per frame at all: frames run back to back with
warm clocks, and :meth:`GpuTimer.collect` reads every frame's sections afterwards.
There is deliberately no CPU-clock fallback: a context without timer queries raises.

Caveats, both measured:

* GL forbids nested ``GL_TIME_ELAPSED`` queries, so sections cannot nest (:class:`RuntimeError`).
* Mesa llvmpipe (CI) answers the queries but records time only in its tile rasterizer: a compute
  dispatch reads as 1 ns and a draw that touches only some tiles can read as garbage (up to the
  saturated 4294.967295 ms). :attr:`reliable` is False there; only GPU runs give real timings.
  moderngl reads the result as a 32-bit count of nanoseconds, so one section use saturates at 4.29 s.
"""

from __future__ import annotations

from contextlib import contextmanager, nullcontext

import moderngl

from dmrt.gl.context import renderer_info


def require_gpu_work(ms: dict, what: str) -> None:
    """Raise if every timed section of a hardware GPU took 0 ns: the context has stopped executing
    commands. Seen on an H200 (NVIDIA 580) after a fault, with no GL error reported, while buffers
    kept returning the last good frame; without this check such frames look like results.

    Parameters
    ----------
    ms : {section: GPU milliseconds} of one frame (:attr:`GpuTimer.ms`).
    what : what was being done, for the message.
    """
    if ms and not any(ms.values()):
        raise RuntimeError(f"the GPU executed none of the work while {what} (every timed section took "
                           f"0 ns): the GL context stopped executing commands and its buffers are stale")


class GpuTimer:
    """Accumulates GPU milliseconds per stage name.

    Parameters
    ----------
    ctx : moderngl.Context

    Attributes
    ----------
    reliable : bool
        False on software rasterizers, whose query results do not measure the work (see module doc).
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

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self.reliable = not renderer_info(ctx)["is_software"]
        self._ms: dict[str, float] = {}
        self._counts: dict[str, int] = {}
        self._pending: list[tuple[str, moderngl.Query]] = []
        self._free: list[moderngl.Query] = []  # moderngl cannot release queries: reuse them
        self._open: str | None = None
        self.enabled = True
        self.fenced = False
        self.passes = False
        self.deferred = False
        self._frames: list[list[tuple[str, moderngl.Query]]] = []  # deferred frames' sections
        try:
            probe = ctx.query(time=True)
        except Exception as exc:
            raise RuntimeError(f"this OpenGL context has no timer queries: {exc}") from exc
        self._free.append(probe)

    @contextmanager
    def section(self, name: str):
        """Time the GL commands issued inside the ``with`` block under ``name``."""
        if self._open is not None:
            raise RuntimeError(f"GpuTimer sections cannot nest ({name!r} inside {self._open!r})")
        if not self.enabled:
            yield self
            return
        query = self._free.pop() if self._free else self.ctx.query(time=True)
        self._open = name
        if self.fenced:
            self.ctx.finish()
        query.mglo.begin()
        try:
            yield self
        finally:
            if self.fenced:
                self.ctx.finish()
            query.mglo.end()
            self._open = None
            self._pending.append((name, query))

    def _resolve(self) -> None:
        if self.deferred:
            return
        for name, query in self._pending:
            ns = query.elapsed  # blocks until the GPU has finished the section
            self._ms[name] = self._ms.get(name, 0.0) + ns / 1e6
            self._counts[name] = self._counts.get(name, 0) + 1
            self._free.append(query)
        self._pending.clear()

    @property
    def ms(self) -> dict[str, float]:
        """``{stage name: accumulated GPU milliseconds}`` (waits for outstanding sections); a
        section ``"stage:part"`` counts toward ``stage``."""
        out: dict[str, float] = {}
        for name, v in self.part_ms.items():
            stage = name.split(":", 1)[0]
            out[stage] = out.get(stage, 0.0) + v
        return out

    @property
    def part_ms(self) -> dict[str, float]:
        """``{section name: accumulated GPU milliseconds}``, parts of stages (``"stage:part"``) apart."""
        self._resolve()
        return dict(self._ms)

    def check_executed(self, what: str) -> None:
        """:func:`require_gpu_work` on the times since :meth:`reset` (hardware GPUs only: a software
        rasterizer's times do not measure the work)."""
        if self.reliable:
            require_gpu_work(self.ms, what)

    @property
    def counts(self) -> dict[str, int]:
        """``{stage name: number of timed uses}``."""
        self._resolve()
        return dict(self._counts)

    def reset(self) -> None:
        """Forget all accumulated times (outstanding queries are waited for and dropped; deferred,
        they are kept as a frame for :meth:`collect`)."""
        if self.deferred and self._pending:
            self._frames.append(self._pending)
            self._pending = []
        self._resolve()
        self._ms.clear()
        self._counts.clear()

    def collect(self) -> list[dict[str, float]]:
        """The sections of every frame timed while :attr:`deferred` (waits for the GPU).

        Returns
        -------
        list of {section name: GPU ms}, one per frame (per :meth:`reset`), oldest first.
        """
        if self._pending:
            self._frames.append(self._pending)
            self._pending = []
        out = []
        for sections in self._frames:
            ms: dict[str, float] = {}
            for name, query in sections:
                ms[name] = ms.get(name, 0.0) + query.elapsed / 1e6
                self._free.append(query)
            out.append(ms)
        self._frames = []
        if self.reliable:
            for ms in out:
                require_gpu_work(ms, "timing deferred frames")
        return out


def timed(timer: "GpuTimer | None", name: str):
    """``timer.section(name)``, or nothing to time without a timer."""
    return nullcontext() if timer is None else timer.section(name)
