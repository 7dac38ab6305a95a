"""Preprocessing (paper Section 4): scene -> scene bundle.

Phases, each with a progress bar and, in ``bundle.json``, a wall-clock timing and the bytes the run
then holds on disk (``disk_bytes_after``; hard links to the scene's photos left out):

1. **octree** — P_HD into nested levels of detail, out of core (:mod:`dmrt.preprocess.octree`);
2. **normals/radii** — normals by plane fit where the input has none, oriented toward the nearest
   photo camera; splat radii from the local density (:mod:`dmrt.preprocess.normals`), out of core;
   nothing on the scan path, whose radii and normals the octree carries (its work files are
   deleted once the octree is built: ``docs/scene3.md``);
3. **depth maps** — P_HD splatted as oriented discs from every photo's camera (:mod:`dmrt.preprocess.depthmaps`;
   :func:`render_depth_phase`: here, or on Dask each GPU worker its share, the maps merged exactly);
4. **proxies** — P_LD = the k coarsest octree levels, with radii from their own density;
5. **candidates** — the photos that see each proxy: inside the frame, in front, not grazing, and
   not occluded according to that photo's depth map;
6. **labeling** — one photo per proxy by alpha-expansion (:mod:`dmrt.preprocess.labeling`); then
   one colour gain per photo from the proxies the photos share (:mod:`dmrt.preprocess.photometric`);
7. **bundle** — written atomically (:mod:`dmrt.io.bundle`) with low-resolution photo copies.
"""

from __future__ import annotations

import collections
import functools
import os
import resource
import shlex
import shutil
import stat
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, replace
from pathlib import Path
from typing import Iterator

import numpy as np
from tqdm import tqdm

from dmrt.io.bundle import BundleWriter, camera_to_json
from dmrt.io.exr import read_depth_exr, write_depth_exr
from dmrt.preprocess.config import PreprocessConfig
from dmrt.preprocess.memory import AnonPeak, cpu_seconds
from dmrt.preprocess.labeling import LabelingConfig
from dmrt.preprocess.knn import kernel as knn_kernel
from dmrt.preprocess.parallel import InProcess, check_gpu_worker, default_workers
from dmrt.preprocess.photometric import solve_for_proxies
from dmrt.preprocess.proxies import choose_proxy_levels, label_proxies
from dmrt.preprocess.registration import coverage_summary
from dmrt.preprocess.scangrid import scan_phase
from dmrt.io.scene import Scene, cloud_extent, load_scene


def _new_bytes(folder) -> int:
    """Bytes of the files under ``folder`` that take disk of their own: hard links (the photos
    linked from the scene) share their data with the scene's files, and are left out."""
    sizes = (f.lstat() for f in Path(folder).rglob("*"))
    return sum(st.st_size for st in sizes if stat.S_ISREG(st.st_mode) and st.st_nlink == 1)


def _gl_renderer_string() -> str:
    from dmrt.gl import get_context, renderer_info

    info = renderer_info(get_context())
    return f"{info['renderer']} ({info['version']})"


class _DepthFiles:
    """``j -> (h, w) float32``: photo ``j``'s depth map, read from ``folder / rels[j]`` (picklable,
    for Dask tasks)."""

    def __init__(self, folder, rels):
        self.folder, self.rels = Path(folder), list(rels)

    def __call__(self, j: int) -> np.ndarray:
        return read_depth_exr(self.folder / self.rels[j])


class _LocalPoints:
    """The scene's points relative to its origin, as octree input chunks ``(positions (n, 3)
    float64 metres, {"normals", "colors"})``; picklable, and split into record ranges as its
    :class:`~dmrt.io.pointcloud.PointRange` splits, so worker processes read the input in parallel."""

    def __init__(self, source, origin):
        self.source, self.origin = source, origin

    def __call__(self):
        for pc in self.source():
            yield pc.positions - self.origin, {"normals": pc.normals, "colors": pc.colors}

    def split(self, parts: int) -> list["_LocalPoints"]:
        return [_LocalPoints(s, self.origin) for s in self.source.split(parts)]


