"""Depth maps of the dense point cloud seen from each photo's camera (paper Section 4.1).

The point cloud P_HD is rendered from a photo's camera as oriented circular splats (a disc of
radius ``r`` centred at ``p`` with normal ``n``, two-sided) into a float32 map of camera-space z,
``0.0`` where nothing was hit. A pixel's depth is the camera z where its ray (through the pixel
centre) meets a disc's plane within ``r`` of the disc's centre; the nearest such disc wins. Rays
that (almost) lie in a disc's plane (|cos| < 1e-3) take the disc centre's z where they pass within
``r`` of it (``GRAZING_COS`` in ``shaders/splat_depth_common.glsl`` says why).

Two GPU paths produce the same maps (``DepthMapConfig.method``):

``"compute"`` (default)
    One thread per splat, ``atomicMin`` on the float bits of z in a storage buffer; discs larger
    than ``max_thread_pixels`` pixels go to a second pass with one workgroup per disc. The fast path
    on NVIDIA Hopper, whose few raster units make GL_POINTS 10-60x slower (``shared/GPU.md``).
``"raster"``
    The paper's way: GL_POINTS sprites with a per-fragment ray-disc test, z-buffering (24-bit
    log-spaced depth test plus a MIN blend on the float32 colour target, so the stored z is the
    exact minimum); discs too big for a point sprite are drawn as geometry-shader quads.

Neither path cuts large discs: a disc close to the camera covers all of its pixels.
For many photos of one cloud (preprocessing renders one map per photo), use
``DepthMapRenderer.render_many``: it keeps every camera's map on the GPU and splats each batch of
the cloud into all of them as soon as it is uploaded, while threads read, pack and cull the next
batches, so that feeding the GPU and splatting overlap (or, when the maps do not fit its GPU
budget, uploads the cloud once whole or in parts, each splatted into every camera's map of a
group of cameras whose maps fit).

Each camera splats only what its frustum can reach (``DepthMapConfig.cull_points``): every batch is
cut into buckets of consecutive points (never across two input chunks: the octree's levels come
as separate chunks), each with the box of its discs (:class:`~dmrt.preprocess.frustum.Buckets`),
and a camera splats the runs of buckets whose box meets its frustum (found for every camera at
once, on the threads that pack the batch: :class:`_Runs`). The culling is conservative
and nearest-wins is order-free, so the maps are bit-identical to splatting everything; what it
saves is in ``last_stats`` (``splats`` against ``splats_all``). Given the octree's order (Morton
order within each level), a photo that sees one room of a long gallery splats about that room.
The module also reads and writes depth maps as OpenEXR files with one float32 channel ``Z``.
"""

from __future__ import annotations

import collections
import functools
import itertools
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass

import moderngl
import numpy as np

from dmrt.camera import Camera
from dmrt.gl import abi
from dmrt.gl.abi import EMPTY_BITS, EMPTY_Z, SPLAT_FLOATS
from dmrt.gl.kernels import EMPTY_DISPATCH, fill_u32
from dmrt.gl.mapped import MappedBuffer, entry_points
from dmrt.gl.shaders import load_program, set_uniforms
from dmrt.gl.timer import GpuTimer
from dmrt.preprocess.buckets import progress_bar
from dmrt.preprocess.frustum import Buckets


@dataclass
class DepthMapConfig:
    """How depth maps are rendered."""

    # Depth-map width in pixels; the height follows the photo's aspect ratio (rounded). The paper
    # uses 1024 (x 684 for its 3:2 photos).
    width: int = 1024
    # "compute" (atomicMin splatting, fast on every GPU) or "raster" (the paper's GL_POINTS).
    method: str = "compute"
    # Points uploaded to the GPU per batch: 4M points = 112 MB of float32 attributes.
    chunk_points: int = 4_000_000
    # Compute path: a disc whose pixel box exceeds this many pixels is splatted by a whole
    # workgroup instead of one thread, so that one near disc does not stall its warp (16 x 16).
    max_thread_pixels: int = 256
    # Frustum culling: points per bucket whose box is tested against each camera (0: every
    # camera splats every point). Smaller buckets cull closer to the frustum but cost more tests
    # and more dispatches (one per run of visible buckets).
    cull_points: int = 4096
    # Threads that pack the batches, reduce their culling boxes and cull them for every camera,
    # ahead of the uploads (numpy releases the GIL there): one does ~20M points/s for 192 photos
    # (0.047 us/point on a 2-core llvmpipe host); splatting 192 maps ran at ~45M/s on an H200.
    feed_threads: int = 4
    # render_many: where every map fits beside two batches, keep all the maps on the GPU and splat
    # each batch into all of them as soon as it is uploaded ("overlapped": feeding and splatting
    # overlap); False: where the cloud fits, upload it whole first ("resident").
    overlap: bool = True


