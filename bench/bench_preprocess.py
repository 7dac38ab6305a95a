"""Benchmark: a synthetic preset from nothing to a scene bundle, in one command.

    python -m bench.bench_preprocess --preset paper --work /tmp/dmrt --out RESULTS_DIR

Generates the scene, preprocesses it, and writes ``preprocess-<preset>.json`` to ``RESULTS_DIR``:
the machine (GL renderer, CPU count), every phase's wall-clock seconds, the depth maps' GPU
milliseconds (GL timer queries) and splat throughput, the counts of ``bundle.json`` (points,
proxies, sub-sampling factors), the labeling's energy per sweep, and the peak resident memory.
Made for the GPU machine, where one command must do everything (GPU.md).
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
    from dmrt.preprocess.pipeline import PreprocessConfig, preprocess

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    p.add_argument("--points", type=int, help="override the preset's point count")
    p.add_argument("--work", type=Path, default=Path("/tmp/dmrt-bench"), help="scratch folder (scene, bundle)")
    p.add_argument("--out", type=Path, required=True, help="folder for the results JSON")
    p.add_argument("--depthmap-width", type=int, default=1024)
    p.add_argument("--method", choices=["compute", "raster"], default="compute")
    p.add_argument("--memory-limit-mb", type=float, default=2048)
    p.add_argument("--keep", action="store_true", help="keep the scene and bundle in --work")
    args = p.parse_args(argv)

    cfg = PRESETS[args.preset] if args.points is None else replace(PRESETS[args.preset], points=args.points)
    shutil.rmtree(args.work, ignore_errors=True)
    args.work.mkdir(parents=True)
    args.out.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    scene = generate_scene(cfg, args.work / "scene")
    t_scene = time.perf_counter() - t0
    t0 = time.perf_counter()
    bundle = preprocess(scene, args.work / "bundle",
                        PreprocessConfig(depthmap_width=args.depthmap_width, depthmap_method=args.method,
                                         memory_limit_mb=args.memory_limit_mb))
    t_pre = time.perf_counter() - t0
    meta = json.loads((bundle / "bundle.json").read_text())
    counts, timings = meta["counts"], meta["timings"]
    gpu = timings.get("depthmaps_gpu_ms", {})
    splat_ms = gpu.get("depthmap", 0.0)
    splats = counts["points"] * counts["photos"]
    result = {
        "benchmark": "preprocess", "version": 1, "preset": args.preset,
        "machine": {"gl": renderer_info(get_context()), "cpus": os.cpu_count(), "platform": platform.platform()},
        "parameters": {"scene": meta["parameters"], "synth": {"points": cfg.points, "photos": cfg.photos,
                                                              "photo_size": cfg.photo_size}},
        "seconds": {"scene_generation": round(t_scene, 2), "preprocess": round(t_pre, 2), **timings},
        "depthmaps": {"splats": splats, "gpu_splat_ms": splat_ms, "gpu_upload_ms": gpu.get("depthmap_upload"),
                      "splats_per_s_gpu": splats / (splat_ms / 1e3) if splat_ms else None,
                      "splats_per_s_wall": splats / timings["depthmaps_s"] if timings["depthmaps_s"] else None},
        "counts": counts, "labeling": meta["labeling"],
        "peak_rss_mb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    }
    path = args.out / f"preprocess-{args.preset}.json"
    path.write_text(json.dumps(result, indent=1))
    print(json.dumps({k: result[k] for k in ("seconds", "depthmaps", "peak_rss_mb")}, indent=1))
    print(f"wrote {path}")
    if not args.keep:
        shutil.rmtree(args.work, ignore_errors=True)


if __name__ == "__main__":
    main()