class _Photos:
    """``j -> (H, W, 3) uint8``: photo ``j`` of ``scene``, the last one kept (192 full photos need
    not sit in RAM); picklable, for Dask tasks."""

    def __init__(self, scene: Scene):
        self.scene, self._cache = scene, {}

    def __call__(self, j: int) -> np.ndarray:
        cache = self._cache  # replaced whole, never changed in place: safe from several threads
        if j not in cache:
            cache = self._cache = {j: self.scene.read_image(j)}
        return cache[j]

    def __getstate__(self):
        return {"scene": self.scene, "_cache": {}}


_END = object()  # what the read-ahead thread hands over past the last chunk


def _read_ahead(items: Iterator, depth: int = 2) -> Iterator:
    """The items of the iterator ``items``, each taken ``depth`` ahead on a background thread while
    the consumer works on the ones before: reading the next chunk (file reads release the GIL)
    overlaps packing and uploading this one. One thread advances ``items``; it is shut down, and
    ``items`` closed, when the consumer is done, fails or drops this generator early."""
    pool = ThreadPoolExecutor(1, thread_name_prefix="dmrt-read-ahead")
    ahead: collections.deque = collections.deque()
    try:
        while True:
            while len(ahead) < depth:
                ahead.append(pool.submit(next, items, _END))
            item = ahead.popleft().result()  # a failed read raises here
            if item is _END:
                return
            yield item
    finally:
        for f in ahead:
            f.cancel()
        pool.shutdown(wait=True)  # the read under way, if any, ends before `items` is closed
        close = getattr(items, "close", None)
        if close is not None:
            close()


def _float32(a) -> np.ndarray:
    """``a`` as contiguous float32 in memory: a memory-mapped slice is copied, so that its pages
    are read here (on the read-ahead thread), not where the chunk is packed."""
    return np.array(a, np.float32) if isinstance(a, np.memmap) else np.ascontiguousarray(a, np.float32)


def _depth_renderer(work, ranges, has_normals: bool, config: PreprocessConfig):
    """This process's depth-map renderer and the chunk source of P_HD's points in ``ranges`` (a
    list of :class:`~dmrt.preprocess.octree.OctreeRange`, read in turn) with their normals and
    radii: the octree's own where it carries them (the scan path: :func:`normals_radii_phase`),
    else ``work/attrs``'s; each call of the source reads its chunks two ahead of the consumer
    (:func:`_read_ahead`), and the renderer packs, buckets and culls its GPU batches on its feed
    threads ahead of its uploads, so that reading, packing and uploading (and, in its overlapped
    mode, splatting) overlap."""
    from dmrt.gl import GpuTimer, get_context
    from dmrt.preprocess.depthmaps import DepthMapConfig, DepthMapRenderer

    check_gpu_worker()
    normals = None if has_normals else np.load(Path(work) / "attrs" / "normals.npy", mmap_mode="r")
    carried = any("radii" in points.fields for points in ranges)
    radii = None if carried else np.load(Path(work) / "attrs" / "radii.npy", mmap_mode="r")
    # only the fields splatted are read (not the colours: 3 of every 15 bytes of a coloured scan)
    wanted = {"positions", *(["normals"] if has_normals else []), *(["radii"] if carried else [])}
    ranges = [replace(points, fields={k: v for k, v in points.fields.items() if k in wanted}) for points in ranges]

    def read():
        for points in ranges:
            g = points.start  # the attributes are indexed in octree order, as the range
            for ch in points():
                m = len(ch["positions"])
                nrm = ch["normals"] if has_normals else normals[g:g + m]
                rad = ch["radii"] if carried else radii[g:g + m]
                yield _float32(ch["positions"]), _float32(nrm), _float32(rad)
                g += m

    def hd_chunks():  # a fresh reader (and thread) per call: render_many may read the cloud twice
        return _read_ahead(read())

    ctx = get_context()
    timer = GpuTimer(ctx)
    # GPU batches of one read chunk: on a CPU renderer (llvmpipe) GPU buffers are host memory
    renderer = DepthMapRenderer(ctx, DepthMapConfig(width=config.depthmap_width, method=config.depthmap_method,
                                                    chunk_points=config.chunk_points,
                                                    cull_points=config.cull_points), timer=timer)
    return renderer, hd_chunks, timer


