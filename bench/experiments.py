"""The experiments of the paper's Section 6, one function and one parameters dataclass each.

An experiment is ``run(ws, params, out_dir) -> measurements``: ``ws`` the
:class:`bench.workspace.Workspace` (scene, bundles, walkthrough, Embree reference frames), ``params``
its dataclass (made from a :class:`bench.workspace.BenchPreset` by its ``params`` function),
``out_dir`` the result set's folder for side files (image maps as ``.npz``). The harness wraps
the measurements with machine, commit, preset and parameters into ``<experiment>.json``;
:mod:`bench.report` reads only those files.

GPU milliseconds come from GL timer queries (``frame["timings"]``); on Mesa llvmpipe they are
meaningless but present, so the report is complete on a CPU too. Quality is measured against the
Embree ray casts of the scene's reference mesh (:mod:`reference`).
"""

from __future__ import annotations

import dataclasses
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from bench.workspace import BenchPreset, Workspace, gpu_clocks


# ----------------------------------------------------------------------------------------------
# Shared measurements
# ----------------------------------------------------------------------------------------------
@dataclass
class Walk:
    """A walkthrough: frames measured along the path through key photo cameras, after warm-up."""

    frame_size: tuple[int, int]
    frames: int
    keys: int
    # frames rendered first and not measured; -1 = the whole path once (steady-state photo cache)
    warmup_frames: int


def walk_of(preset: BenchPreset) -> Walk:
    return Walk(preset.frame_size, preset.walkthrough_frames, preset.walkthrough_keys, preset.warmup_frames)