def depth_map_size(camera: Camera, width: int) -> tuple[int, int]:
    """``(width, height)`` of a depth map ``width`` pixels wide for ``camera``'s aspect ratio."""
    return int(width), max(1, int(round(width * camera.height / camera.width)))


class _Target:
    """One depth map being rendered on the GPU, ``size = (w, h)`` pixels.

    Compute path: ``depth``, a buffer of w x h uints (the float bits of z). Raster path: a float32
    colour texture ``color`` (the exact z, MIN-blended) and a depth texture for the depth test,
    with their framebuffer and a scope that binds it.
    """

    def __init__(self, ctx: moderngl.Context, method: str, w: int, h: int):
        self.size = (w, h)
        if method == "compute":
            self.depth = ctx.buffer(reserve=4 * w * h)
        else:
            self.color = ctx.texture((w, h), 1, dtype="f4")
            self.zbuf = ctx.depth_texture((w, h))
            self.fbo = ctx.framebuffer([self.color], self.zbuf)
            # one scope per target, reused: moderngl only frees scopes on release()
            flags = moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.PROGRAM_POINT_SIZE
            self.scope = ctx.scope(self.fbo, enable_only=flags)

    def release(self) -> None:
        for name in ("scope", "fbo", "depth", "color", "zbuf"):
            obj = self.__dict__.pop(name, None)
            if obj is not None:
                obj.release()


class _Splats:
    """A batch of splats on the GPU: ``count`` rows of 7 float32 in ``buffer`` (the raster path
    also gets its two vertex arrays over the buffer), and the runs of rows each camera of
    :meth:`DepthMapRenderer.render_many` splats (None: all of them)."""

    def __init__(self, renderer: "DepthMapRenderer", buffer: moderngl.Buffer, count: int = 0,
                 runs: "_Runs | None" = None):
        self.buffer, self.count, self.runs = buffer, count, runs
        self.vaos = ()
        if renderer.config.method == "raster":
            layout = [(buffer, "3f 3f 1f", "in_position", "in_normal", "in_radius")]
            self.vaos = tuple(renderer.ctx.vertex_array(p, layout) for p in (renderer._points, renderer._quads))

    def release(self) -> None:
        if self.buffer is not None:
            for obj in (*self.vaos, self.buffer):
                obj.release()
        self.vaos, self.buffer = (), None


class _Runs:
    """The runs of consecutive rows of a batch that each of ``c`` cameras splats (those of the
    buckets whose box meets its frustum): camera ``i``'s runs start at rows
    ``firsts[bounds[i]:bounds[i + 1]]`` and hold ``counts[...]`` rows alike ((c + 1,), (k,), (k,)
    int64)."""

    def __init__(self, bounds: np.ndarray, firsts: np.ndarray, counts: np.ndarray):
        self.bounds, self.firsts, self.counts = bounds, firsts, counts

    @classmethod
    def of(cls, buckets: Buckets | None, rows: int, cameras) -> "_Runs":
        """The runs of a batch of ``rows`` rows cut into ``buckets`` (None: no culling, every
        camera splats every row) for ``cameras`` (at their maps' sizes)."""
        c = len(cameras)
        if buckets is None:
            return cls(np.arange(c + 1), np.zeros(c, np.int64), np.full(c, rows, np.int64))
        visible = buckets.visible_to(cameras, lines=True)  # (c, b)
        # +1 where a run of visible buckets starts, -1 past its end; row-major, so a camera's
        # starts and ends alternate and the cameras come in order
        edges = np.diff(np.pad(visible, ((0, 0), (1, 1))).astype(np.int8), axis=1)
        camera, at = np.nonzero(edges)
        start, stop = at[0::2], at[1::2]  # bucket index ranges [start, stop)
        firsts = buckets.starts[start]
        counts = buckets.starts[stop - 1] + buckets.counts[stop - 1] - firsts
        return cls(np.searchsorted(camera[0::2], np.arange(c + 1)), firsts, counts)

    def __getitem__(self, i: int) -> tuple[np.ndarray, np.ndarray]:
        a, b = self.bounds[i], self.bounds[i + 1]
        return self.firsts[a:b], self.counts[a:b]


IN_FLIGHT = 2
"""Batches the overlapped mode of :meth:`DepthMapRenderer.render_many` may have on the GPU: one
being splatted, the next uploaded."""