def render_depth_maps(cameras, names, work, out_dir, has_normals: bool, config: PreprocessConfig,
                      progress: bool = False, wall: dict | None = None) -> tuple[list[str], list[list[int]], dict, str]:
    """Phase 3 in this process: every photo's depth map from all of P_HD (the octree and the
    normals/radii in the work folder ``work``), splatted by
    :meth:`~dmrt.preprocess.depthmaps.DepthMapRenderer.render_many` on this process's GL context
    and written to ``out_dir/depthmaps/<photo stem>.exr``.

    Returns
    -------
    rels : the maps' paths relative to ``out_dir``, in photo order.  sizes : ``[w, h]`` each.
    gpu_ms : GPU milliseconds per stage (:class:`~dmrt.gl.GpuTimer`).  renderer : the GL renderer.
    ``wall``, when given, receives the wall seconds of :func:`_wall_seconds` and ``writes_s``
    (the wait for the last EXR writes after the last map).
    """
    from dmrt.preprocess.octree import Octree

    points = Octree.open(Path(work) / "octree").point_range(chunk_size=config.chunk_points)
    renderer, hd_chunks, timer = _depth_renderer(work, [points], has_normals, config)
    rels, sizes, writes = [], [], []
    t0 = time.perf_counter()
    # EXR compression (~40 ms a map) runs on threads while the GPU renders the next maps
    with ThreadPoolExecutor(default_workers()) as pool:
        try:
            for j, depth in renderer.render_many(cameras, hd_chunks, resident_mb=config.resident_mb,
                                                 progress=progress):
                rel = f"depthmaps/{Path(names[j]).stem}.exr"
                writes.append(pool.submit(write_depth_exr, Path(out_dir) / rel, depth))
                rels.append(rel)
                sizes.append([depth.shape[1], depth.shape[0]])
        finally:
            renderer.release()
        t1 = time.perf_counter()
        for f in writes:
            f.result()  # a failed write raises here
    if wall is not None:
        wall.update(_wall_seconds(renderer, t1 - t0), writes_s=round(time.perf_counter() - t1, 3))
    return rels, sizes, dict(timer.ms), _gl_renderer_string()


def _wall_seconds(renderer, render_s: float) -> dict:
    """Where a render_many loop's ``render_s`` wall seconds went: ``upload_s`` (waiting for the
    cloud's batches, read, packed and culled on other threads, and uploading them), ``splat_wait_s``
    (the overlapped mode's waits for the GPU's splats of an earlier batch), ``readback_s`` (waiting
    for and copying back the maps), the rest being splatting and the caller's work between maps;
    with ``mode``, ``camera_groups`` and the frustum culling's ``splats`` sent of ``splats_all``
    (:attr:`DepthMapRenderer.last_stats`)."""
    stats = renderer.last_stats
    return {"mode": stats.get("mode"), "camera_groups": stats.get("camera_groups"), "render_s": round(render_s, 3),
            **{k: round(stats.get(k, 0.0), 3) for k in ("upload_s", "splat_wait_s", "readback_s")},
            **{k: int(stats.get(k, 0)) for k in ("splats", "splats_all")}}


def culling_summary(wall: dict) -> dict:
    """bundle.json's ``depthmap_splats`` record from :func:`render_depth_phase`'s ``wall``: splats sent to
    the GPU and splats of every point for every photo (summed over the GPUs' shares on Dask), the
    fraction the frustum culling left out, and the wall seconds per stage."""
    parts = wall.get("parts", [wall])
    sent, every = (sum(p.get(k, 0) for p in parts) for k in ("splats", "splats_all"))
    return {"splats": sent, "splats_all": every, "culled_fraction": round(1 - sent / every, 4) if every else 0.0,
            "modes": sorted({str(p.get("mode")) for p in parts}),
            "camera_groups": max((p.get("camera_groups") or 0 for p in parts), default=0), "wall": wall}


