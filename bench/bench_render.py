"""Benchmark: DMRT frame times per stage over a walkthrough (the paper's Table 2 and Fig. 12).

    python -m bench.bench_render --preset paper --work /tmp/dmrt --out RESULTS_DIR
    python -m bench.bench_render --bundle BUNDLE --out RESULTS_DIR

With ``--preset`` the scene is generated and preprocessed first (one command for the GPU machine).
For every visibility path (compute, raster) and layer count, a walkthrough through the photo
cameras is rendered at 1280x720 after warm-up frames; per-stage GPU milliseconds (GL timer
queries) are recorded per frame, and medians, fps and the compute/raster ratio are written to
``render-<name>.json`` together with the GPU memory per resource.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import shutil
import time
from pathlib import Path

import numpy as np


def bundle_path(args, setup: dict) -> Path:
    """``args.bundle``, or with ``args.preset`` the preset's scene generated and preprocessed in
    ``args.work`` (``args.write_normals``: the scan carries normals); seconds go into ``setup``."""
    if not args.preset:
        return args.bundle
    from bench.scenes.synthetic import PRESETS, generate_scene
    from dmrt.preprocess.pipeline import preprocess

    shutil.rmtree(args.work, ignore_errors=True)
    t0 = time.perf_counter()
    cfg = dataclasses.replace(PRESETS[args.preset], write_normals=args.write_normals)
    scene = generate_scene(cfg, args.work / "scene")
    setup["scene_generation_s"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    out = preprocess(scene, args.work / "bundle")
    setup["preprocess_s"] = time.perf_counter() - t0
    return out


def main(argv=None) -> None:
    from dmrt.io.bundle import read_bundle
    from dmrt.gl import get_context, renderer_info
    from dmrt.runtime.renderer import RenderConfig, Renderer
    from dmrt.runtime.walkthrough import camera_path

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--bundle", type=Path)
    src.add_argument("--preset")
    p.add_argument("--work", type=Path, default=Path("/tmp/dmrt-bench"))
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=720)
    p.add_argument("--layers", type=int, nargs="+", default=[1, 3, 5, 7, 9, 11])
    p.add_argument("--methods", nargs="+", default=["compute", "raster"])
    p.add_argument("--frames", type=int, default=60, help="walkthrough frames per configuration")
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--warmup-path", action="store_true", help="warm up over the whole path (warm photo cache)")
    p.add_argument("--write-normals", action="store_true", help="synthetic scan carries normals (skips estimation)")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)

    setup = {}
    args.bundle = bundle_path(args, setup)
    bundle = read_bundle(args.bundle)
    name = args.preset or bundle.root.name
    keys = bundle.cameras[:: max(1, len(bundle.cameras) // 12)]
    path = camera_path(keys, args.frames, args.width, args.height)

    runs = []
    for method in args.methods:
        for k in args.layers:
            t0 = time.perf_counter()
            renderer = Renderer(bundle, RenderConfig(layers=k, method=method))
            setup[f"renderer_{method}_{k}_upload_s"] = time.perf_counter() - t0
            # warm-up: compile, first allocations and, with --warmup-path, a photo cache that has
            # seen the whole walkthrough (steady state) instead of cold-start streaming
            for cam in (path if args.warmup_path else path[: args.warmup]):
                renderer.render(cam)
            uploads0 = renderer.images.uploads
            per_frame, iters, surface = [], [], []
            for cam in path:
                f = renderer.render(cam)
                per_frame.append(f["timings"])
                hit = f["depth"] > 0
                surface.append(float(hit.mean()))
                iters.append(float(f["iterations"][hit].mean()) if hit.any() else 0.0)
            stages = list(per_frame[0])
            med = {s: float(np.median([t[s] for t in per_frame])) for s in stages}
            totals = [sum(t.values()) for t in per_frame]
            runs.append({"method": method, "layers": k, "median_ms": med, "median_total_ms": float(np.median(totals)),
                         "fps_min_avg_max": [1e3 / max(totals), 1e3 / float(np.mean(totals)), 1e3 / min(totals)],
                         "total_ms_per_frame": totals, "mean_iterations": float(np.mean(iters)),
                         "surface_fraction": float(np.mean(surface)),
                         "photo_uploads": renderer.images.uploads - uploads0})
            print(f"{method:8s} k={k:2d}  " + "  ".join(f"{s} {v:.3f}" for s, v in med.items())
                  + f"  total {runs[-1]['median_total_ms']:.3f} ms  iters {runs[-1]['mean_iterations']:.2f}")
            gpu_bytes = renderer.gpu_bytes
            renderer.release()
    ratio = {}
    for k in args.layers:
        r = {x["method"]: x for x in runs if x["layers"] == k}
        if {"compute", "raster"} <= set(r):
            ratio[k] = r["raster"]["median_ms"]["visibility"] / max(r["compute"]["median_ms"]["visibility"], 1e-9)
    result = {"benchmark": "render", "version": 1, "bundle": str(bundle.root), "preset": args.preset,
              "machine": {"gl": renderer_info(get_context())}, "setup_s": setup,
              "frame_size": [args.width, args.height], "frames": args.frames, "counts": bundle.meta.get("counts"),
              "runs": runs, "visibility_raster_over_compute": ratio, "gpu_bytes": gpu_bytes}
    out = args.out / f"render-{name}.json"
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
