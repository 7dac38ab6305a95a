"""Benchmark of preprocessing's depth-map phase on several GPUs (``dmrt preprocess --dask local:N``).

    python -m bench.bench_depth_gpus SCENE --out RESULT.json [--gpus N] [--workers W]
        [--memory-limit-mb MB] [--resident-mb MB] [--depthmap-width PX] [--repeat R] [--work DIR] [--keep]

Builds phases 1-2 of SCENE once, as ``dmrt preprocess`` does (the octree and the normals/radii,
:func:`~dmrt.preprocess.pipeline.octree_phase` and :func:`~dmrt.preprocess.pipeline.normals_radii_phase`,
on W local processes), then times phase 3 (:func:`~dmrt.preprocess.pipeline.render_depth_phase`:
every photo's depth map, written as EXR) three ways on the same work folder:

``in_process``
    This process's one GL context (``dmrt preprocess`` without ``--dask``).
``dask_1gpu``
    A ``LocalCluster`` of N workers of which one renders: all of P_HD into every map
    (``--dask local:N --dask-gpus 1``).
``dask_ngpu``
    The same cluster with its N workers rendering, one per GPU, each its share of P_HD into every
    map, the maps merged as the nearest depth (``--dask local:N --dask-gpus N``).

The cluster's start is not timed: it is started first, and each GPU worker (and this process)
warmed on a two-camera render of a few points, which makes its GL context and compiles the
depth-map programs. With ``--repeat R`` the three ways run in turn R times and each way's fastest
run counts (all are recorded). The maps of the three ways must be equal (``np.array_equal``), else the result
is written and the command exits 1. The result (JSON): points, photos, the seconds of each way,
their GPU milliseconds per stage (summed over the GPUs), their wall seconds per stage
(:func:`~dmrt.preprocess.pipeline.render_depth_phase`'s ``wall``: reading and uploading, read-backs,
each GPU task, the merge), the speed-ups (``dask_1gpu / dask_ngpu``
and ``in_process / dask_ngpu``), the GL renderers, the machine and commit (``DMRT_COMMIT`` or git)
and ``nvidia-smi``'s view of the GPUs where there is one. On a machine without NVIDIA GPUs
(llvmpipe) N defaults to 1 and the timings say nothing about GPUs; ``--gpus 2`` still runs
the split.
"""

from __future__ import annotations

import argparse
import importlib
import shutil
import subprocess
import sys
import tempfile
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np

BENCH_VERSION = 1
WAYS = ("in_process", "dask_1gpu", "dask_ngpu")
_SMI_FIELDS = ("index", "name", "uuid", "memory.total", "driver_version", "clocks.sm", "clocks.max.sm",
               "pcie.link.gen.current", "pcie.link.width.current")


def nvidia_smi() -> list[dict] | None:
    """The NVIDIA GPUs as ``nvidia-smi --query-gpu`` sees them (one dict per GPU), or None
    without the tool."""
    try:
        out = subprocess.run(["nvidia-smi", f"--query-gpu={','.join(_SMI_FIELDS)}", "--format=csv,noheader"],
                             capture_output=True, text=True, timeout=20, check=True).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    return [dict(zip(_SMI_FIELDS, (v.strip() for v in line.split(",")))) for line in out.splitlines() if line.strip()]


def _warm(_, cameras, config) -> str:
    """Make this process's GL context and compile the depth-map programs (a two-camera render of
    a few points in front of the first camera); returns the GL renderer. A Dask task, also run here."""
    from dmrt.gl import get_context, renderer_info
    from dmrt.preprocess.depthmaps import DepthMapConfig, DepthMapRenderer

    importlib.import_module("dmrt.preprocess.pipeline")  # render_depth_part's module: imported here, not timed
    ctx = get_context()
    cam = cameras[0]
    rng = np.random.default_rng(0)
    # within a metre of the point 2 m in front of the camera (COLMAP's: it looks along its +z)
    ahead = cam.center + 2.0 * cam.R[2]
    positions = (ahead + rng.uniform(-1, 1, (64, 3))).astype(np.float32)
    chunk = (positions, np.tile(np.float32([0, 0, 1]), (64, 1)), np.full(64, 0.05, np.float32))
    renderer = DepthMapRenderer(ctx, DepthMapConfig(width=config.depthmap_width, method=config.depthmap_method,
                                                    chunk_points=config.chunk_points))
    try:
        for _ in renderer.render_many(cameras[:2], lambda: iter([chunk]), resident_mb=config.resident_mb):
            pass
    finally:
        renderer.release()
    ctx.finish()
    info = renderer_info(ctx)
    return f"{info['renderer']} ({info['version']})"