def walkthrough_cameras(ws: Workspace, walk: Walk) -> list:
    from dmrt.runtime.walkthrough import camera_path

    cams = ws.bundle().cameras
    keys = cams[:: max(1, len(cams) // walk.keys)]
    return camera_path(keys, walk.frames, *walk.frame_size)


def fps_summary(totals_ms) -> dict:
    """``fps_min_avg_max`` (from the slowest, mean and fastest frame, as the paper) and ``fps_median``."""
    t = np.maximum(np.asarray(totals_ms, np.float64), 1e-9)
    return {"fps_min_avg_max": [1e3 / t.max(), 1e3 / t.mean(), 1e3 / t.min()], "fps_median": 1e3 / float(np.median(t))}


# The sustained pass: the walkthrough back to back for at least SUSTAINED_S seconds, after WARM_UP_S
# seconds of the same. A 30-frame 1280x720 walkthrough lasts ~0.1 s, less than the GPU takes to
# raise clocks lowered while the timed pass waited for its queries: single passes right after it
# read 2.5 ms a frame at 1980 MHz and 4.4 ms at 1245 MHz for the same code (H200, session 10).
# the paper's experiments texture from the labels fixed per proxy (paper 5.2); the runtime's default
# is the view-dependent choice (dmrt/runtime/view_choice.py), measured in real_views
PAPER_CHOICE = "labels"
WARM_UP_S = 0.5
SUSTAINED_S = 1.0


def _back_to_back(renderer, cameras, seconds: float) -> list[float]:
    """Render ``cameras`` back to back, frames left on the GPU, whole walkthroughs until ``seconds``
    of wall clock have passed (at least one); waits for the GPU at the end. Returns each
    ``render()`` call's wall ms: the CPU's time to issue the frame plus whatever it waited for."""
    renderer.ctx.finish()
    t0, calls = time.perf_counter(), []
    while not calls or time.perf_counter() - t0 < seconds:
        for cam in cameras:
            t1 = time.perf_counter()
            renderer.render(cam, readback=False)
            calls.append((time.perf_counter() - t1) * 1e3)
    renderer.ctx.finish()
    return calls


# The photo cache fills over several walkthroughs: a frame uploads at most max_uploads_per_frame
# photos, each once its background decode is done. On the paper preset at 1280x720 (192 photos, all
# of which fit) ~100 photos were still uploaded after the statistics pass, the last ones within the
# sustained timed pass, where each upload frame read 2-8 ms and moved the median (reports/frame-h200,
# sessions 18-19). The timed passes measure the steady state that a viewer reaches once it has
# looked around: warm_photo_cache preloads what the walkthrough wants, until a whole pass uploads
# nothing, for at most WARM_UP_MAX_S (a path whose frames take 100 ms gains nothing from a steadier
# cache that is worth minutes).
WARM_UP_MAX_S = 10.0


def warm_photo_cache(renderer, cameras, wanted) -> dict:
    """Make the photo cache steady for ``cameras``: upload ``wanted`` (photo indices, e.g. those the
    statistics pass wanted, first seen first; :meth:`dmrt.runtime.texturing.ImageCache.preload`),
    render the walkthrough (frames left on the GPU), and again with what it wanted added, until a
    whole walkthrough uploads no photo and starts no decode, with none pending, or
    :data:`WARM_UP_MAX_S` have passed (a decode that a frame started and a later one no longer
    wanted ends in the CPU cache, not uploaded: the next walkthrough wants it again). (A
    streaming cache follows the frame before's choice, so the statistics pass never wants its last
    frame's own.) Returns ``loops`` (walkthroughs rendered), ``uploads`` (photos uploaded, the
    preloads' included) and ``steady`` (the last walkthrough uploaded and decoded nothing)."""
    images = renderer.images
    first, wanted = images.uploads, dict.fromkeys(wanted)
    t0, loops = time.perf_counter(), 0
    while True:
        images.preload(list(wanted))
        before = images.uploads, images.decodes
        for cam in cameras:
            renderer.render(cam, readback=False)
            wanted.update(dict.fromkeys(images.wanted))
        loops += 1
        steady = (images.uploads, images.decodes) == before and not images.pending
        if steady or time.perf_counter() - t0 > WARM_UP_MAX_S:
            return {"loops": loops, "uploads": int(images.uploads - first), "steady": steady}


def _stage_summary(frames: list[dict]) -> dict:
    """Medians of per-frame timer sections (:meth:`dmrt.gl.GpuTimer.collect`): ``median_ms``
    {stage}, ``median_part_ms`` {``stage:part``}, ``median_total_ms``, ``p95_total_ms``,
    ``total_ms_per_frame``, ``part_ms_per_frame`` {section: list} (which section a slow frame's
    time went to)."""
    parts = sorted({k for f in frames for k in f})
    stages = sorted({k.split(":", 1)[0] for k in parts})
    per_stage = [{s: sum(v for k, v in f.items() if k.split(":", 1)[0] == s) for s in stages} for f in frames]
    totals = [float(sum(f.values())) for f in frames]
    return {"median_ms": {s: float(np.median([f[s] for f in per_stage])) for s in stages},
            "median_part_ms": {k: float(np.median([f.get(k, 0.0) for f in frames])) for k in parts if ":" in k},
            "median_total_ms": float(np.median(totals)), "p95_total_ms": float(np.percentile(totals, 95)),
            "total_ms_per_frame": totals, "part_ms_per_frame": {k: [f.get(k, 0.0) for f in frames] for k in parts}}


def measure_walkthrough(bundle, config, cameras, desc: str = "walkthrough",
                        on_frame: Callable[[dict], None] | None = None, progress: bool = True,
                        fenced: bool = False, passes: bool = False) -> dict:
    """Render ``cameras`` in four passes with a fresh renderer: a statistics pass that reads every
    frame back, then the walkthrough again until the photo cache is steady (:func:`warm_photo_cache`),
    the timed pass, whose
    frames stay on the GPU as in interactive use (``Renderer.render(readback=False)``) and whose
    stages are timed with GL timer queries, the sustained pass: the same frames back to back
    with no timer query, one wall clock over all of them (repeated for at least
    :data:`SUSTAINED_S` after :data:`WARM_UP_S` of warm-up), and the sustained timed pass: back to
    back again with each frame's queries read only after the last frame
    (:attr:`dmrt.gl.GpuTimer.deferred`). Waiting for each frame's timers leaves the GPU idle
    between frames, and an idle GPU lowers its clocks (an H200 ran a light 720p walkthrough at
    1200 of its 1980 MHz), so the timed pass's stage times are upper bounds; the sustained ms per
    frame is what a viewer gets, and the sustained timed pass splits it into stages.

    Parameters
    ----------
    bundle : dmrt.io.bundle.Bundle.  config : dmrt.runtime.renderer.RenderConfig.
    cameras : list of Camera (the frame size is each camera's).
    on_frame : called with every frame of the statistics pass (e.g. to collect statistics).
    fenced : the timed pass's sections fenced by ``glFinish`` (:attr:`dmrt.gl.GpuTimer.fenced`):
        each stage's own time, at the cost of slower frames; the sustained pass is never fenced.
    passes : in both timed passes, each dispatch of a stage that names them a part of its own
        (:attr:`dmrt.gl.GpuTimer.passes`: the tile lists' six).

    Returns
    -------
    dict
        ``median_ms`` {stage: median GPU ms}, ``median_part_ms`` {``stage:part``: median GPU ms
        of the stages' timed parts, e.g. ``image_management:histogram``}, ``median_total_ms``, ``p95_total_ms``,
        ``mean_total_ms`` (the paper's Table 2 averages), ``median_wall_ms``, ``p95_wall_ms``,
        ``frame_size`` (w, h), ``sustained_ms`` (wall ms per frame of the sustained pass),
        ``sustained_timed`` {``wall_ms`` per frame, ``median_ms`` {stage}, ``median_part_ms``
        {part}, ``median_total_ms``, ``p95_total_ms``, ``total_ms_per_frame``, ``part_ms_per_frame``} of the sustained
        timed pass, ``status_reads_per_frame`` (status records read back a frame, sustained pass),
        ``sustained_call_ms`` {``median``, ``p95``} (wall ms of each ``render()`` call of the
        sustained pass: what the CPU takes to issue a frame, plus its waits; with
        ``tile_check="lagged"`` there are none, so this is the CPU's share of a frame),
        ``gpu_clocks`` {``before``, ``after``, ``sustained``: :func:`gpu_clocks` around the timed
        pass and after the sustained one, None without nvidia-smi}, ``fps_min_avg_max``, ``fps_median``,
        per frame ``total_ms_per_frame``, ``stage_ms_per_frame`` {stage: list}, ``wall_ms_per_frame``
        (``render()`` wall clock), ``median_cpu_ms``, ``mean_iterations`` (over the pixels with a
        surface), ``surface_fraction``, ``photo_uploads`` (in the timed passes: 0 once the cache is
        steady), ``warm_up`` {``loops``, ``uploads``, ``steady``} (:func:`warm_photo_cache`), ``gpu_bytes``,
        ``map_cache`` {``slots``, ``partial``, ``loads_before_timed``, ``loads_timed``, ``rerendered_timed``,
        ``missing_per_frame_timed``, ``frames_missing_timed``} (the depth-map cache:
        :mod:`dmrt.runtime.maps`; missing maps are holes until loaded) and ``tile_stats`` (the tiles
        path's :meth:`~dmrt.runtime.tiles.TileVisibility.stats` of the last frame, else None) and
        ``tile_lists_per_frame`` {``entries``, ``large``, ``longest``, ``split_tiles``,
        ``split_discs``, ``split_slices``: lists of the statistics pass's frames},
        ``split_frames_sustained`` (the share of the sustained pass's frames that ran the tiles
        path's split: :attr:`~dmrt.runtime.tiles.TileVisibility.split_hold`; None without it)
        (:meth:`~dmrt.runtime.tiles.TileVisibility.stats`: the tile raster's and labeling's work,
        whose longest tile sets a slow frame's time unless it was split; None without the tiles path).
    """
    from tqdm import tqdm

    from dmrt.runtime.renderer import Renderer

    renderer = Renderer(bundle, config)
    renderer.timer.wait = True  # the timed pass: each frame's own times (the other passes do not read them)
    try:
        iters, surface, wanted, lists = [], [], {}, {k: [] for k in ("entries", "large", "longest", "split_tiles",
                                                                   "split_discs", "split_slices")}
        for cam in tqdm(cameras, desc=f"{desc} (statistics)", unit="frame", leave=False, disable=not progress):
            f = renderer.render(cam)
            wanted.update(dict.fromkeys(renderer.images.wanted))
            if renderer.visibility.tiles is not None:  # the frame is read back: its list is done, no extra wait
                stats = renderer.visibility.tiles.stats()
                for key, values in lists.items():
                    values.append(stats[key])
            hit = f["depth"] > 0
            surface.append(float(hit.mean()))
            iters.append(float(f["iterations"][hit].mean()) if hit.any() else 0.0)
            if on_frame is not None:
                on_frame(f)
        warm_up = warm_photo_cache(renderer, cameras, list(wanted))
        uploads0, map_loads0, rerendered, missing = renderer.images.uploads, renderer.maps.loads, 0, []
        clocks_before = gpu_clocks()  # the statistics pass just ran back to back: clocks are up
        timings, parts, cpu, wall = [], [], [], []
        renderer.timer.fenced = fenced
        renderer.timer.passes = passes
        for cam in tqdm(cameras, desc=desc, unit="frame", leave=False, disable=not progress):
            t0 = time.perf_counter()
            f = renderer.render(cam, readback=False)
            wall.append((time.perf_counter() - t0) * 1e3)
            timings.append(f["timings"])
            rerendered += bool(f.get("rerendered"))
            missing.append(f.get("maps_missing", 0))
            parts.append(f.get("part_timings", {}))
            cpu.append(f.get("cpu_ms", {}))
        clocks = {"before": clocks_before, "after": gpu_clocks()}
        renderer.timer.fenced = False
        renderer.timer.enabled = False
        _back_to_back(renderer, cameras, WARM_UP_S)  # clocks up again after the timed pass's waits
        tiles = renderer.visibility.tiles  # its list length: the tile raster's work (disc-tile pairs)
        reads0, splits0 = renderer.shading.status.reads, tiles.split_frames if tiles is not None else 0
        t0 = time.perf_counter()
        calls = _back_to_back(renderer, cameras, SUSTAINED_S)
        n = len(calls)
        sustained = (time.perf_counter() - t0) * 1e3 / n
        reads = (renderer.shading.status.reads - reads0) / n
        split_share = (tiles.split_frames - splits0) / n if tiles is not None else None
        renderer.timer.enabled = True
        clocks["sustained"] = gpu_clocks()
        renderer.timer.deferred = True
        t0 = time.perf_counter()
        for cam in cameras:
            renderer.render(cam, readback=False)
        renderer.ctx.finish()
        timed_wall = (time.perf_counter() - t0) * 1e3 / len(cameras)
        renderer.timer.reset()
        frames = renderer.timer.collect()
        renderer.timer.deferred = False
        renderer.timer.passes = False
        sustained_timed = _stage_summary(frames)
        sustained_timed["wall_ms"] = timed_wall
        tile_stats = tiles.stats() if tiles is not None else None
        stages = list(timings[0])
        totals = [float(sum(t.values())) for t in timings]
        part_names = sorted({k for t in parts for k in t})
        return {"median_ms": {s: float(np.median([t[s] for t in timings])) for s in stages},
                "median_part_ms": {k: float(np.median([t.get(k, 0.0) for t in parts])) for k in part_names},
                "median_total_ms": float(np.median(totals)), "mean_total_ms": float(np.mean(totals)),
                "p95_total_ms": float(np.percentile(totals, 95)), "p95_wall_ms": float(np.percentile(wall, 95)),
                "frame_size": [cameras[0].width, cameras[0].height], "sustained_ms": sustained,
                "gpu_clocks": clocks, "sustained_timed": sustained_timed, "status_reads_per_frame": reads,
                "split_frames_sustained": split_share,
                "sustained_call_ms": {"median": float(np.median(calls)), "p95": float(np.percentile(calls, 95))},
                **fps_summary(totals),
                "total_ms_per_frame": totals, "stage_ms_per_frame": {s: [t[s] for t in timings] for s in stages},
                "wall_ms_per_frame": wall, "median_wall_ms": float(np.median(wall)),
                "median_cpu_ms": {k: float(np.median([c.get(k, 0.0) for c in cpu])) for k in cpu[0]},
                "mean_iterations": float(np.mean(iters)), "surface_fraction": float(np.mean(surface)),
                "photo_uploads": int(renderer.images.uploads - uploads0), "warm_up": warm_up,
                "gpu_bytes": dict(renderer.gpu_bytes),
                "map_cache": {"slots": renderer.maps.n_slots, "partial": renderer.maps.partial,
                              "loads_before_timed": map_loads0, "loads_timed": renderer.maps.loads - map_loads0,
                              "rerendered_timed": rerendered,
                              # maps a frame two before wanted and did not find (holes meanwhile, with
                              # async_photos), and how many frames had any
                              "missing_per_frame_timed": float(np.mean(missing)),
                              "frames_missing_timed": int(np.count_nonzero(missing))},
                "tile_stats": tile_stats,
                "tile_lists_per_frame": lists if lists["entries"] else None}
    finally:
        renderer.release()


def profile_walkthrough(bundle, config, cameras, seconds: float = SUSTAINED_S, top: int = 25) -> dict:
    """Where the CPU's time goes while it issues frames: ``cameras`` rendered back to back (frames
    left on the GPU, as the sustained pass) under :mod:`cProfile`, after :data:`WARM_UP_S` of
    warm-up, with a fresh renderer.

    Returns
    -------
    dict
        ``frames``; ``ms_per_frame`` (wall, profiled: the profiler slows Python, not the driver);
        ``top`` - the ``top`` functions by own time: ``function`` (file:line(name), or the C
        method, e.g. ``{method 'run' of 'mgl.ComputeShader' objects}``: a GL call), ``calls_per_frame``,
        ``own_ms_per_frame``, ``total_ms_per_frame`` (with what it calls).
    """
    import cProfile
    import pstats

    from dmrt.runtime.renderer import Renderer

    renderer = Renderer(bundle, config)
    try:
        renderer.timer.enabled = False
        _back_to_back(renderer, cameras, WARM_UP_S)
        profiler = cProfile.Profile()
        t0 = time.perf_counter()
        profiler.enable()
        n = len(_back_to_back(renderer, cameras, seconds))
        profiler.disable()
        wall = (time.perf_counter() - t0) * 1e3 / n
        stats = pstats.Stats(profiler).stats  # (file, line, name) -> (calls, primitive, own s, total s, callers)
        rows = sorted(stats.items(), key=lambda kv: -kv[1][2])[:top]
        return {"frames": n, "ms_per_frame": wall,
                "top": [{"function": f"{f}:{line}({name})" if line else name, "calls_per_frame": c / n,
                         "own_ms_per_frame": own * 1e3 / n, "total_ms_per_frame": total * 1e3 / n}
                        for (f, line, name), (_, c, own, total, _) in rows]}
    finally:
        renderer.release()


def quality_config(**kw):
    """RenderConfig for quality measurements: every frame's photo cache exactly its most frequent
    labels (no streaming delay), no leveling and no photometric gains, so colours are the photos'
    own, as the reference's;
    no hole filling from neighbours, so that holes are the layers' own (the paper's Figs. 7, 13:
    :func:`hole_counts` reads every layer count off one frame, which filled pixels would break)."""
    from dmrt.runtime.renderer import RenderConfig

    return RenderConfig(**{"async_photos": False, "max_uploads_per_frame": 0, "leveling": False,
                           "photometric": False, "fill_passes": 0, "photo_choice": PAPER_CHOICE, **kw})


def scaled_radii(bundle, scale: float):
    """The bundle with its proxy splat radii multiplied by ``scale`` (in memory; Fig. 10's worst case)."""
    if scale == 1.0:
        return bundle
    return dataclasses.replace(bundle, _proxy={**bundle.proxy, "radii": bundle.proxy["radii"] * np.float32(scale)})


def hole_counts(layer_used: np.ndarray, mask: np.ndarray, max_layers: int) -> np.ndarray:
    """Pixels of ``mask`` left empty with ``k = 1 .. max_layers`` layers, from one frame.

    The raytracer tries the layers in order and the first valid hit wins, and the first ``k`` layers
    of a frame with more layers are the ``k`` layers of a ``k``-layer frame (exactly with depth
    peeling; with the k-buffer, which keeps more fragments for more layers, within its >= 99.9 %),
    so a pixel is surface with ``k`` layers when its hit layer is below ``k``. The ci test checks
    this against Fig. 13's direct 1/2/3-layer renders.

    Returns
    -------
    (max_layers,) int64: holes with 1, 2, ... layers.
    """
    return np.array([int((mask & ~((layer_used >= 0) & (layer_used < k))).sum()) for k in range(1, max_layers + 1)])


class HoleTally:
    """Holes per layer count summed over views, among all reference surface pixels (``all``) and
    among those some depth map can show (``representable``, :func:`bench.workspace.representable_mask`)."""

    KINDS = ("all", "representable")

    def __init__(self, max_layers: int):
        self.max_layers = max_layers
        self.holes = {k: np.zeros(max_layers, np.int64) for k in self.KINDS}
        self.pixels = {k: 0 for k in self.KINDS}

    def add(self, layer_used: np.ndarray, ref: dict) -> None:
        for kind, mask in zip(self.KINDS, (ref["depth"] > 0, ref["representable"] & (ref["depth"] > 0))):
            self.holes[kind] += hole_counts(layer_used, mask, self.max_layers)
            self.pixels[kind] += int(mask.sum())

    def rates(self) -> dict:
        """{kind: [hole rate with 1, 2, ... layers]}."""
        return {k: (self.holes[k] / max(self.pixels[k], 1)).tolist() for k in self.KINDS}


def tally_holes(ws, bundle, config, cams, max_layers: int) -> HoleTally:
    """The holes of ``bundle`` rendered with ``config`` (``max_layers`` layers) at ``cams``
    against the workspace's Embree reference frames."""
    from dmrt.runtime.renderer import Renderer

    renderer = Renderer(bundle, config)
    tally = HoleTally(max_layers)
    try:
        for cam in cams:
            tally.add(renderer.render(cam)["layer_used"], ws.reference(cam))
    finally:
        renderer.release()
    return tally


def hole_rate(frame: dict, ref: dict, mask: np.ndarray) -> float:
    """Share of ``mask``'s reference surface pixels that are background in ``frame``."""
    m = mask & (ref["depth"] > 0)
    return float((m & (frame["depth"] <= 0)).sum() / max(int(m.sum()), 1))


def pick_camera(ws: Workspace, index: int, width: int):
    """Photo camera ``index`` of the bundle (-1: the middle photo), ``width`` pixels wide (its aspect)."""
    cams = ws.bundle().cameras
    return cams[len(cams) // 2 if index < 0 else index].resized(width, None)


def footprint_map(camera, ref: dict, labels: np.ndarray, cameras, depthmap_width: int) -> np.ndarray:
    """(h, w) metres per depth-map texel at the reference surface, in the depth map of ``labels``."""
    from reference.metrics import texel_footprint

    dirs, center = camera.pixel_rays()
    pts = center + dirs * ref["depth"].reshape(-1, 1).astype(np.float64)
    return texel_footprint(pts, labels.ravel(), cameras, depthmap_width).reshape(ref["depth"].shape)


def bundle_summary(bundle) -> dict:
    c = bundle.meta["counts"]
    return {"path": str(bundle.root), "points": c["points"], "photos": c["photos"], "proxies": c["proxies"],
            "proxy_levels": c["proxy_levels"], "subsampling_factor": c["points"] / max(c["proxies"], 1)}


# ----------------------------------------------------------------------------------------------
# Table 1: scene characteristics
# ----------------------------------------------------------------------------------------------
PHASES = ("scan_grid_s", "octree_s", "normals_radii_s", "depthmaps_s", "proxies_s", "candidates_s", "labeling_s",
          "photometric_s", "photos_s")
OPTIONAL_PHASES = ("scan_grid_s",)  # only where the bundle ran it (radii from the scan's grid)


@dataclass
class Table1Params:
    """Table 1 reads the main bundle's ``bundle.json``; nothing to choose."""

    phases: tuple[str, ...] = PHASES


def run_table1(ws: Workspace, p: Table1Params, out: Path) -> dict:
    b = ws.bundle()
    meta = b.meta
    c, t = meta["counts"], meta["timings"]
    sizes = meta.get("depthmap_sizes") or [[0, 0]]
    return {"bundle": bundle_summary(b), "counts": c,
            "photo_size": [b.cameras[0].width, b.cameras[0].height], "depthmap_size": sizes[0],
            "phases_s": {ph: t.get(ph) for ph in p.phases if ph in t or ph not in OPTIONAL_PHASES},
            "preprocess_total_s": float(sum(t.get(ph) or 0.0 for ph in p.phases)),
            "bundle_total_s": t.get("total_s"),  # the whole `dmrt preprocess`: loading and writing too
            "depthmaps_gpu_ms": t.get("depthmaps_gpu_ms"), "peak_rss_mb": meta.get("peak_rss_mb_after"),
            "peak_anon_mb": meta.get("peak_anon_mb_per_phase"), "cpu_s_per_phase": meta.get("cpu_s_per_phase"),
            "cores": os.cpu_count(), "octree": meta.get("octree"), "radii": meta.get("normals_radii"),
            "derived_from_base": meta.get("derived_from") is not None,
            "scene_generation_s": ws.setup_s.get("scene_generation"), "labeling": meta.get("labeling")}


# ----------------------------------------------------------------------------------------------
# Table 2: per-stage GPU ms per layer count and visibility path
# ----------------------------------------------------------------------------------------------
# visibility-stage ratios reported: the paper's peeling by rasterization vs by compute splatting,
# and both vs the one-pass k-buffer
VISIBILITY_PAIRS = (("raster", "compute"), ("compute", "tiles"), ("kbuffer", "tiles"), ("raster", "tiles"))


@dataclass
class Table2Params:
    # layer counts (paper: 1, 3, 5, 7, 9, 11)
    layers: tuple[int, ...]
    # visibility paths (RenderConfig.method), the default first
    methods: tuple[str, ...]
    walk: Walk
    # The paper's texturing pass includes screen-space leveling: on, reported as its own stage.
    leveling: bool = True
    # the same walkthrough at these frame sizes, LARGE_LAYERS layers, every method but raster
    large_frames: tuple[tuple[int, int], ...] = ()


LARGE_LAYERS = 5


def run_table2(ws: Workspace, p: Table2Params, out: Path) -> dict:
    from dmrt.runtime.renderer import RenderConfig

    b = ws.bundle()
    cams = walkthrough_cameras(ws, p.walk)

    def measure(method, k, cameras):
        r = measure_walkthrough(b, RenderConfig(layers=k, method=method, leveling=p.leveling,
                                                photo_choice=PAPER_CHOICE), cameras,
                                f"{method} k={k}", progress=ws.progress)
        w, h = r["frame_size"]
        print(f"  {method:8s} k={k:2d} {w}x{h} " + " ".join(f"{s} {v:.3f}" for s, v in r["median_ms"].items())
              + f" | total {r['median_total_ms']:.3f} ms, sustained {r['sustained_ms']:.3f} ms/frame, "
              f"{r['mean_iterations']:.2f} steps", flush=True)
        return {"method": method, "layers": k, **r}

    runs = [measure(method, k, cams) for method in p.methods for k in p.layers]
    large = [measure(method, LARGE_LAYERS, [c.resized(w, h) for c in cams])
             for w, h in p.large_frames for method in p.methods if method != "raster"]
    ratios = {}
    for a, b_ in VISIBILITY_PAIRS:
        for k in p.layers:
            by = {r["method"]: r["median_ms"]["visibility"] for r in runs if r["layers"] == k}
            if a in by and b_ in by:
                ratios.setdefault(f"{a}/{b_}", {})[str(k)] = by[a] / max(by[b_], 1e-9)
    return {"bundle": bundle_summary(b), "runs": runs, "visibility_ratios": ratios, "large_runs": large}


# ----------------------------------------------------------------------------------------------
# Table 3 and Fig. 12: DMT vs DMRT
# ----------------------------------------------------------------------------------------------
@dataclass
class Table3Params:
    # DMT depth-map widths (heights: the photos' aspect; paper: 256, 512, 1024)
    resolutions: tuple[int, ...]
    # the walkthrough both methods render
    walk: Walk
    # DMRT's side as in the paper: 5 layers on the main proxy set
    layers: int = 5
    # DMT's per-texel labeling: "graphcut" (as the paper's DMT: timed against DMRT's), or "wta" /
    # "own" (frame rates only, no labeling time to compare)
    labeler: str = "graphcut"
    # Graph cuts: wall-clock seconds per resolution; when all maps do not fit, a seeded random
    # subset that does is labelled and its per-map CPU time extrapolated to every map (None: all)
    dmt_budget_s: float | None = None
    # labeling processes (None: every CPU core) and the subset's seed
    dmt_workers: int | None = None
    dmt_seed: int = 0

    def __post_init__(self):
        from dmrt.errors import ConfigError

        if self.labeler not in ("graphcut", "wta", "own"):
            raise ConfigError("labeler", f"must be one of 'graphcut', 'wta', 'own', not {self.labeler!r}")
        if self.dmt_budget_s is not None and not self.dmt_budget_s >= 0:
            raise ConfigError("dmt_budget_s", f"must be >= 0 seconds or None, not {self.dmt_budget_s}")
        if self.dmt_workers is not None and self.dmt_workers < 1:
            raise ConfigError("dmt_workers", f"must be >= 1 or None (every core), not {self.dmt_workers}")


def run_table3_fig12(ws: Workspace, p: Table3Params, out: Path) -> dict:
    """:func:`bench.bench_dmt.run` (DMT labeling per depth-map width, timed in wall and CPU seconds
    against DMRT's labeling run again; DMT and DMRT walkthroughs) on the main bundle and the
    walkthrough of the other experiments; its result is stored unchanged under ``dmt``
    (:func:`bench.report.table3_rows` reads it)."""
    from bench.bench_dmt import run as dmt_run
    from dmrt.runtime.walkthrough import save_path

    cams = walkthrough_cameras(ws, p.walk)
    path = ws.work / "walkthrough.json"
    save_path(path, cams)
    w, h = p.walk.frame_size
    warmup = len(cams) if p.walk.warmup_frames < 0 else p.walk.warmup_frames
    result = dmt_run(ws.bundle_path(), resolutions=tuple(p.resolutions), frames=len(cams), width=w, height=h,
                     labeler=p.labeler, layers=p.layers, warmup=warmup, path=path, progress=ws.progress,
                     budget_s=p.dmt_budget_s, workers=p.dmt_workers, seed=p.dmt_seed)
    return {"bundle": bundle_summary(ws.bundle()), "dmt": result}


# ----------------------------------------------------------------------------------------------
# Fig. 7: proxy-count sweep
# ----------------------------------------------------------------------------------------------
@dataclass
class Fig7Params:
    # proxy sets: numbers of coarsest octree levels (LOD k)
    proxy_levels: tuple[int, ...]
    # hole rates vs Embree at these many photo cameras, frame width there
    photo_cameras: int
    quality_width: int
    # layer counts tried (1 .. max_layers)
    max_layers: int
    # "layers needed": the fewest with hole rate <= target; "layers to converge": the fewest within
    # converge_tolerance of the rate with max_layers (holes more layers do not fill); both over the
    # representable reference pixels (the others are holes by design: unscanned, occluded in all photos)
    hole_rate_target: float
    converge_tolerance: float
    # fps over the walkthrough at these layer counts (and at the layers needed) per proxy set
    fps_layers: tuple[int, ...]
    walk: Walk


def run_fig7(ws: Workspace, p: Fig7Params, out: Path) -> dict:
    from dmrt.runtime.renderer import RenderConfig

    cams = [c.resized(p.quality_width, None) for c in ws.photo_cameras(p.photo_cameras)]
    path = walkthrough_cameras(ws, p.walk)
    sets = []
    for levels in p.proxy_levels:
        b = ws.bundle(levels)
        t = b.meta["timings"]
        tally = tally_holes(ws, b, quality_config(layers=p.max_layers), cams, p.max_layers)
        rates = tally.rates()
        rate = rates["representable"]
        needed = next((k for k in range(1, p.max_layers + 1) if rate[k - 1] <= p.hole_rate_target), None)
        converged = next(k for k in range(1, p.max_layers + 1) if rate[k - 1] <= rate[-1] + p.converge_tolerance)
        fps = {}
        for k in sorted(set(p.fps_layers) | {needed or converged}):
            r = measure_walkthrough(b, RenderConfig(layers=k, photo_choice=PAPER_CHOICE), path, f"LOD {levels} k={k}",
                                    progress=ws.progress)
            fps[str(k)] = {key: r[key] for key in ("median_total_ms", "fps_min_avg_max", "fps_median",
                                                   "median_ms", "total_ms_per_frame", "median_wall_ms")}
        sets.append({**bundle_summary(b), "candidates_s": t.get("candidates_s"), "labeling_s": t.get("labeling_s"),
                     "labeling_total_s": (t.get("candidates_s") or 0.0) + (t.get("labeling_s") or 0.0),
                     "hole_rate_per_layers": rates["all"], "hole_rate_representable_per_layers": rate,
                     "layers_needed": needed, "layers_to_converge": converged,
                     "fps": fps})
        print(f"  LOD {levels}: {sets[-1]['proxies']} proxies, labeling {sets[-1]['labeling_total_s']:.2f} s, "
              f"holes (representable) {', '.join(f'{x:.2%}' for x in rate)}", flush=True)
    return {"cameras": [c.name for c in cams], "frame_sizes": [[c.width, c.height] for c in cams],
            "reference_pixels": tally.pixels, "sets": sets}


# ----------------------------------------------------------------------------------------------
# Fig. 8: depth and colour error heat maps at a photo camera
# ----------------------------------------------------------------------------------------------
FIG8_STAGES = {
    "coarse_splats": {"raytrace": False},      # Fig. 8b: the first splat layer is the surface
    "raytraced": {"labeling": False},          # Fig. 8c: raytraced, each layer's splat label
    "raytraced_labels": {},                    # Fig. 8d: raytraced + per-pixel labeling pass
}


@dataclass
class Fig8Params:
    # bundle photo index of the view (-1: the middle photo); frame width there
    camera_index: int
    quality_width: int
    # the paper's Section 6.3 setting
    layers: int = 4


def run_fig8(ws: Workspace, p: Fig8Params, out: Path) -> dict:
    from dmrt.runtime.renderer import Renderer
    from reference.metrics import compare

    b = ws.bundle()
    cam = pick_camera(ws, p.camera_index, p.quality_width)
    ref = ws.reference(cam)
    dm_width = (b.meta.get("depthmap_sizes") or [[b.cameras[0].width]])[0][0]
    maps = {"reference_color": ref["color"], "reference_depth": ref["depth"], "representable": ref["representable"]}
    stages = {}
    for stage, options in FIG8_STAGES.items():
        renderer = Renderer(b, quality_config(layers=p.layers, **options))
        try:
            frame = renderer.render(cam)
        finally:
            renderer.release()
        fp = footprint_map(cam, ref, frame["label_raw"], b.cameras, dm_width)
        m = compare(frame, ref, fp)
        m["hole_rate_representable"] = hole_rate(frame, ref, ref["representable"])
        for name, a in m.pop("maps").items():
            maps[f"{stage}_{name}"] = a
        maps[f"{stage}_color"] = frame["color"]
        stages[stage] = dict(m)
        print(f"  {stage}: depth median {m['depth_median_m'] * 1e3:.1f} mm, holes {m['hole_rate']:.2%}, "
              f"PSNR {m['psnr_db']:.1f} dB", flush=True)
    np.savez_compressed(out / "fig8.npz", **maps)
    return {"camera": cam.name, "frame_size": [cam.width, cam.height], "depthmap_width": dm_width,
            "stages": stages, "maps_file": "fig8.npz", "maps": sorted(maps)}


# ----------------------------------------------------------------------------------------------
# Figs. 9 and 10: iterative-search step sizes, iterations, the radii x2.5 worst case
# ----------------------------------------------------------------------------------------------
@dataclass
class Fig9Params:
    # (name, splat radius scale, layers): the paper's 4 layers, then radii x2.5 with 4 and 11 layers
    cases: tuple[tuple[str, float, int], ...]
    # timings, iterations and step statistics over this walkthrough
    walk: Walk
    # hole rates of each case at these photo cameras
    photo_cameras: int
    quality_width: int
    # the paper's 100 iterative and 20 binary-search steps
    max_steps: int = 100
    binary_steps: int = 20
    # iterations histogram: counts of 0 .. max_iterations_bin - 1, the last bin pools the rest
    max_iterations_bin: int = 64


def step_statistics(bundle, config, cameras) -> dict:
    """Mean step length (metres) and step count per layer and step index, summed over ``cameras``
    (``RenderConfig(statistics=True)``; see :meth:`dmrt.runtime.renderer.Renderer._read_step_stats`)."""
    from dmrt.runtime.renderer import Renderer

    steps_sum, counts = None, None
    renderer = Renderer(bundle, dataclasses.replace(config, statistics=True))
    try:
        for cam in cameras:
            s = renderer.render(cam, readback=False)["step_stats"]
            c = np.asarray(s["count"], np.int64)
            t = np.asarray(s["mean_step_m"], np.float64) * c
            steps_sum, counts = (t, c) if counts is None else (steps_sum + t, counts + c)
    finally:
        renderer.release()
    mean_step = np.divide(steps_sum, counts, out=np.zeros_like(steps_sum), where=counts > 0)
    return {"step_mean_m": mean_step.tolist(), "step_count": counts.tolist()}


def run_fig9_10(ws: Workspace, p: Fig9Params, out: Path) -> dict:
    from dmrt.runtime.renderer import RenderConfig

    path = walkthrough_cameras(ws, p.walk)
    cams = [c.resized(p.quality_width, None) for c in ws.photo_cameras(p.photo_cameras)]
    cases, configs = [], []
    for name, scale, layers in p.cases:
        b = scaled_radii(ws.bundle(), scale)
        cfg = dict(layers=layers, max_steps=p.max_steps, binary_steps=p.binary_steps, photo_choice=PAPER_CHOICE)
        hist = np.zeros(p.max_iterations_bin, np.int64)
        searched = []

        def collect(f):
            it = f["iterations"][f["iterations"] > 0]  # pixels whose search ran (a splat in layer 1)
            hist[:] += np.bincount(np.minimum(it, p.max_iterations_bin - 1), minlength=p.max_iterations_bin)
            searched.append(float(it.mean()) if it.size else 0.0)

        timing = measure_walkthrough(b, RenderConfig(**cfg), path, f"{name} k={layers}", on_frame=collect,
                                     progress=ws.progress)
        rates = tally_holes(ws, b, quality_config(**cfg), cams, layers).rates()
        cases.append({"case": name, "radius_scale": scale, "layers": layers,
                      "raytracing_ms_median": timing["median_ms"]["raytracing"],
                      "raytracing_ms_per_frame": timing["stage_ms_per_frame"]["raytracing"],
                      "mean_iterations": timing["mean_iterations"],
                      "mean_iterations_searched": float(np.mean(searched)),
                      "iterations_histogram": hist.tolist(),
                      "hole_rate": rates["all"][-1], "hole_rate_representable": rates["representable"][-1]})
        configs.append((b, RenderConfig(**cfg)))
        print(f"  {name} k={layers}: {timing['mean_iterations']:.2f} steps per surface pixel, "
              f"holes {rates['all'][-1]:.2%} ({rates['representable'][-1]:.2%} of representable)", flush=True)
    # Step statistics (atomics, so not in the timed pass) come last, for every case: on an H200 this
    # pass with radii x2.5 on the paper preset stopped the GL context (no GL error; every later frame
    # stale), which the renderer now detects. A case it fails for keeps its other measurements.
    error = None
    for case, (b, config) in zip(cases, configs):
        if error is None:
            try:
                case.update(step_statistics(b, config, path))
                continue
            except RuntimeError as exc:
                error = f"{case['case']}, {case['layers']} layers: {exc}"
                print(f"  step statistics failed: {error}", flush=True)
        case["step_statistics_error"] = error
    return {"cases": cases, "cameras": [c.name for c in cams]}


# ----------------------------------------------------------------------------------------------
# Fig. 13: 1, 2, 3 layers, hole maps
# ----------------------------------------------------------------------------------------------
@dataclass
class Fig13Params:
    # layer counts compared (paper: 1, 2, 3)
    layers: tuple[int, ...]
    # hole rates at these many photo cameras, frame width there
    photo_cameras: int
    quality_width: int
    # the view whose hole maps are kept (bundle photo index; -1: the middle photo)
    camera_index: int = -1


def filled_holes(ws: Workspace, bundle, layers: int, cams) -> dict:
    """Hole and extra-surface rates with the renderer's default hole filling from neighbours (beyond
    the paper; Fig. 13's other rates are the layers' own), summed over ``cams``."""
    from dmrt.runtime.renderer import RenderConfig, Renderer
    from reference.metrics import compare

    passes = RenderConfig().fill_passes
    renderer = Renderer(bundle, quality_config(layers=layers, fill_passes=passes))
    holes = {"all": 0, "representable": 0}
    pixels = dict(holes)
    extra = []
    try:
        for cam in cams:
            ref, frame = ws.reference(cam), renderer.render(cam)
            for kind, mask in (("all", ref["depth"] > 0), ("representable", ref["representable"] & (ref["depth"] > 0))):
                holes[kind] += int((mask & (frame["depth"] <= 0)).sum())
                pixels[kind] += int(mask.sum())
            extra.append(compare(frame, ref)["extra_rate"])
    finally:
        renderer.release()
    return {"fill_passes": passes, "hole_rate_filled": holes["all"] / max(pixels["all"], 1),
            "hole_rate_representable_filled": holes["representable"] / max(pixels["representable"], 1),
            "extra_rate_filled": float(np.mean(extra))}


def run_fig13(ws: Workspace, p: Fig13Params, out: Path) -> dict:
    from dmrt.runtime.renderer import Renderer
    from reference.metrics import compare

    b = ws.bundle()
    cams = [c.resized(p.quality_width, None) for c in ws.photo_cameras(p.photo_cameras)]
    shown = pick_camera(ws, p.camera_index, p.quality_width)
    maps = {"reference_color": ws.reference(shown)["color"], "representable": ws.reference(shown)["representable"]}
    rows = []
    for k in p.layers:
        renderer = Renderer(b, quality_config(layers=k))
        tally = HoleTally(k)
        try:
            extra = []
            for cam in cams:
                ref, frame = ws.reference(cam), renderer.render(cam)
                tally.add(frame["layer_used"], ref)
                extra.append(compare(frame, ref)["extra_rate"])
            ref, frame = ws.reference(shown), renderer.render(shown)
            m = compare(frame, ref)
            maps[f"holes_{k}"] = m["maps"]["holes"]
            maps[f"color_{k}"] = frame["color"]
            shown_rates = {"hole_rate": m["hole_rate"], "extra_rate": m["extra_rate"],
                           "hole_rate_representable": hole_rate(frame, ref, ref["representable"])}
        finally:
            renderer.release()
        rates = tally.rates()
        filled = filled_holes(ws, b, k, cams)
        rows.append({"layers": k, "hole_rate": rates["all"][-1], "hole_rate_representable": rates["representable"][-1],
                     "extra_rate": float(np.mean(extra)), "shown_camera": shown_rates, **filled})
        print(f"  k={k}: holes {rows[-1]['hole_rate']:.2%} ({rows[-1]['hole_rate_representable']:.2%} of "
              f"representable) at {len(cams)} photo cameras; {filled['hole_rate_filled']:.2%} "
              f"({filled['hole_rate_representable_filled']:.2%}) with hole filling", flush=True)
    np.savez_compressed(out / "fig13.npz", **maps)
    return {"cameras": [c.name for c in cams], "shown_camera": shown.name, "frame_size": [shown.width, shown.height],
            "rows": rows, "maps_file": "fig13.npz", "maps": sorted(maps)}


# ----------------------------------------------------------------------------------------------
# Section 6.2: GPU memory
# ----------------------------------------------------------------------------------------------
@dataclass
class MemoryParams:
    # one frame of this size with this many layers (paper: 1280x720, 5 layers)
    frame_size: tuple[int, int]
    layers: int = 5


def run_memory(ws: Workspace, p: MemoryParams, out: Path) -> dict:
    from bench import paper
    from dmrt.runtime.renderer import RenderConfig, Renderer
    from dmrt.runtime.texturing import PAPER_CACHE_MB

    b = ws.bundle()
    cam = walkthrough_cameras(ws, Walk(p.frame_size, 2, 2, 0))[0]
    # the paper's 1 GB photo cache, not the GPU-sized default: the same figure on any machine
    renderer = Renderer(b, RenderConfig(layers=p.layers, photo_choice=PAPER_CHOICE, cache_mb=PAPER_CACHE_MB))
    try:
        renderer.render(cam)
        measured = dict(renderer.gpu_bytes)
        cache_mb = renderer.shading.images.budget_mb
    finally:
        renderer.release()
    w, h = p.frame_size
    sizes = b.meta.get("depthmap_sizes") or [[c.width, c.height] for c in b.cameras]
    lh, lw = b.image(0, low=True).shape[:2]
    n = len(b.cameras)
    formula = {"depthmaps": int(sum(sw * sh * 4 for sw, sh in sizes)),
               "images_low": n * lw * lh * 3,
               "proxies": b.meta["counts"]["proxies"] * paper.BYTES_PER_PROXY,
               "layers": w * h * p.layers * paper.BYTES_PER_LAYER_PIXEL,
               # the paper reserves a budget (1 GB); the cache holds at most every photo at full size, RGB8
               "image_cache": int(min(cache_mb * 2 ** 20, sum(c.width * c.height * 3 for c in b.cameras)))}
    return {"bundle": bundle_summary(b), "frame_size": [w, h], "layers": p.layers, "photos": n,
            "lowres_size": [lw, lh], "gpu_bytes": measured, "formula_bytes": formula,
            "total_measured_bytes": int(sum(measured.values()))}


# ----------------------------------------------------------------------------------------------
# Registry
# ----------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Experiment:
    """One experiment: what the harness needs to run it, label its result file and require it."""

    title: str
    # bump when the measurement changes meaning (asv's benchmark version)
    version: int
    run: Callable
    params: Callable[[BenchPreset], object]
    # a complete report needs it (the CI and nightly completeness check)
    required: bool = True
    # run after the others: a failure there must not cost the others their GPU time
    run_last: bool = False


def _run_real_views(ws: Workspace, p, out: Path) -> dict:
    from bench.real_views import run_real_views

    return run_real_views(ws, p, out)


def _real_views_params(pr: BenchPreset):
    from bench.real_views import RealViewsParams

    # frames at least 512 wide (the photo's width if smaller): held-out photos are judged in detail;
    # the stability walkthrough as wide as the preset's and half as long (it joins two photos, not
    # the preset's tour; a DMT frame takes ~1 s on llvmpipe)
    return RealViewsParams(width=max(pr.quality_width, 512), dmt_labeler=pr.dmt_labeler,
                           walk_frames=max(6, pr.walkthrough_frames // 2), walk_width=pr.frame_size[0])


def _q(preset: BenchPreset) -> dict:
    return {"photo_cameras": preset.photo_cameras, "quality_width": preset.quality_width}


# The one list of experiments, in the report's order (``dmrt bench --only``, the report's sections,
# its completeness check and bench/paper_run.sh all read it).
EXPERIMENTS: dict[str, Experiment] = {
    "table1": Experiment("Table 1: scene characteristics and preprocessing", 1, run_table1,
                         lambda pr: Table1Params()),
    "table2": Experiment("Table 2: GPU ms per stage and layer count, compute vs raster visibility", 1, run_table2,
                         lambda pr: Table2Params(tuple(pr.layers), tuple(pr.methods), walk_of(pr),
                                                    large_frames=tuple(pr.large_frames))),
    # version 2: DMT's graph cuts always timed (in parallel, wall and CPU seconds, a subset within
    # the preset's budget), DMRT's labeling timed again in the same run
    "table3_fig12": Experiment("Table 3 / Fig. 12: DMT vs DMRT labeling time and fps", 2, run_table3_fig12,
                               lambda pr: Table3Params(tuple(pr.dmt_resolutions), walk_of(pr),
                                                       dmt_budget_s=pr.dmt_budget_s)),
    "fig7": Experiment("Fig. 7: proxy count vs labeling time, layers needed, fps, holes", 1, run_fig7,
                       lambda pr: Fig7Params(tuple(pr.proxy_levels), max_layers=pr.max_layers,
                                             hole_rate_target=0.005, converge_tolerance=0.001,
                                             fps_layers=tuple(pr.fig7_fps_layers), walk=walk_of(pr), **_q(pr))),
    "fig8": Experiment("Fig. 8: depth and colour error vs Embree at a photo camera", 1, run_fig8,
                       lambda pr: Fig8Params(camera_index=-1, quality_width=pr.quality_width)),
    # its statistics pass once stopped an H200's GL context, which fails every later experiment of
    # the same process
    "fig9_10": Experiment("Figs. 9/10: step sizes, iterations, radii x2.5 worst case", 1, run_fig9_10,
                          lambda pr: Fig9Params((("baseline", 1.0, 4), ("radii x2.5", 2.5, 4),
                                                 ("radii x2.5", 2.5, 11)), walk_of(pr), **_q(pr)),
                          run_last=True),
    "fig13": Experiment("Fig. 13: 1, 2, 3 layers, hole maps", 2, run_fig13,
                        lambda pr: Fig13Params((1, 2, 3), **_q(pr))),
    "memory": Experiment("Section 6.2: GPU memory per resource", 1, run_memory,
                         lambda pr: MemoryParams(tuple(pr.frame_size))),
    # beyond the paper: renders at held-out photos' cameras vs those photos (bench/real_views.py);
    # version 2: FLIP, the data's own bounds (the kept photos reprojected), walkthrough stability,
    # a choice of variants
    "real_views": Experiment("Real views: held-out photos vs DMRT, DMT and coarse splats (PSNR, SSIM, FLIP) and "
                             "vs what the photos allow", 2, _run_real_views, _real_views_params),
}


def run_order() -> list[str]:
    """Every experiment's name in the order ``dmrt bench`` runs them (``run_last`` ones last)."""
    return sorted(EXPERIMENTS, key=lambda name: EXPERIMENTS[name].run_last)


def required_experiments() -> list[str]:
    """The experiments a complete report needs."""
    return [name for name, e in EXPERIMENTS.items() if e.required]


if __name__ == "__main__":
    print(*run_order())  # bench/paper_run.sh's default list