def render_depth_part(item, cameras, work, has_normals: bool, config: PreprocessConfig) -> tuple[dict, str, dict]:
    """Phase 3 on one of several GPUs (a Dask task): every photo's depth map from the points of
    ``item = (part, ranges)`` only (a list of :class:`~dmrt.preprocess.octree.OctreeRange` of
    P_HD: a share of :meth:`~dmrt.preprocess.octree.OctreeRange.deal`),
    saved as ``work/depth-parts/p<part>/<photo index>.npy`` ((h, w) float32 camera z, 0 where
    empty). A map is the nearest splat at each texel, so the nearest of the parts' maps there
    (:func:`nearest_depth`) is the map of all points, bit for bit. Each GPU reads and uploads only
    its share of the points, which dominates the phase at scale (683M points in one process: 33.5
    s, of which 8 s of GPU splatting and read-back).

    Returns
    -------
    gpu_ms : GPU milliseconds per stage.  renderer : the GL renderer.
    wall : wall seconds, as :func:`render_depth_maps` gives them (``saves_s``: the wait for the
    last saves), ``task_s`` (the whole task), and ``device_index`` (the worker's
    ``GLCONTEXT_DEVICE_INDEX``: :func:`~dmrt.preprocess.parallel._pin_gpu`).
    """
    t_task = time.perf_counter()
    part, ranges = item
    folder = Path(work) / "depth-parts" / f"p{part:03d}"
    folder.mkdir(parents=True, exist_ok=True)
    renderer, hd_chunks, timer = _depth_renderer(work, ranges, has_normals, config)
    t0 = time.perf_counter()
    # each map is saved on a thread while the GPU splats the next one (as the in-process EXRs)
    with ThreadPoolExecutor(2) as pool:
        try:
            saves = [pool.submit(np.save, folder / f"{j}.npy", depth)
                     for j, depth in renderer.render_many(cameras, hd_chunks, resident_mb=config.resident_mb)]
        finally:
            renderer.release()
        t1 = time.perf_counter()
        for f in saves:
            f.result()  # a failed save raises here
    wall = {**_wall_seconds(renderer, t1 - t0), "saves_s": round(time.perf_counter() - t1, 3),
            "task_s": round(time.perf_counter() - t_task, 3),
            "device_index": os.environ.get("GLCONTEXT_DEVICE_INDEX")}  # the EGL device asked for, if any
    return dict(timer.ms), _gl_renderer_string(), wall


