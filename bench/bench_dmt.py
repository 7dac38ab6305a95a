"""Benchmark: DMT against DMRT - labeling time and frame rate (the paper's Table 3 and Fig. 12).

    python -m bench.bench_dmt --bundle BUNDLE --resolutions 256 512 1024 --frames 120 --out dmt.json

For each DMT depth-map resolution: the labeling of every depth map (graph cut per map, timed in
this run unless ``--reuse-labels``; cached in the bundle under ``dmt/<W>/``) and a walkthrough
rendered with :class:`baselines.dmt.DMTRenderer`; then the same walkthrough with DMRT
(:class:`dmrt.runtime.renderer.Renderer`, ``--layers`` label layers, the bundle's own depth maps). Frame
times are GPU milliseconds (GL timer queries, the sum of every stage) per frame; fps = 1000 / that,
min / avg / max as in Table 3 (avg = 1000 / mean frame time). DMRT's labeling time is the bundle's
(``bundle.json`` timings: candidates + graph cut, the same work DMT's figure covers); the ratio
DMT / DMRT is the paper's "26x at 1024x684". On a software renderer (llvmpipe) GPU timings are
meaningless: ``gpu_timer_reliable`` is then false and wall-clock milliseconds are recorded beside.

``--labeler wta`` skips the graph cuts (winner-take-all labels; for frame rates on large scenes,
whose rendering cost does not depend on the labels). The core is :func:`run`, for the harness.
"""

from __future__ import annotations

import argparse
import json
import os
import time
from pathlib import Path

import numpy as np

from dmrt.io.atomic import write_text

VERSION = 1


def _walk(renderer, cameras, warmup: int) -> dict:
    """Render ``cameras`` after ``warmup`` frames; per-frame GPU ms, fps and statistics. The timed
    frames stay on the GPU (``readback=False``), as in interactive use."""
    for cam in cameras[:warmup]:
        renderer.render(cam)
    totals, wall, stages, drawn = [], [], [], []
    for cam in cameras:
        t0 = time.perf_counter()
        f = renderer.render(cam, readback=False)
        wall.append((time.perf_counter() - t0) * 1e3)
        stages.append(f["timings"])
        totals.append(float(sum(f["timings"].values())))
        if "stats" in f:
            drawn.append(f["stats"]["maps_drawn"])
    fps = [1e3 / max(t, 1e-9) for t in totals]
    out = {"gpu_ms_per_frame": totals, "fps_per_frame": fps, "wall_ms_per_frame": wall,
           "fps_min_avg_max": [1e3 / max(totals), 1e3 / float(np.mean(totals)), 1e3 / max(min(totals), 1e-9)],
           "median_ms": {s: float(np.median([t[s] for t in stages])) for s in stages[0]},
           "median_total_ms": float(np.median(totals)), "gpu_bytes": dict(renderer.gpu_bytes)}
    if drawn:
        out["maps_drawn_mean"] = float(np.mean(drawn))
    return out