def _run_way(executor, octree, cameras, names, work, out_dir, has_normals, config) -> dict:
    """Phase 3 once on ``executor``, timed; the maps go to ``out_dir/depthmaps``."""
    from dmrt.preprocess.pipeline import render_depth_phase

    wall: dict = {}
    t0 = time.perf_counter()
    rels, _, gpu_ms, renderers = render_depth_phase(executor, octree, cameras, names, work, out_dir, has_normals,
                                                    config, wall=wall)
    seconds = time.perf_counter() - t0
    return {"seconds": round(seconds, 3), "gpu_ms": {k: round(v, 3) for k, v in gpu_ms.items()}, "wall_s": wall,
            "gl_renderers": renderers, "maps": [str(Path(out_dir) / r) for r in rels]}


def _maps_equal(ways: dict) -> bool:
    """Whether every way's maps equal the in-process ones, value for value (np.array_equal)."""
    from dmrt.io.exr import read_depth_exr
    from dmrt.preprocess.parallel import default_workers

    def same(pair) -> bool:
        return np.array_equal(read_depth_exr(pair[0]), read_depth_exr(pair[1]))

    first = ways["in_process"]["maps"]
    pairs = [p for way in WAYS[1:] for p in zip(first, ways[way]["maps"], strict=True)]
    with ThreadPoolExecutor(default_workers()) as pool:  # EXR decompression releases the GIL
        return all(pool.map(same, pairs))


def run(scene_dir, gpus: int, workers: int | None, config, work: Path, repeat: int = 1,
        progress: bool = False) -> dict:
    """Phases 1-2 of ``scene_dir`` once in ``work``, then phase 3 timed the three ways, ``repeat``
    times each (see the module docstring); returns the result (without the machine and commit)."""
    from dmrt.io.scene import load_scene
    from dmrt.preprocess.parallel import DaskExecutor, InProcess, open_executor
    from dmrt.preprocess.pipeline import normals_radii_phase, octree_phase

    scene = load_scene(Path(scene_dir).resolve(), chunk_size=config.chunk_points)
    cameras = [c.relative_to(scene.origin) for c in scene.cameras]
    names = [c.name for c in scene.cameras]
    setup = {}
    # phases 1-2 as dmrt preprocess runs them; the pool is closed before the timed ways (its idle
    # processes would hold memory, not cores, but nothing of them is wanted there)
    with open_executor(None, workers=workers) as pool:
        t0 = time.perf_counter()
        octree = octree_phase(scene, work, config, pool, progress)
        setup["octree_s"] = round(time.perf_counter() - t0, 3)
        t0 = time.perf_counter()
        _, has_normals = normals_radii_phase(octree, cameras, work, config, pool, progress)
        setup["normals_radii_s"] = round(time.perf_counter() - t0, 3)
        setup["workers"] = pool.workers

    t0 = time.perf_counter()
    warm_here = _warm(0, cameras, config)
    setup["warm_in_process_s"] = round(time.perf_counter() - t0, 3)
    t0 = time.perf_counter()
    with open_executor(f"local:{gpus}", gpus_per_host=gpus) as ex:
        setup["cluster_start_s"] = round(time.perf_counter() - t0, 3)
        t0 = time.perf_counter()
        warm_there = ex.map_gpus(_warm, range(len(ex.gpu_workers)), cameras=cameras, config=config)
        setup["warm_workers_s"] = round(time.perf_counter() - t0, 3)
        # --dask-gpus 1 on the same warmed cluster: its first GPU worker
        one = DaskExecutor(ex.client, ex.spec, ex.gpu_workers[:1])
        executors = {"in_process": InProcess(), "dask_1gpu": one, "dask_ngpu": ex}
        runs = {w: [] for w in WAYS}
        for _ in range(repeat):  # the ways in turn, so that a drift in clocks or caches hits them alike
            for way in WAYS:
                out_dir = work / f"maps-{way}"
                shutil.rmtree(out_dir, ignore_errors=True)
                runs[way].append(_run_way(executors[way], octree, cameras, names, work, out_dir, has_normals, config))
        dask = {"1gpu": one.record(), "ngpu": ex.record(), "gpu_workers": ex.gpu_workers}
    # each way's fastest run (its maps are the last run's, the same every run)
    ways = {w: {**min(runs[w], key=lambda r: r["seconds"]), "maps": runs[w][-1]["maps"]} for w in WAYS}
    equal = _maps_equal(ways)
    s = {w: ways[w]["seconds"] for w in WAYS}
    return {
        "points": octree.n_points, "photos": len(cameras), "gpus": gpus,
        "seconds": s, "runs_s": {w: [r["seconds"] for r in runs[w]] for w in WAYS},
        "gpu_ms": {w: ways[w]["gpu_ms"] for w in WAYS}, "wall_s": {w: ways[w]["wall_s"] for w in WAYS},
        "speedup": {"dask_1gpu_over_ngpu": round(s["dask_1gpu"] / s["dask_ngpu"], 3),
                    "in_process_over_ngpu": round(s["in_process"] / s["dask_ngpu"], 3)},
        "gl_renderers": {**{w: ways[w]["gl_renderers"] for w in WAYS},
                         "warm_in_process": warm_here, "warm_workers": warm_there},
        "maps_equal": equal, "setup_s": setup, "dask": dask,
    }