class DepthMapRenderer:
    """Renders depth maps from streamed point chunks on one GL context.

    Parameters
    ----------
    ctx : moderngl.Context
        GL 4.3+ context (:func:`dmrt.gl.get_context`).
    config : DepthMapConfig, optional
    timer : GpuTimer, optional
        When given, GPU milliseconds are accumulated under ``"depthmap"`` (splatting),
        ``"depthmap_upload"`` (the copy of each batch to the GPU: 28 MB per million points; for
        :meth:`render`'s rewritten batch the driver runs it on the GPU timeline, 3.5-18 ms per
        million measured on an H200, while :meth:`render_many`'s one-time uploads read ~0 ms there:
        see ``last_stats["upload_s"]``) and ``"depthmap_readback"`` (copying finished maps back,
        ~3 ms for 1024 x 684 on an H200).
        Do not also wrap :meth:`render` or :meth:`render_many` in a section of the same timer:
        sections cannot nest.

    Attributes
    ----------
    last_stats : dict
        Set by :meth:`render_many`: ``mode`` (``"overlapped"``, ``"resident"``, ``"grouped"`` or
        ``"streamed"``), ``groups`` (parts the cloud was uploaded in, over all camera groups;
        overlapped: its batches; streamed: once whole per camera), ``camera_groups`` (groups of
        cameras whose maps were kept on the GPU together, each reading the cloud once),
        ``points`` (points in the cloud; None when streamed), ``upload_s`` / ``readback_s`` (wall
        seconds in uploads, waiting for the feed's batches (read, packed, bucketed and culled on
        its threads) included, and in read-backs, waiting for the GPU to finish the map included),
        ``splat_wait_s`` (overlapped: wall seconds waiting for the GPU to finish a batch before the
        next is uploaded, which bounds the batches on the GPU; 0 otherwise),
        ``splats`` (splats sent to the GPU, summed over the cameras) and ``splats_all`` (what
        splatting every point for every camera would have sent: the culling kept ``splats /
        splats_all``).
    """

    def __init__(self, ctx: moderngl.Context, config: DepthMapConfig | None = None,
                 timer: GpuTimer | None = None):
        self.ctx = ctx
        self.config = config or DepthMapConfig()
        self.timer = timer
        self.last_stats: dict = {}
        if self.config.method not in ("compute", "raster"):
            raise ValueError(f"DepthMapConfig.method must be 'compute' or 'raster', not {self.config.method!r}")
        if self.config.chunk_points < 1 or self.config.width < 1 or self.config.cull_points < 0:
            raise ValueError("DepthMapConfig.width and chunk_points must be positive, cull_points >= 0")
        if self.config.feed_threads < 1:
            raise ValueError("DepthMapConfig.feed_threads must be at least 1")
        if self.config.method == "compute":
            defines = {"MAX_THREAD_PIXELS": int(self.config.max_thread_pixels)}
            self._cs = load_program(ctx, "splat_depth_compute", defines)
            self._cs_large = load_program(ctx, "splat_depth_compute_large")
            self._large = ctx.buffer(reserve=16 + 4 * self.config.chunk_points)
            self._programs = (self._cs, self._cs_large)
        else:
            self._points = load_program(ctx, "splat_depth_raster")
            self._quads = load_program(ctx, "splat_depth_raster_large")
            self._programs = (self._points, self._quads)
            # the implementation's largest sprite (llvmpipe: 255 px; NVIDIA: thousands)
            self.max_point_size = float(ctx.info["GL_POINT_SIZE_RANGE"][1])
        # the batch that render() streams through, rewritten for every batch
        stream = ctx.buffer(reserve=self.config.chunk_points * SPLAT_FLOATS * 4, dynamic=True)
        self._stream = _Splats(self, stream)
        self._targets: dict[int, _Target] = {}  # reusable maps, by slot (render_many alternates two)
        self._camera: Camera | None = None  # the programs' camera, at its map's size (for culling)
        # wall seconds spent and splats sent, ever (last_stats are their differences)
        self._totals = {"upload_s": 0.0, "readback_s": 0.0, "splat_wait_s": 0.0, "splats": 0, "splats_all": 0}

    # -- public -------------------------------------------------------------------------------
    def render(self, camera: Camera, chunks: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> np.ndarray:
        """Splat every chunk into one depth map seen from ``camera``.

        Parameters
        ----------
        camera : Camera
            The photo's camera, already relative to the scene origin; any resolution (it is scaled
            to ``config.width`` x the matching height).
        chunks : iterable of (positions, normals, radii)
            ``positions`` (n, 3) float32, metres, scene-origin-relative; ``normals`` (n, 3) float32
            (any length; zero = face the camera); ``radii`` (n,) float32, metres. Chunks are
            re-cut into GPU batches of ``config.chunk_points``.

        Returns
        -------
        depth : (height, width) float32
            Camera-space z in metres, row 0 at the top of the photo; 0.0 where no disc was hit.
        """
        target = self._begin(camera, self._target(camera, slot=0))
        t0 = time.perf_counter()
        for data, buckets, _ in self._feed(chunks):
            n = len(data)
            if buckets is not None:  # only what this camera can see goes to the GPU
                data = data[buckets.rows(buckets.visible(self._camera, lines=True))]
            self._totals["splats_all"] += n - len(data)  # _splat counts the rest
            if not len(data):
                continue
            with self._timed("depthmap_upload"):
                self._stream.buffer.orphan(self._stream.buffer.size)  # the GPU may still read the last batch
                self._stream.buffer.write(data)
            self._stream.count = len(data)
            self._totals["upload_s"] += time.perf_counter() - t0
            with self._timed("depthmap"):
                self._splat(self._stream, target)
            t0 = time.perf_counter()
        return self._read(target)

    def render_many(self, cameras: Sequence[Camera],
                    chunks_fn: Callable[[], Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]]],
                    resident_mb: float = 4096, progress: bool = False) -> Iterator[tuple[int, np.ndarray]]:
        """Depth maps of many cameras from one point cloud, uploading each point once if possible.

        Equal, bit for bit, to ``render(cameras[i], chunks_fn())`` for every ``i``, in one of
        four ways (:attr:`last_stats` says which ran):

        ``"overlapped"``
            Every camera's map (:meth:`map_bytes`) fits in ``resident_mb`` beside
            :data:`IN_FLIGHT` batches of ``config.chunk_points`` (and ``config.overlap``): the maps
            stay on the GPU, and each batch is splatted into all of them as soon as it is
            uploaded, while the feed's threads prepare the next ones; the GPU holds at most
            :data:`IN_FLIGHT` batches (the upload of one waits for the splats of the one
            :data:`IN_FLIGHT` before). The cloud is read once; the maps are read back at the end.
        ``"resident"``
            The cloud (28 bytes per point) fits in ``resident_mb``: it is uploaded once, then
            splatted for each camera in turn.
        ``"grouped"``
            It does not, but one depth map (4 bytes per pixel compute, 8 raster: :meth:`map_bytes`)
            plus one batch of ``config.chunk_points`` do. The cameras are cut into consecutive
            groups whose maps fit beside one batch (one group when all of them do); a group's
            maps stay on the GPU while the cloud is uploaded in parts of what is left of the
            budget, each part splatted into every map of the group; the maps are read back at
            the end of the group. The cloud is read once per group: the first attempt at
            ``"resident"`` uploaded a part already, which the first group keeps as far as it fits
            beside its maps (``chunks_fn()`` is iterated once more, skipping that part), and each
            further group iterates ``chunks_fn()`` again.
        ``"streamed"``
            Not even one map and a batch fit: :meth:`render` per camera (``chunks_fn()`` once per
            camera).

        Parameters
        ----------
        cameras : sequence of Camera
            As :meth:`render` takes them; sizes may differ.
        chunks_fn : callable
            Returns a fresh iterator over the same (positions, normals, radii) chunks each call,
            as :meth:`render` takes them.
        resident_mb : float
            GPU memory, in MiB, that point batches and kept depth maps may take together.
        progress : bool
            A tqdm bar over the maps.

        Yields
        ------
        index : int
            ``i`` of ``cameras[i]``, in order.
        depth : (height, width) float32
            Its depth map, as :meth:`render` returns it; the caller may keep or drop it.
        """
        cameras = list(cameras)
        budget = float(resident_mb) * 2**20
        stats = self.last_stats = {"mode": None, "groups": 0, "camera_groups": 0, "points": None}
        bar = progress_bar(len(cameras), "depth maps", progress, unit="map")
        totals = dict(self._totals)
        batch = self.config.chunk_points * SPLAT_FLOATS * 4
        sizes = [self.map_bytes(c) for c in cameras]
        try:
            if self.config.overlap and cameras and sum(sizes) + IN_FLIGHT * batch <= budget:
                stats.update(mode="overlapped", camera_groups=1, points=0)
                yield from self._render_overlapped(cameras, self._feed(chunks_fn(), cameras), bar)
                return
            # try to upload the whole cloud, stopping before the batch that would exceed the budget
            group, pending = self._upload_until(self._feed(chunks_fn(), cameras), budget)
            if pending is None:
                stats.update(mode="resident", groups=1, camera_groups=1, points=sum(s.count for s in group))
                yield from self._render_resident(cameras, group, bar)
                return
            if max(sizes, default=0) + batch > budget:
                _release(group)
                stats.update(mode="streamed", groups=len(cameras), camera_groups=len(cameras))
                for i, camera in enumerate(cameras):
                    yield i, self.render(camera, chunks_fn())
                    bar.update()
                return
            stats["mode"] = "grouped"
            for first, stop in _camera_groups(sizes, budget - batch):
                room = budget - sum(sizes[first:stop])  # left for points beside the group's maps
                if first == 0:  # keep the part of the first upload that fits, re-read the rest
                    keep, used = 0, 0
                    while keep < len(group) and used + group[keep].buffer.size <= room:
                        used += group[keep].buffer.size
                        keep += 1
                    _release(group[keep:])
                    group = group[:keep]
                    rest = itertools.islice(self._feed(chunks_fn(), cameras), keep, None)
                else:
                    group, rest = [], self._feed(chunks_fn(), cameras)
                stats["camera_groups"] += 1
                stats["points"] = 0  # counted again by each group: the cloud's points
                yield from self._render_grouped(cameras, range(first, stop), group, rest, room, bar)
        finally:
            stats.update({k: self._totals[k] - totals[k] for k in totals})
            bar.close()

    def map_bytes(self, camera: Camera) -> int:
        """GPU bytes of one depth map being rendered for ``camera`` (4 per pixel compute, 8 raster)."""
        w, h = depth_map_size(camera, self.config.width)
        return w * h * (4 if self.config.method == "compute" else 8)

    def release(self) -> None:
        """Free this renderer's GPU buffers (the cached programs stay with the context)."""
        _release(self._targets.values())
        self._targets.clear()
        for name in ("_stream", "_large"):
            obj = self.__dict__.pop(name, None)
            if obj is not None:
                obj.release()

    # -- render_many's strategies -------------------------------------------------------------
    def _render_overlapped(self, cameras, batches, bar):
        """The "overlapped" mode: every map of ``cameras`` kept on the GPU, each of ``batches``
        (:meth:`_feed`'s) splatted into all of them right after its upload."""
        stats = self.last_stats
        targets = [self._begin(c, _Target(self.ctx, self.config.method, *depth_map_size(c, self.config.width)))
                   for c in cameras]
        # one fence per batch on the GPU: the upload of a batch waits for the splats of the batch
        # IN_FLIGHT before (a released buffer's memory stays taken until the GPU is done with it)
        fences = [MappedBuffer(self.ctx, bytes(4)) for _ in range(IN_FLIGHT)]
        try:
            t0 = time.perf_counter()
            for k, (data, _, runs) in enumerate(batches):
                t1 = time.perf_counter()
                fences[k % IN_FLIGHT].read(0)
                t2 = time.perf_counter()
                with self._timed("depthmap_upload"):
                    splats = _Splats(self, self.ctx.buffer(data), len(data), runs)
                self._totals["upload_s"] += (t1 - t0) + (time.perf_counter() - t2)
                self._totals["splat_wait_s"] += t2 - t1
                stats["groups"] += 1
                stats["points"] += splats.count
                with self._timed("depthmap"):
                    for i, (camera, target) in enumerate(zip(cameras, targets)):
                        self._set_camera(camera)
                        self._splat(splats, target, i)
                splats.release()
                fences[k % IN_FLIGHT].written()
                # sent to the GPU now: else they may wait in the driver's queue while the CPU
                # waits for the feed, until the next fence wait flushes them
                _gl_flush()
                t0 = time.perf_counter()
            self._totals["upload_s"] += time.perf_counter() - t0  # the wait for the feed's end
            for i, target in enumerate(targets):
                yield i, self._read(target)
                target.release()  # the maps' memory goes as they go
                bar.update()
        finally:
            batches.close()  # the feed's threads end here, not when the generator is collected
            _release(targets)
            _release(fences)

    def _render_resident(self, cameras, splats, bar):
        # Two maps alternate: camera i is splatted while camera i - 1 is read back (and handed to
        # the caller, who may write it to disk) so that the GPU has work during both. A moderngl
        # read waits for everything queued, camera i's splats too; the compute path's maps are
        # therefore copied on the GPU into mapped host memory, and the read waits for that copy only.
        mapped = None
        if self.config.method == "compute":
            size = max(4 * w * h for w, h in (depth_map_size(c, self.config.width) for c in cameras))
            mapped = [MappedBuffer(self.ctx, bytes(size)) for _ in range(2)]
        try:
            previous = None
            for i, camera in enumerate(cameras):
                target = self._begin(camera, self._target(camera, slot=i % 2))
                with self._timed("depthmap"):
                    for s in splats:
                        self._splat(s, target, i)
                host = None
                if mapped is not None:
                    host = mapped[i % 2]
                    with self._timed("depthmap_readback"):
                        host.copy_from(target.depth, target.depth.size)
                if previous is not None:
                    yield previous[0], self._read(*previous[1:])
                    bar.update()
                previous = (i, target, host)
            if previous is not None:
                yield previous[0], self._read(*previous[1:])
                bar.update()
        finally:
            _release(splats)
            _release(mapped or [])

    def _render_grouped(self, cameras, group_of, group, rest, room, bar):
        """One camera group of the "grouped" mode: ``cameras[i]`` for ``i`` in ``group_of`` (a
        range) of :meth:`render_many`'s ``cameras``; ``group`` the part of the cloud already
        uploaded, ``rest`` the batches still to upload in parts within ``room`` bytes."""
        stats = self.last_stats
        targets = [_Target(self.ctx, self.config.method, *depth_map_size(cameras[i], self.config.width))
                   for i in group_of]
        try:
            for i, target in zip(group_of, targets):
                self._begin(cameras[i], target)
            pending = next(rest, None)
            while True:
                stats["groups"] += 1
                stats["points"] += sum(s.count for s in group)
                for i, target in zip(group_of, targets):
                    self._set_camera(cameras[i])
                    with self._timed("depthmap"):
                        for s in group:
                            self._splat(s, target, i)
                _release(group)
                if pending is None:
                    break
                group, pending = self._upload_until(itertools.chain([pending], rest), room)
            for i, target in zip(group_of, targets):
                yield i, self._read(target)
                target.release()  # the maps' memory goes as they go
                bar.update()
        finally:
            _release(group)
            _release(targets)

    def _upload_until(self, batches, budget: float) -> tuple[list[_Splats], tuple | None]:
        """Upload batches (:meth:`_feed`'s) while their bytes stay within ``budget``.

        Returns the uploaded batches and the first batch that did not fit (None when none is left).
        """
        group, used = [], 0
        t0 = time.perf_counter()
        try:
            for data, buckets, runs in batches:
                if used + data.nbytes > budget:
                    return group, (data, buckets, runs)
                with self._timed("depthmap_upload"):
                    group.append(_Splats(self, self.ctx.buffer(data), len(data), runs))
                used += data.nbytes
            return group, None
        finally:
            self._totals["upload_s"] += time.perf_counter() - t0

    # -- internals ----------------------------------------------------------------------------
    def _target(self, camera: Camera, slot: int) -> _Target:
        """The reusable map of ``slot``, (re)made at ``camera``'s size."""
        size = depth_map_size(camera, self.config.width)
        target = self._targets.get(slot)
        if target is None or target.size != size:
            if target is not None:
                target.release()
            target = self._targets[slot] = _Target(self.ctx, self.config.method, *size)
        return target

    def _feed(self, chunks, cameras: Sequence[Camera] | None = None
              ) -> Iterator[tuple[np.ndarray, Buckets | None, _Runs | None]]:
        """The GPU batches of ``chunks`` with their culling buckets and, given ``cameras``, the
        runs each of them splats (:func:`_batches`), produced on the feed's threads."""
        maps = None if cameras is None else [c.scaled(*depth_map_size(c, self.config.width)) for c in cameras]
        return _batches(chunks, self.config.chunk_points, self.config.cull_points, maps, self.config.feed_threads)

    def _set_camera(self, camera: Camera) -> None:
        w, h = depth_map_size(camera, self.config.width)
        cam = self._camera = camera.scaled(w, h)
        for program in self._programs:
            set_uniforms(program, u_R=cam.R.T.ravel(), u_t=cam.t, u_size=(w, h),
                         u_K=(cam.fx, cam.fy, cam.cx, cam.cy))

    def _begin(self, camera: Camera, target: _Target) -> _Target:
        """Point the programs at ``camera`` and clear ``target``."""
        self._set_camera(camera)
        w, h = target.size
        if self.config.method == "compute":
            fill_u32(self.ctx, target.depth, EMPTY_BITS, w * h)
            self.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)
        else:
            target.fbo.clear(EMPTY_Z, 0.0, 0.0, 0.0, depth=1.0)
        return target

    def _timed(self, name: str):
        return self.timer.section(name) if self.timer is not None else nullcontext()

    def _splat(self, splats: _Splats, target: _Target, camera: int = 0) -> None:
        """Splat the runs of ``splats`` that the current camera (``splats.runs[camera]``) can see
        into ``target``."""
        if splats.count == 0:
            return
        if splats.runs is None:
            firsts, counts = np.zeros(1, np.int64), np.array([splats.count])
        else:
            firsts, counts = splats.runs[camera]
        self._totals["splats"] += int(counts.sum())
        self._totals["splats_all"] += splats.count
        if not len(firsts):
            return
        runs = list(zip(firsts.tolist(), counts.tolist()))
        if self.config.method == "compute":
            self._splat_compute(splats, target, runs)
        else:
            self._splat_raster(splats, target, runs)

    def _splat_compute(self, splats: _Splats, target: _Target, runs) -> None:
        self._large.write(EMPTY_DISPATCH)  # empty large-disc list
        splats.buffer.bind_to_storage_buffer(abi.B_SPLATS)
        target.depth.bind_to_storage_buffer(abi.B_DEPTH_BITS)
        self._large.bind_to_storage_buffer(abi.B_DEPTH_LARGE)
        # the runs' first passes only add atomically (to the map, to the list): no barrier between
        for first, n in runs:
            set_uniforms(self._cs, u_first=first, u_count=n)
            self._cs.run(min(-(-n // 64), 65535))
        # pass 2 reads the list, and its dispatch the list's group count
        self.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT)
        self._cs_large.run_indirect(self._large)
        self.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)  # the next batch's atomics

    def _splat_raster(self, splats: _Splats, target: _Target, runs) -> None:
        ctx = self.ctx
        set_uniforms(self._points, u_max_point_size=self.max_point_size)
        set_uniforms(self._quads, u_max_point_size=self.max_point_size)
        with target.scope:  # binds the target and the flags, restores the caller's on exit
            # LEQUAL lets depth-key ties (1.4e-6 relative) through to the MIN blend, which keeps
            # the exact nearest float32 z
            ctx.depth_func, ctx.blend_equation = "<=", moderngl.MIN
            try:
                for first, n in runs:
                    for vao in splats.vaos:
                        vao.render(moderngl.POINTS, vertices=n, first=first)
            finally:
                # moderngl cannot read these back: restore its defaults
                ctx.depth_func, ctx.blend_equation = "<", moderngl.FUNC_ADD

    def _read(self, target: _Target, host: MappedBuffer | None = None) -> np.ndarray:
        """Copy a finished map back: (h, w) float32 camera z, 0.0 where empty. ``host``: the
        mapped buffer the compute path's map was copied into (:meth:`_render_resident`)."""
        w, h = target.size
        t0 = time.perf_counter()
        if host is not None:  # the copy was timed when issued
            bits = np.frombuffer(host.read(4 * w * h), np.uint32).reshape(h, w).copy()
            depth = bits.view(np.float32)
            depth[bits == EMPTY_BITS] = 0.0
            self._totals["readback_s"] += time.perf_counter() - t0
            return depth
        with self._timed("depthmap_readback"):
            if self.config.method == "compute":
                self.ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT)
                bits = np.empty((h, w), dtype=np.uint32)
                target.depth.read_into(bits)
                depth = bits.view(np.float32)
                depth[bits == EMPTY_BITS] = 0.0
            else:
                # row 0 of the texture is image row 0 (Camera.gl_view_projection's unflipped clip y)
                depth = np.empty((h, w), dtype=np.float32)
                target.color.read_into(depth)
                depth[depth >= EMPTY_Z] = 0.0
        self._totals["readback_s"] += time.perf_counter() - t0
        return depth