def run(bundle_path, resolutions=(256, 512, 1024), frames: int = 60, width: int = 1280, height: int = 720,
        labeler: str = "graphcut", layers: int = 5, warmup: int = 5, path=None, reuse_labels: bool = False,
        epsilon: float | None = None, dmrt: bool = True, progress: bool = True) -> dict:
    """Labeling times and walkthrough frame rates of DMT per resolution and of DMRT, one run.

    Parameters
    ----------
    bundle_path : a preprocessed bundle (its depth maps at least as wide as the largest resolution).
    resolutions : DMT depth-map widths (heights follow the photos' aspect).
    frames, width, height : walkthrough length and frame size (default path: through every
        ``n / 12``-th photo camera, :func:`dmrt.runtime.walkthrough.camera_path`).
    labeler : "graphcut" (timing comparisons) or "wta".
    layers : DMRT label layers (paper's comparison: 5).
    warmup : frames rendered before timing (compilation, first allocations, photo cache).
    path : camera path JSON (``dmrt path``) instead of the default walkthrough.
    reuse_labels : load cached DMT labels (their recorded time is reported) instead of relabeling.
    epsilon : DMT stitching threshold (default DMTConfig's).
    dmrt : also run DMRT.

    Returns
    -------
    dict (JSON-ready): ``dmt`` list per resolution {width, size, labeling {seconds, cached,
    candidates_s, costs_s, cut_s, texels}, labeling_ratio_dmt_over_dmrt, fps_min_avg_max,
    gpu_ms_per_frame, fps_per_frame, median_ms per stage, gpu_bytes} (or {width, error}),
    ``dmrt`` {labeling_s, fps_min_avg_max, ...}, ``fps_ratio_dmrt_over_dmt`` per width, machine info.
    """
    from baselines.dmt import DMTConfig, DMTLabelingConfig, DMTRenderer, dmt_labels
    from baselines.dmt.geometry import dmt_size
    from dmrt.io.bundle import read_bundle
    from dmrt.errors import InputError
    from dmrt.gl import get_context, renderer_info
    from dmrt.runtime.walkthrough import camera_path, load_path

    bundle = read_bundle(bundle_path)
    cams = bundle.cameras
    cameras = load_path(path) if path else camera_path(cams[:: max(1, len(cams) // 12)], frames, width, height)
    t = bundle.meta.get("timings", {})
    dmrt_label_s = float(t.get("candidates_s", 0.0)) + float(t.get("labeling_s", 0.0))
    info = renderer_info(get_context())
    result = {"benchmark": "dmt", "version": VERSION, "bundle": str(bundle.root), "frames": len(cameras),
              "frame_size": [width, height], "labeler": labeler, "machine": {"gl": info, "cpus": os.cpu_count()},
              "gpu_timer_reliable": not info["is_software"], "counts": bundle.meta.get("counts"),
              "dmrt_labeling_s": {"candidates_s": t.get("candidates_s"), "labeling_s": t.get("labeling_s"),
                                  "total_s": dmrt_label_s},
              "dmt": []}
    for w in resolutions:
        entry = {"width": int(w), "size": list(dmt_size(cams[0], int(w)))}
        try:
            labels, meta = dmt_labels(bundle, int(w), DMTLabelingConfig(labeler=labeler), progress=progress,
                                      recompute=not reuse_labels)
        except InputError as exc:
            entry["error"] = str(exc)
            result["dmt"].append(entry)
            print(f"DMT {w}: skipped ({exc})")
            continue
        entry["labeling"] = {"seconds": meta["timings"]["total_s"], "cached": meta["cached"],
                             **{k: meta["timings"][k] for k in ("candidates_s", "costs_s", "cut_s")},
                             "texels": meta["counts"]["texels"], "energy": meta["energy"]}
        entry["labeling_ratio_dmt_over_dmrt"] = meta["timings"]["total_s"] / dmrt_label_s if dmrt_label_s else None
        cfg = DMTConfig(width=int(w), labeler=labeler, progress=progress,
                        **({} if epsilon is None else {"epsilon": float(epsilon)}))
        renderer = DMTRenderer(bundle, cfg, labels=labels)
        entry.update(_walk(renderer, cameras, warmup))
        entry["config"] = {"epsilon": cfg.epsilon, "discontinuity_threshold": cfg.discontinuity_threshold}
        renderer.release()
        result["dmt"].append(entry)
    if dmrt:
        from dmrt.runtime.renderer import RenderConfig, Renderer

        renderer = Renderer(bundle, RenderConfig(layers=layers))
        result["dmrt"] = {"layers": layers, "labeling_s": dmrt_label_s, **_walk(renderer, cameras, warmup)}
        renderer.release()
        avg = result["dmrt"]["fps_min_avg_max"][1]
        result["fps_ratio_dmrt_over_dmt"] = {str(e["width"]): avg / e["fps_min_avg_max"][1]
                                             for e in result["dmt"] if "fps_min_avg_max" in e}
    return result


def print_table(result: dict) -> None:
    """Table 3 layout: labeling time, DMT/DMRT labeling ratio, min/avg/max fps per method."""
    def fps(e):
        return "/".join(f"{v:.1f}" for v in e["fps_min_avg_max"])

    print(f"{'method':<18}{'labeling':>12}{'DMT/DMRT':>10}{'fps min/avg/max':>24}{'median GPU ms':>15}")
    for e in result["dmt"]:
        name = f"DMT {e['size'][0]}x{e['size'][1]}"
        if "error" in e:
            print(f"{name:<18}  {e['error']}")
            continue
        lab = e["labeling"]
        ratio = e["labeling_ratio_dmt_over_dmrt"]
        print(f"{name:<18}{lab['seconds']:>11.1f}s{(f'{ratio:.1f}x' if ratio else '-'):>10}{fps(e):>24}"
              f"{e['median_total_ms']:>15.2f}" + ("  (labels cached)" if lab["cached"] else ""))
    if "dmrt" in result:
        d = result["dmrt"]
        print(f"{'DMRT (' + str(d['layers']) + ' layers)':<18}{d['labeling_s']:>11.1f}s{'1.0x':>10}{fps(d):>24}"
              f"{d['median_total_ms']:>15.2f}")
    if not result["gpu_timer_reliable"]:
        print("(software GL renderer: GPU timings are meaningless here; see wall_ms_per_frame)")


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--bundle", type=Path, required=True)
    p.add_argument("--resolutions", type=int, nargs="+", default=[256, 512, 1024])
    p.add_argument("--frames", type=int, default=60, help="walkthrough frames")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=720)
    p.add_argument("--labeler", choices=["graphcut", "wta", "own"], default="graphcut")
    p.add_argument("--layers", type=int, default=5, help="DMRT label layers")
    p.add_argument("--warmup", type=int, default=5)
    p.add_argument("--path", type=Path, help="camera path JSON (dmrt path) instead of the default walkthrough")
    p.add_argument("--reuse-labels", action="store_true", help="load cached DMT labels instead of relabeling")
    p.add_argument("--epsilon", type=float, help="DMT stitching threshold, metres")
    p.add_argument("--no-dmrt", action="store_true", help="skip the DMRT walkthrough")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--out", type=Path, required=True, help="results JSON file")
    args = p.parse_args(argv)
    result = run(args.bundle, args.resolutions, args.frames, args.width, args.height, args.labeler, args.layers,
                 args.warmup, args.path, args.reuse_labels, args.epsilon, not args.no_dmrt, not args.quiet)
    print_table(result)
    write_text(args.out, json.dumps(result, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