def main(argv=None) -> int:
    from bench.workspace import commit_info, machine_info, write_json
    from dmrt.errors import DMRTError
    from dmrt.preprocess.config import PreprocessConfig
    from dmrt.preprocess.parallel import _nvidia_gpus

    defaults = PreprocessConfig()
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("scene", type=Path, help="scene folder (as dmrt preprocess takes it)")
    p.add_argument("--out", type=Path, required=True, help="result JSON file to write")
    p.add_argument("--gpus", type=int, help="GPU workers of the N-GPU way (default: this host's NVIDIA GPUs, "
                   "at least 1)")
    p.add_argument("--workers", type=int, help="local processes of phases 1-2 (default: CPU cores)")
    p.add_argument("--repeat", type=int, default=1, help="runs of each way, in turn; the fastest counts (default 1)")
    p.add_argument("--memory-limit-mb", type=float, default=defaults.memory_limit_mb)
    p.add_argument("--resident-mb", type=float, default=defaults.resident_mb)
    p.add_argument("--depthmap-width", type=int, default=defaults.depthmap_width)
    p.add_argument("--work", type=Path, help="scratch folder (default: a new one under $TMPDIR, removed after)")
    p.add_argument("--keep", action="store_true", help="keep the scratch folder (octree, attributes, maps)")
    p.add_argument("--progress", action="store_true", help="progress bars for phases 1-2")
    args = p.parse_args(argv)
    gpus = args.gpus if args.gpus is not None else max(1, _nvidia_gpus())
    for name, value in (("--gpus", gpus), ("--workers", args.workers), ("--repeat", args.repeat),
                        ("--depthmap-width", args.depthmap_width)):
        if value is not None and value < 1:
            p.error(f"{name}: must be >= 1, not {value}")
    if not args.out.parent.is_dir():
        p.error(f"--out: no folder {args.out.parent}")

    try:
        config = PreprocessConfig(depthmap_width=args.depthmap_width, memory_limit_mb=args.memory_limit_mb,
                                  resident_mb=args.resident_mb)
        work = Path(args.work or tempfile.mkdtemp(prefix="dmrt-depth-gpus-")).resolve()
        if args.work is not None and work.exists() and any(work.iterdir()):
            raise DMRTError(f"--work: {work} is not empty")
        try:
            result = run(args.scene, gpus, args.workers, config, work, args.repeat, args.progress)
        finally:
            if not args.keep:
                shutil.rmtree(work, ignore_errors=True)
    except DMRTError as exc:
        print(f"bench_depth_gpus: error: {exc}", file=sys.stderr)
        return 2
    payload = {"benchmark": "depth_gpus", "version": BENCH_VERSION, "date": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
               "scene": str(args.scene.resolve()), **result,
               "parameters": {"depthmap_width": config.depthmap_width, "method": config.depthmap_method,
                              "resident_mb": config.resident_mb, "memory_limit_mb": config.memory_limit_mb,
                              "chunk_points": config.chunk_points},
               "machine": machine_info(), "commit": commit_info(), "nvidia_smi": nvidia_smi()}
    write_json(args.out, payload)
    s, x = result["seconds"], result["speedup"]
    print(f"depth maps, {result['points']:,} points x {result['photos']} photos: in-process {s['in_process']:.2f} s, "
          f"Dask 1 GPU {s['dask_1gpu']:.2f} s, Dask {gpus} GPU{'s' * (gpus > 1)} {s['dask_ngpu']:.2f} s "
          f"({x['dask_1gpu_over_ngpu']:.2f}x over 1 GPU, {x['in_process_over_ngpu']:.2f}x over in-process); "
          f"maps {'equal' if result['maps_equal'] else 'DIFFER'}; {'; '.join(result['gl_renderers']['dask_ngpu'])}"
          f" -> {args.out}")
    return 0 if result["maps_equal"] else 1


if __name__ == "__main__":
    sys.exit(main())