def _gl_flush() -> None:
    """``glFlush`` (moderngl has none): the GL commands issued so far start on the GPU."""
    _gl().glFlush()


@functools.lru_cache(maxsize=None)  # once a process: glvnd's entry points dispatch to the current context
def _gl():
    return entry_points({"glFlush": (None, [])}, "glFlush")


def _release(objects) -> None:
    for obj in objects:
        obj.release()


def _batches(chunks, size: int, cull: int = 0, cameras=None, threads: int = 1,
             ) -> Iterator[tuple[np.ndarray, Buckets | None, "_Runs | None"]]:
    """Interleave (positions, normals, radii) chunks into (m, 7) float32 rows (position, normal,
    radius), in batches of exactly ``size`` rows (the last one: fewer) whatever the chunks' sizes.
    Each value is copied once, straight into its batch. Yields ``(rows, buckets, runs)``: the
    batch's culling buckets of ``cull`` rows, also cut where a chunk begins inside the batch (None
    when ``cull`` is 0), and the runs of rows each of ``cameras`` (at their maps' sizes) splats
    (:class:`_Runs`; None without cameras). Batches are packed on ``threads`` threads
    (:func:`ordered_map`), in order."""
    work = functools.partial(_packed, cull=cull, cameras=cameras)
    return ordered_map(work, _plans(chunks, size), threads)