def nearest_depth(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Texel-wise nearest of two depth maps ((h, w) float32 camera z, 0 = empty)."""
    return np.where((b > 0) & ((a == 0) | (b < a)), b, a)


def octree_phase(scene: Scene, work, config: PreprocessConfig, executor=None, progress: bool = False, scan=None):
    """Phase 1: P_HD's octree in ``work/octree``, positions relative to the scene origin (where
    its float32 keeps micrometres), with the radii and normals of ``scan`` (a
    :class:`~dmrt.preprocess.scangrid.ScanResult`) when given; returns the
    :class:`~dmrt.preprocess.octree.Octree`."""
    from dmrt.preprocess.octree import Octree, OctreeConfig

    origin = scene.origin
    points = _LocalPoints(scene.point_range(config.chunk_points), origin)
    # the bounds load_scene measured save the octree a pass (min(p) - o = min(p - o) exactly)
    return Octree.build(points if scan is None else scan.attach(points), Path(work) / "octree",
                        OctreeConfig(levels=config.octree_levels, memory_limit_mb=config.memory_limit_mb),
                        bbox=[b - origin for b in scene.bounds], progress=progress,
                        executor=executor or InProcess())


def normals_radii_phase(octree, cameras, work, config: PreprocessConfig, executor=None, progress: bool = False,
                        scan=None):
    """Phase 2: normals (where the input has none) and splat radii over P_HD, in octree order, in
    ``work/attrs``. ``cameras``: the photos' cameras relative to the origin (normals face the
    nearest). Returns (the :func:`~dmrt.preprocess.normals.process_chunked` result, whether the
    octree carries normals). With ``scan`` (:mod:`dmrt.preprocess.scangrid`) the octree carries
    the normals and the radii (its ``radii`` field), read from there by the later phases: nothing
    is written and the result is None (a copy in ``work/attrs`` would cost 4 bytes a point of disk:
    ``docs/scene3.md``)."""
    from dmrt.preprocess.normals import process_chunked

    if scan is not None:
        return None, True
    executor = executor or InProcess()
    has_normals = octree.read_level(0).get("normals") is not None
    centers = np.array([c.center for c in cameras])
    attrs = process_chunked(octree.point_range(chunk_size=config.chunk_points), Path(work) / "attrs",
                            normals=not has_normals, radii=True, k_normals=config.normals_k,
                            k_radii=config.radius_k, scale=config.radius_scale, viewpoints=centers,
                            # the budget is per bucket task, and the workers hold one each
                            memory_limit_mb=config.memory_limit_mb / executor.workers, progress=progress,
                            executor=executor)
    return attrs, has_normals


def render_depth_phase(executor, octree, cameras, names, work, out_dir, has_normals: bool, config: PreprocessConfig,
                       progress: bool = False,
                       wall: dict | None = None) -> tuple[list[str], list[list[int]], dict, list[str]]:
    """Phase 3: every photo's depth map from all of P_HD (the octree and the normals/radii in the
    work folder ``work``), written to ``out_dir/depthmaps/<photo stem>.exr``.

    On an executor with ``gpu_tasks`` (Dask), P_HD's chunks are dealt into one share per GPU
    worker (:meth:`~dmrt.preprocess.octree.OctreeRange.deal`,
    :meth:`~dmrt.preprocess.parallel.DaskExecutor.map_gpus`), each splatted into every map
    (:func:`render_depth_part`), and each map merged here as the nearest depth of the shares'
    (:func:`nearest_depth`, exact); otherwise :func:`render_depth_maps` on this process's GL
    context. The maps are the same bit for bit either way.

    Parameters
    ----------
    executor : an executor of :func:`dmrt.preprocess.parallel.open_executor`.
    octree : :class:`~dmrt.preprocess.octree.Octree` in ``work/octree``.
    cameras : the photos' cameras relative to the origin.  names : their image names.

    Returns
    -------
    rels : the maps' paths relative to ``out_dir``, in photo order.  sizes : ``[w, h]`` each.
    gpu_ms : GPU milliseconds per stage, summed over the GPUs.  renderers : the GL renderers used.
    ``wall``, when given, receives wall seconds per stage: in process, those of
    :func:`render_depth_maps`; on Dask, ``parts`` (each GPU task's, :func:`render_depth_part`),
    ``gpus_s`` (until the last task ended) and ``merge_s`` (the merge and the EXRs after it).
    """
    work, out_dir = Path(work), Path(out_dir)
    if not executor.gpu_tasks:
        rels, sizes, gpu_ms, renderer = render_depth_maps(cameras, names, work, out_dir, has_normals, config,
                                                          progress=progress, wall=wall)
        return rels, sizes, gpu_ms, [renderer]
    # each GPU worker splats its share of P_HD into every map; the maps' nearest depths are merged here
    points = octree.point_range(chunk_size=config.chunk_points)
    # dealt by chunks, not cut in halves: each GPU's splats then cost about the same (OctreeRange.deal)
    shares = list(enumerate(points.deal(len(executor.gpu_workers))))
    t0 = time.perf_counter()
    parts = executor.map_gpus(render_depth_part, shares, desc="depth maps", progress=progress,
                              cameras=cameras, work=str(work), has_normals=has_normals, config=config)
    t1 = time.perf_counter()

    def merge(j):
        maps = (np.load(work / "depth-parts" / f"p{p:03d}" / f"{j}.npy") for p, _ in shares)
        depth = functools.reduce(nearest_depth, maps)
        rel = f"depthmaps/{Path(names[j]).stem}.exr"
        write_depth_exr(out_dir / rel, depth)
        return rel, [depth.shape[1], depth.shape[0]]

    with ThreadPoolExecutor(default_workers()) as pool:
        rels, sizes = (list(x) for x in zip(*pool.map(merge, range(len(cameras)))))
    shutil.rmtree(work / "depth-parts")
    if wall is not None:
        wall.update(parts=[w for _, _, w in parts], gpus_s=round(t1 - t0, 3),
                    merge_s=round(time.perf_counter() - t1, 3))
    gpu_ms: dict[str, float] = {}
    for ms, _, _ in parts:
        for k, v in ms.items():
            gpu_ms[k] = gpu_ms.get(k, 0.0) + v
    return rels, sizes, gpu_ms, list(dict.fromkeys(r for _, r, _ in parts))


def preprocess(scene_dir, out, config: PreprocessConfig | None = None,
               labeling: LabelingConfig | None = None, force: bool = False, progress: bool = True,
               executor=None) -> Path:
    """Preprocess ``scene_dir`` into the bundle ``out``; returns its path.

    ``executor`` (:func:`dmrt.preprocess.parallel.open_executor`) runs the parallel phases as tasks
    in other processes: octree buckets, normals/radii per spatial bucket, candidates per group of
    photos (one contiguous group per worker), and on Dask also the depth maps (on its GPU workers:
    :func:`render_depth_phase`). The (global)
    labeling runs here. The bundle equals the in-process one; bundle.json records the workers under
    ``dask`` or ``processes``. None: everything in this process.

    bundle.json's ``timings`` give each phase's seconds and the time outside them: ``load_scene_s``
    (loading and validating the scene; on the kNN path also the pass that finds the points'
    bounds, which the scan-grid pass finds on its own), ``bookkeeping_s`` (the census after each
    phase) and ``finish_s`` (the proxies written, the work files' deletion waited for).
    """
    from PIL import Image

    config = config or PreprocessConfig()
    labeling = labeling or LabelingConfig()
    executor = executor or InProcess()
    t_all = time.perf_counter()
    # absolute paths: Dask workers may run elsewhere on the shared file system
    # a binary PLY's points are first read (and validated) by the scan-grid pass where it runs,
    # which finds their bounds on the way: no pass of the loader's own (bounds below)
    scene: Scene = load_scene(Path(scene_dir).resolve(), chunk_size=config.chunk_points, bounds=False)
    # the time outside the phases, recorded too: loading and validating the scene (and the pass
    # for its bounds where no phase found them: load_scene_s), the census after each phase
    # (bookkeeping_s), writing the proxies and the rest of the work files' deletion (finish_s)
    timings: dict[str, float] = {"load_scene_s": round(time.perf_counter() - t_all, 3)}
    bookkeeping = [0.0]

    peak_rss: dict[str, float] = {}
    peak_anon: dict[str, float | None] = {}
    anon = AnonPeak()
    cpu_s: dict[str, float] = {}  # CPU seconds per phase, worker processes included
    cpu_mark = [cpu_seconds()]

    def cpu_tic(name):
        now = cpu_seconds()
        cpu_s[name] = round(now - cpu_mark[0], 2)
        cpu_mark[0] = now

    disk: dict[str, int] = {}  # bytes the run holds on disk after each phase

    def ended(name):
        t0 = time.perf_counter()
        cpu_tic(name)
        disk[name] = _new_bytes(bw.tmp)
        # peak resident memory so far (MiB), so the phase that raised it can be read off, and the
        # phase's own peak of anonymous memory (what --memory-limit-mb governs: dmrt.preprocess.memory)
        peak_rss[name] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)
        peak_anon[name] = anon.take()
        bookkeeping[0] += time.perf_counter() - t0

    def tic(name, t0):
        timings[name] = round(time.perf_counter() - t0, 3)
        ended(name)

    with BundleWriter(out, force=force) as bw, anon:
        work = Path(bw.tmp).resolve() / "work"
        # 0. radii and normals from the scan's grid where it is known (None: kNN in phase 2),
        # in input order, carried through the octree with the points
        t0 = time.perf_counter()
        scan = scan_phase(scene, work, config, progress, executor)
        if scan is not None:
            tic("scan_grid_s", t0)
        if scene.bounds is None and scan is not None:
            scene = scene.with_bounds(*scan.bounds)
        elif scene.bounds is None:  # the kNN path's first pass needs them: the loader's pass, here
            t0 = time.perf_counter()
            scene = scene.with_bounds(*cloud_extent(scene.points_path, config.chunk_points)[:2])
            timings["load_scene_s"] = round(timings["load_scene_s"] + time.perf_counter() - t0, 3)
            cpu_tic("load_scene_s")
        origin = scene.origin
        cams_local = [c.relative_to(origin) for c in scene.cameras]

        # 1. octree (positions relative to the origin, where its float32 keeps micrometres)
        t0 = time.perf_counter()
        octree = octree_phase(scene, work, config, executor, progress, scan)
        if scan is not None:  # the octree carries the scan's radii and normals from here on
            shutil.rmtree(scan.folder)
        tic("octree_s", t0)

        # 2. normals (if missing) and splat radii over P_HD, in octree order (coarsest level first)
        t0 = time.perf_counter()
        attrs, has_normals = normals_radii_phase(octree, cams_local, work, config, executor, progress, scan)
        tic("normals_radii_s", t0)

        # 3. depth maps: in process, or on the GPU workers each with its share of P_HD (read from
        # the work folder)
        t0 = time.perf_counter()
        depth_wall: dict = {}
        depth_files, depth_sizes, gpu_ms, gl_renderers = render_depth_phase(
            executor, octree, cams_local, [c.name for c in scene.cameras], work, work.parent, has_normals,
            config, progress, wall=depth_wall)
        tic("depthmaps_s", t0)
        timings["depthmaps_gpu_ms"] = {k: round(v, 3) for k, v in gpu_ms.items()}

        # 4-6. proxies (the k coarsest levels, first in octree order) with radii of their own
        # density, their candidate photos and labels
        t0 = time.perf_counter()
        lod_counts = octree.lod_counts()
        k = choose_proxy_levels(lod_counts, octree.n_points, config)
        proxy = octree.read_lod(k)
        n_proxy = len(proxy["positions"])
        proxy = {"positions": proxy["positions"],
                 "normals": proxy["normals"] if has_normals else np.array(attrs.normals[:n_proxy]),
                 "hd_radii": np.array(proxy["radii"] if "radii" in proxy else attrs.radii[:n_proxy], np.float32)}
        # the work files (the octree: 21 GB at 683M points) are read no more (the depth maps lie in
        # the bundle; the arrays above are copies): deleted while the proxies are labelled
        bw.discard(work)
        read_s = time.perf_counter() - t0
        proxies = label_proxies(proxy, cams_local, _DepthFiles(work.parent, depth_files), _Photos(scene),
                                config, labeling, progress=progress, executor=executor, phase_done=ended)
        timings.update(proxies.timings, proxies_s=round(proxies.timings["proxies_s"] + read_s, 3))

        # 6b. photometric adjustment: one gain per photo and channel from the proxies' colours in
        # the photos that share them (dmrt.preprocess.photometric)
        t0 = time.perf_counter()
        photometric = solve_for_proxies(proxies.proxy, proxies.candidates, cams_local, _Photos(scene),
                                        progress=progress)
        tic("photometric_s", t0)

        # 7. photos (undistorted or cut from panoramas where the scene's are not pinhole photos:
        # Scene.read_image) and their low-resolution copies
        t0 = time.perf_counter()

        def photo(j):  # decoding, resampling, resizing and encoding release the GIL: threads scale
            cam, rgb = scene.cameras[j], scene.read_image(j)
            made = scene.photo_source(j) is not None
            rel = bw.add_image(scene.image_paths[j], cam.name, rgb if made else None)
            low_h = max(1, round(config.lowres_width * cam.height / cam.width))
            low = f"images_low/{Path(cam.name).stem}.png"
            Image.fromarray(rgb).resize((config.lowres_width, low_h), Image.BOX).save(bw.tmp / low)
            return rel, low

        with ThreadPoolExecutor(default_workers()) as pool:
            written = list(tqdm(pool.map(photo, range(len(scene.cameras))), total=len(scene.cameras),
                                desc="photos", unit="photo", disable=not progress))
        images, images_low = [rel for rel, _ in written], [low for _, low in written]
        tic("photos_s", t0)

        t0 = time.perf_counter()
        bw.write_proxy(**proxies.proxy)
        coverage = coverage_summary(proxies.candidates, [c.name for c in scene.cameras])
        bw.wait_discarded()
        timings["finish_s"] = round(time.perf_counter() - t0, 3)
        timings["bookkeeping_s"] = round(bookkeeping[0], 3)
        timings["total_s"] = round(time.perf_counter() - t_all, 3)
        meta = {
            "scene": str(Path(scene_dir).resolve()),
            "command": " ".join(shlex.quote(a) for a in sys.argv),
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "gl_renderer": "; ".join(gl_renderers),
            "origin": origin.tolist(),
            "cameras": [camera_to_json(c) for c in scene.cameras],
            "images": images, "images_low": images_low, "depthmaps": depth_files,
            # where a photo was undistorted or cut from a panorama: its source (cameras: the result)
            **({"photo_sources": [src and src.about for src in scene.photos]} if scene.photos else {}),
            "depthmap_sizes": depth_sizes,
            "parameters": {"preprocess": asdict(config), "labeling": asdict(labeling)},
            "timings": timings,
            "peak_rss_mb_after": peak_rss,
            "peak_anon_mb_per_phase": peak_anon,
            "cpu_s_per_phase": cpu_s,
            "disk_bytes_after": disk,
            "counts": {
                "points": octree.n_points, "photos": len(scene.cameras), **proxies.counts(),
                "proxy_levels": k, "octree_level_counts": list(octree.level_counts),
                "lod_counts": lod_counts, "subsampling_factors": octree.subsampling_factors(),
                "normals_estimated": not has_normals or bool(scan and scan.normals), **coverage.counts(),
            },
            # how the out-of-core phases cut the cloud, and the octree's passes in seconds
            "octree": {k: octree.meta.get(k) for k in ("bucket_level", "n_buckets", "max_bucket_points",
                                                       "bucket_capacity", "workers", "timings")},
            # which method gave the radii and normals (dmrt.preprocess.scangrid: how many points fell back)
            "normals_radii": scan.meta() if scan is not None else {
                "method": "knn", "radii": "knn", "normals": "input" if has_normals else "knn", "kernel": knn_kernel(),
                "margin_m": attrs.margin,
                "buckets": attrs.n_buckets, "max_bucket_points": attrs.max_bucket_points,
                "unverified_points": attrs.n_unverified},
            "labeling": proxies.labeling_meta(),
            "depthmap_splats": culling_summary(depth_wall),
            "photo_gains": photometric.gains.tolist(),
            "photometric": photometric.meta(),
        }
        if executor.distributed:  # outside "parameters": workers do not change the bundle
            meta["dask" if executor.gpu_tasks else "processes"] = executor.record()
        done = bw.finish(meta)
    # the end of every run: which proxies and photos the candidates left unseen, and a warning
    # when a registration mistake is likely (dmrt.preprocess.registration.Coverage)
    print(coverage.line(), file=sys.stderr)
    if coverage.warning():
        print(coverage.warning(), file=sys.stderr)
    return done

