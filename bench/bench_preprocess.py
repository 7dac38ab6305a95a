"""Benchmark: a synthetic preset from nothing to a scene bundle, in one command.

    python -m bench.bench_preprocess --preset paper --work /tmp/dmrt --out RESULTS_DIR
    python -m bench.bench_preprocess --preset many --write-normals --workers 16 --keep --work W --out R

Generates the scene, preprocesses it, and writes ``preprocess-<preset>.json`` to ``RESULTS_DIR``:
the machine (GL renderer, CPU count), the scene generation's and every phase's wall-clock seconds,
CPU seconds and peak memory per phase (``bundle.json``'s ``peak_anon_mb_per_phase``: the phase's
own peak of anonymous memory, worker processes included; ``peak_rss_mb_after``: this process's
peak resident memory when the phase ended), the depth maps' GPU milliseconds (GL timer queries),
splats sent after the frustum culling and splat throughput, the counts of ``bundle.json``
(``photos``, points, proxies, sub-sampling factors), the labeling's energy per sweep, and the peak
resident memory. Made for the GPU machine, where one command must do everything (GPU.md); with
``--keep`` the scene and the bundle stay in ``--work`` for the runtime benchmarks
(``bench.bench_render --bundle WORK/bundle``).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import time
from dataclasses import replace
from pathlib import Path


def main(argv=None) -> None:
    from bench.scenes.synthetic import PRESETS, generate_scene
    from dmrt.gl import get_context, renderer_info
    from dmrt.preprocess.parallel import open_executor
    from dmrt.preprocess.pipeline import PreprocessConfig, preprocess

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    p.add_argument("--points", type=int, help="override the preset's point count")
    p.add_argument("--photos", type=int, help="override the preset's photo count")
    p.add_argument("--photo-size", type=int, nargs=2, metavar=("W", "H"), help="override the preset's photo size")
    p.add_argument("--photographer", choices=["auto", "embree", "gl"],
                   help="override the preset's photographer (auto: OpenGL for matte photos, minutes for thousands)")
    p.add_argument("--write-normals", action="store_true", help="the scan carries normals (as the paper preset's "
                   "benchmarks: estimating them is measured apart)")
    p.add_argument("--work", type=Path, default=Path("/tmp/dmrt-bench"), help="scratch folder (scene, bundle)")
    p.add_argument("--out", type=Path, required=True, help="folder for the results JSON")
    p.add_argument("--depthmap-width", type=int, default=1024)
    p.add_argument("--method", choices=["compute", "raster"], default="compute")
    p.add_argument("--memory-limit-mb", type=float, default=2048)
    p.add_argument("--workers", type=int, default=1, help="processes for the CPU phases (dmrt preprocess --workers)")
    p.add_argument("--keep", action="store_true", help="keep the scene and bundle in --work")
    args = p.parse_args(argv)

    overrides = {k: v for k, v in (("points", args.points), ("photos", args.photos),
                                   ("photo_size", args.photo_size and tuple(args.photo_size)),
                                   ("photographer", args.photographer)) if v is not None}
    cfg = replace(PRESETS[args.preset], **overrides, write_normals=args.write_normals or PRESETS[args.preset].write_normals)
    shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scene = generate_scene(cfg, args.work / "scene")
    t_scene = time.perf_counter() - t0
    t0 = time.perf_counter()
    with open_executor(None, workers=args.workers) as executor:
        bundle = preprocess(scene, args.work / "bundle",
                            PreprocessConfig(depthmap_width=args.depthmap_width, depthmap_method=args.method,
                                             memory_limit_mb=args.memory_limit_mb), executor=executor)
    t_pre = time.perf_counter() - t0
    meta = json.loads((bundle / "bundle.json").read_text())
    counts, timings = meta["counts"], meta["timings"]
    gpu = timings.get("depthmaps_gpu_ms", {})
    splat_ms = gpu.get("depthmap", 0.0)
    culling = meta.get("depthmap_splats", {})
    splats = culling.get("splats", counts["points"] * counts["photos"])
    result = {
        "benchmark": "preprocess", "version": 2, "preset": args.preset,
        "machine": {"gl": renderer_info(get_context()), "cpus": os.cpu_count(), "platform": platform.platform()},
        "parameters": {"scene": meta["parameters"], "synth": {"points": cfg.points, "photos": cfg.photos,
                                                              "photo_size": cfg.photo_size, "rooms": cfg.rooms,
                                                              "write_normals": cfg.write_normals},
                       "workers": args.workers, "commit": os.environ.get("DMRT_COMMIT")},
        "seconds": {"scene_generation": round(t_scene, 2), "preprocess": round(t_pre, 2), **timings},
        "cpu_s_per_phase": meta.get("cpu_s_per_phase"),
        "memory_mb": {"peak_anon_per_phase": meta.get("peak_anon_mb_per_phase"),
                      "peak_rss_after_phase": meta.get("peak_rss_mb_after")},
        # splats: sent to the GPU after the frustum culling (splats_all: every point for every photo)
        "depthmaps": {"splats": splats, "splats_all": culling.get("splats_all"),
                      "culled_fraction": culling.get("culled_fraction"), "mode": culling.get("modes"),
                      "gpu_splat_ms": splat_ms, "gpu_upload_ms": gpu.get("depthmap_upload"),
                      "gpu_readback_ms": gpu.get("depthmap_readback"),
                      "splats_per_s_gpu": splats / (splat_ms / 1e3) if splat_ms else None,
                      "splats_per_s_wall": splats / timings["depthmaps_s"] if timings["depthmaps_s"] else None},
        "counts": counts, "labeling": meta["labeling"], "photometric": meta.get("photometric"),
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    path = args.out / f"preprocess-{args.preset}.json"
    path.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: result[k] for k in ("seconds", "memory_mb", "depthmaps", "peak_rss_mb")}, indent=1))
    print(f"wrote {path}")
    if not args.keep:
        shutil.rmtree(args.work, ignore_errors=True)


if __name__ == "__main__":
    main()