def _plans(chunks, size: int) -> Iterator[list[tuple[int, np.ndarray, np.ndarray, np.ndarray]]]:
    """Each batch of :func:`_batches` as its pieces ``(first row, positions, normals, radii)``:
    views of the chunks, nothing copied yet."""
    pieces, n = [], 0
    for chunk in chunks:
        positions, normals, radii = _checked(*chunk)
        start, m = 0, len(positions)
        while start < m:
            take = min(m - start, size - n)
            part = slice(start, start + take)
            pieces.append((n, positions[part], normals[part], radii[part]))
            n, start = n + take, start + take
            if n == size:
                yield pieces
                pieces, n = [], 0
    if n:
        yield pieces


def _packed(pieces, cull: int, cameras) -> tuple[np.ndarray, Buckets | None, "_Runs | None"]:
    """One batch of :func:`_batches` from its :func:`_plans` pieces."""
    first, positions, _, _ = pieces[-1]
    batch = np.empty((first + len(positions), SPLAT_FLOATS), np.float32)
    bucketed = []
    for first, positions, normals, radii in pieces:
        rows = batch[first:first + len(positions)]
        _pack(rows, positions, normals, radii)
        if cull:
            bucketed.append(_piece_buckets(rows, positions, radii, first, cull))
    buckets = _joined(bucketed, cull)
    return batch, buckets, None if cameras is None else _Runs.of(buckets, len(batch), cameras)


def ordered_map(fn: Callable, items: Iterable, threads: int, ahead: int | None = None) -> Iterator:
    """``fn(item)`` for each of ``items``, in order, computed on ``threads`` threads (1 or less:
    here, one by one) at most ``ahead`` items (default ``threads + 1``) ahead of the consumer: for
    work that releases the GIL (numpy copies and reductions, file reads). ``items`` is advanced
    here, on the consumer's thread; it is closed, and the threads shut down, when the consumer is
    done, fails or drops this generator early."""
    try:
        if threads <= 1:
            for item in items:
                yield fn(item)
            return
        ahead = threads + 1 if ahead is None else max(1, ahead)
        pending: collections.deque = collections.deque()
        with ThreadPoolExecutor(threads, thread_name_prefix="dmrt-feed") as pool:
            try:
                for item in items:
                    pending.append(pool.submit(fn, item))
                    if len(pending) >= ahead:
                        yield pending.popleft().result()  # a failure raises here
                while pending:
                    yield pending.popleft().result()
            finally:
                for f in pending:
                    f.cancel()
    finally:
        close = getattr(items, "close", None)
        if close is not None:
            close()


def _pack(rows: np.ndarray, positions, normals, radii) -> None:
    """Copy a chunk piece into ``rows`` ((m, 7) float32 of a batch), cast to float32. Contiguous
    float32 arrays are copied as 12- and 4-byte items, one per row: the same bytes, 1.3-1.5x
    faster than float by float (15-18 against 20-27 ms per million rows on a 2-core llvmpipe host)."""
    for (a, b), x in zip(((0, 3), (3, 6), (6, 7)), (positions, normals, radii)):
        if x.dtype == np.float32 and x.flags.c_contiguous:
            item = np.dtype((np.void, 4 * (b - a)))
            rows.view(np.uint8)[:, 4 * a:4 * b].view(item)[:, 0] = x.view(item).reshape(-1)
        else:
            rows[:, a:b] = x.reshape(len(x), b - a)


def _piece_buckets(rows: np.ndarray, positions, radii, first: int, cull: int) -> Buckets:
    """The buckets of a chunk's ``rows`` (its piece ``positions``, ``radii`` packed at row
    ``first`` of a batch), cut at the batch's multiples of ``cull``: :meth:`Buckets.of` of the whole
    batch's rows, cut also at ``first``, has these buckets. The boxes are reduced over the chunk's
    own (contiguous) arrays where they are float32 already, 2.5x faster than over the batch's
    28-byte rows (the same values: min and max are exact); else over the rows (the float32 values
    splatted)."""
    if positions.dtype != np.float32 or radii.dtype != np.float32:
        positions, radii = rows[:, 0:3], rows[:, 6]
    m = len(rows)
    cuts = np.arange(-(-first // cull) * cull, first + m, cull, dtype=np.int64) - first
    piece = Buckets.of(positions, radii, m, cuts[cuts > 0])  # size m: cut only at `cuts`
    piece.starts += first
    return piece


def _joined(pieces: list[Buckets], cull: int) -> Buckets | None:
    """One batch's buckets from its pieces' (:func:`_piece_buckets`), in row order."""
    if not cull:
        return None
    return Buckets(*(np.concatenate([getattr(b, k) for b in pieces]) for k in ("starts", "counts", "lo", "hi")))


def _camera_groups(sizes: list[int], room: float) -> Iterator[tuple[int, int]]:
    """Consecutive ``[first, stop)`` ranges of maps of ``sizes`` bytes, each within ``room``
    bytes (every single map fits)."""
    first, used = 0, 0
    for i, size in enumerate(sizes):
        if used + size > room:
            yield first, i
            first, used = i, 0
        used += size
    if first < len(sizes):
        yield first, len(sizes)


def _checked(positions, normals, radii):
    """One chunk's arrays, shapes checked (values are cast to float32 as they are packed)."""
    positions, normals, radii = np.asarray(positions), np.asarray(normals), np.asarray(radii)
    n = len(positions)
    if positions.shape != (n, 3) or normals.shape != (n, 3) or radii.shape != (n,):
        raise ValueError(f"a depth-map chunk needs positions (n, 3), normals (n, 3), radii (n,); got "
                         f"{positions.shape}, {normals.shape}, {radii.shape}")
    return positions, normals, radii


# -- OpenEXR ----------------------------------------------------------------------------------
