"""Benchmark: DMRT frame times per stage over a walkthrough (the paper's Table 2 and Fig. 12), per
visibility path, layer count and frame size.

    python -m bench.bench_render --preset paper --work /tmp/dmrt --out RESULTS_DIR \
        --methods tiles compute kbuffer --layers 5 --sizes 1280x720 3840x2160
    python -m bench.bench_render --bundle BUNDLE --out RESULTS_DIR

With ``--preset`` the scene is generated and preprocessed first (one command for the GPU machine).
Every configuration renders the same walkthrough through the photo cameras as ``dmrt bench``'s
Table 2 does (:func:`bench.experiments.measure_walkthrough`): a read-back pass that warms up the GPU
clocks and the photo cache, then the timed pass, frames back to back and left on the GPU. Per-stage
GPU milliseconds (GL timer queries), median and p95 of the GPU total and of the wall-clock
``render()`` call, and the SM clocks seen (nvidia-smi) go to ``render-<name>.json`` with the GPU
memory per resource.
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
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


def walk_keys(cameras: list, walk_photos: int = 0) -> list:
    """The walkthrough's 12 key cameras (``--walk-photos``): every n/12-th of ``cameras`` in their
    order, or with ``walk_photos`` N > 0 of the first N along the scene's longer horizontal extent
    (a stretch of it)."""
    span = cameras
    if walk_photos:
        centres = np.array([c.center for c in cameras])
        axis = int(np.argmax(np.ptp(centres[:, :2], axis=0)))
        span = [cameras[i] for i in np.argsort(centres[:, axis], kind="stable")[:walk_photos]]
    return span[:: max(1, len(span) // 12)]


def open_bundle(p: argparse.ArgumentParser, args, setup: dict):
    """:func:`bundle_path` read (``args.bundle`` set to its path): a bundle that cannot be read ends the
    program with one line that names it and exit status 2, before anything is written."""
    from dmrt.errors import DMRTError
    from dmrt.io.bundle import read_bundle

    try:
        args.bundle = bundle_path(args, setup)
        return read_bundle(args.bundle)
    except DMRTError as exc:
        p.exit(2, f"{p.prog}: error: {exc}\n")


def add_source_args(p: argparse.ArgumentParser, work: str) -> None:
    """``--bundle BUNDLE`` or ``--preset NAME`` (made in ``--work``, default ``work``), and ``--out``."""
    src = p.add_mutually_exclusive_group(required=True)
    src.add_argument("--bundle", type=Path)
    src.add_argument("--preset")
    p.add_argument("--work", type=Path, default=Path(work))
    p.add_argument("--out", type=Path, required=True)


def _depth_change(first_steps: int, first: list, depths: list) -> dict:
    """What a step cap changes against the first one, over the same walkthrough's frames ((h, w)
    float32 camera z, 0 = background): ``pixels_differing`` (fraction whose depth differs),
    ``background_change`` (fraction of background pixels, this cap minus the first)."""
    return {"max_steps": first_steps,
            "pixels_differing": float(np.mean([np.mean(a != b) for a, b in zip(first, depths)])),
            "background_change": float(np.mean([np.mean(b == 0) - np.mean(a == 0) for a, b in zip(first, depths)]))}


def _budget(text: str) -> float | None:
    """``--cache-mb``'s values: MiB, or ``auto`` (None: RenderConfig's default)."""
    return None if text == "auto" else float(text)


_budget.__name__ = "MiB or auto"  # argparse's "invalid ... value" names the type by it


def _mb(budget: float | None) -> str:
    """A cache budget for the progress line: MiB, or the config's default ("auto")."""
    return "auto" if budget is None else f"{budget:g}MB"


def main(argv=None) -> None:
    from bench.experiments import measure_walkthrough, profile_walkthrough
    from dmrt.gl import get_context, renderer_info
    from dmrt.runtime.renderer import RenderConfig
    from dmrt.errors import DMRTError
    from dmrt.runtime.walkthrough import camera_path, load_path, save_path

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_source_args(p, "/tmp/dmrt-bench")
    p.add_argument("--sizes", nargs="+", default=["1280x720"], help="frame sizes WxH (default: 1280x720)")
    p.add_argument("--layers", type=int, nargs="+", default=[1, 3, 5, 7, 9, 11])
    p.add_argument("--methods", nargs="+", default=["compute", "raster"])
    p.add_argument("--refine", nargs="+", default=["illinois"], help="hit refinements (RenderConfig.refine)")
    p.add_argument("--tile-check", nargs="+", default=["frame"], help="tiles list checks (RenderConfig.tile_check)")
    p.add_argument("--tile-split", type=int, nargs="+", default=[RenderConfig().tile_split],
                   help="tiles: lists longer than this split over workgroups (RenderConfig.tile_split; 0 = never): "
                        "0 and the default side by side show what the split saves on a walk whose discs pile up; "
                        "each value after the first records its statistics pass's frames against the first's "
                        "(frames_vs_first_split: frames whose depth or label differs anywhere, 0 expected)")
    p.add_argument("--photo-choice", nargs="+", default=["labels"], choices=["labels", "view"],
                   help="photo choices (RenderConfig.photo_choice), each with the other options at their defaults")
    p.add_argument("--map-cache-mb", type=float, nargs="+", default=[0.0],
                   help="depth-map cache budgets (RenderConfig.map_cache_mb; 0 = one texture array's worth)")
    p.add_argument("--cache-mb", type=_budget, nargs="+", default=[RenderConfig().cache_mb],
                   help="full-resolution photo cache budgets (RenderConfig.cache_mb, MiB, or auto: the config's "
                        "default, sized from the GPU's free memory, its size in gpu_bytes.image_cache; default auto): a "
                        "walk that wants more photos than the cache holds uploads photos in every frame")
    p.add_argument("--max-steps", type=int, nargs="+", default=[100],
                   help="iterative-search steps per layer (RenderConfig.max_steps; the paper: 100). A lower cap "
                        "shortens the few searches that do not converge, which set their warps' time; it also "
                        "changes some pixels: each cap after the first records what it changes against the first "
                        "(depth_vs_first_cap: pixels whose depth differs, background change); Figs. 8 and 13 must "
                        "be measured with a cap before it becomes a default")
    p.add_argument("--fenced", action="store_true", help="glFinish around every timed section: each stage's "
                   "and part's own GPU time (slower frames; see dmrt.gl.timer.GpuTimer.fenced)")
    p.add_argument("--passes", action="store_true", help="each pass of the tile lists timed as a part of its own "
                   "(visibility:lists_*; see dmrt.gl.timer.GpuTimer.passes)")
    p.add_argument("--leveling", action=argparse.BooleanOptionalAction, default=True,
                   help="screen-space leveling, as the paper's texturing pass (default: on)")
    p.add_argument("--frames", type=int, default=30, help="walkthrough frames per configuration")
    p.add_argument("--walk-photos", type=int, default=0, metavar="N",
                   help="the walkthrough's 12 key cameras spread over the N photos first along the scene's "
                        "longer horizontal extent (default 0: over all photos, in their order). The path's length "
                        "sets how far a frame moves: on a scene with thousands of photos, all of them put the "
                        "whole scene into 30 frames (every frame a new place, every map new); N photos at the "
                        "paper scene's density (many: 960, about its first 12 rooms, as the paper preset's 192 "
                        "photos are its 12) keep the paper's walking speed")
    p.add_argument("--keys", type=Path, metavar="PATH_JSON",
                   help="the walkthrough's key cameras from a camera path file (--save-keys of another run: the same "
                        "walk through a scene of the same geometry with other photos) instead of the bundle's photos")
    p.add_argument("--save-keys", type=Path, metavar="PATH_JSON", help="write the walkthrough's key cameras here")
    p.add_argument("--cpu-profile", action="store_true", help="also profile the CPU while it issues the frames "
                   "back to back (cProfile: Python and each GL call's own time; cpu_profile in the JSON)")
    p.add_argument("--write-normals", action="store_true", help="synthetic scan carries normals (skips estimation)")
    args = p.parse_args(argv)
    if args.walk_photos and args.walk_photos < 2:
        p.exit(2, f"{p.prog}: error: --walk-photos: {args.walk_photos} photos give no path (at least 2 key "
                  f"cameras; 0 = all)\n")
    if args.keys and args.walk_photos:
        p.exit(2, f"{p.prog}: error: --keys and --walk-photos both choose the walk's key cameras: give one\n")
    try:
        given_keys = load_path(args.keys) if args.keys else None
    except DMRTError as exc:
        p.exit(2, f"{p.prog}: error: --keys: {exc}\n")
    if given_keys is not None and len(given_keys) < 2:
        p.exit(2, f"{p.prog}: error: --keys: {args.keys} holds {len(given_keys)} camera (a walk needs 2)\n")
    setup = {}
    bundle = open_bundle(p, args, setup)
    args.out.mkdir(parents=True, exist_ok=True)
    name = args.preset or bundle.root.name
    keys = given_keys or walk_keys(bundle.cameras, args.walk_photos)
    if args.walk_photos:
        name += f"-walk{args.walk_photos}"
    if args.keys:
        name += f"-keys-{args.keys.stem}"
    if args.save_keys:
        save_path(args.save_keys, keys)
    runs = []
    # with several step caps, the first one's depths (statistics pass) and what the others change
    reference: dict[tuple, tuple[int, list]] = {}
    split_reference: dict[tuple, tuple[int, list, list]] = {}  # the first --tile-split's frames
    for size in args.sizes:
        w, h = (int(v) for v in size.lower().split("x"))
        path = camera_path(keys, args.frames, w, h)
        for method, refine, check, split, steps, k, choice, maps_mb, photos_mb in itertools.product(
                args.methods, args.refine, args.tile_check, args.tile_split, args.max_steps, args.layers,
                args.photo_choice, args.map_cache_mb, args.cache_mb):
            if (check != "frame" or split != args.tile_split[0]) and method != "tiles":
                continue
            config = RenderConfig(layers=k, method=method, leveling=args.leveling, refine=refine, tile_check=check,
                                  tile_split=split, max_steps=steps, photo_choice=choice, map_cache_mb=maps_mb,
                                  cache_mb=photos_mb)
            depths: list[np.ndarray] = []
            labels: list[np.ndarray] = []

            def keep(f):
                depths.append(f["depth"].copy())
                labels.append(f["label"].copy())
            if len(args.max_steps) == 1 and len(args.tile_split) == 1:
                keep = None
            r = measure_walkthrough(bundle, config, path,
                                    f"{method} {choice} maps={maps_mb:g}MB photos={_mb(photos_mb)} k={k} {w}x{h}",
                                    fenced=args.fenced, passes=args.passes, on_frame=keep)
            r.pop("stage_ms_per_frame")
            if args.cpu_profile:
                r["cpu_profile"] = profile_walkthrough(bundle, config, path)
            if len(args.max_steps) > 1:
                first_steps, first = reference.setdefault((w, h, method, refine, check, split, k, choice), (steps, depths))
                if first is not depths:
                    r["depth_vs_first_cap"] = _depth_change(first_steps, first, depths)
            if len(args.tile_split) > 1:  # the split changes no frame: counted on this GPU
                first_split, first_d, first_l = split_reference.setdefault(
                    (w, h, method, refine, check, steps, k, choice, maps_mb, photos_mb), (split, depths, labels))
                if first_d is not depths:
                    r["frames_vs_first_split"] = {
                        "tile_split": first_split, "frames": len(depths),
                        "frames_differing": sum(not (np.array_equal(a, b) and np.array_equal(c, d))
                                                for a, b, c, d in zip(first_d, depths, first_l, labels))}
            runs.append({"method": method, "refine": refine, "tile_check": check, "tile_split": split,
                         "max_steps": steps, "layers": k,
                         "photo_choice": choice, "map_cache_mb": maps_mb, "cache_mb": photos_mb, **r})
            stages = "  ".join(f"{s} {v:.3f}" for s, v in {**r["median_ms"], **r["median_part_ms"]}.items())
            print(f"{w}x{h} {method:8s} {choice:6s} split={split} maps={r['map_cache']['slots']} photos={_mb(photos_mb)} "
                  f"{refine:9s} {check:6s} steps={steps:3d} k={k:2d}  {stages}"
                  + f"  | GPU median {r['median_total_ms']:.3f} p95 {r['p95_total_ms']:.3f} ms, wall median "
                    f"{r['median_wall_ms']:.3f} p95 {r['p95_wall_ms']:.3f} ms, sustained {r['sustained_ms']:.3f} "
                    f"ms/frame, {r['mean_iterations']:.2f} steps, status reads {r['status_reads_per_frame']:.2f}/frame, "
                    f"split in {'-' if r['split_frames_sustained'] is None else format(r['split_frames_sustained'], '.0%')} "
                    "of the sustained frames, "
                    f"render() call {r['sustained_call_ms']['median']:.3f} ms (the CPU's issue + waits), "
                    f"sustained timed: wall {r['sustained_timed']['wall_ms']:.3f} ms/frame, GPU median "
                    f"{r['sustained_timed']['median_total_ms']:.3f} = " + "  ".join(
                        f"{k} {v:.3f}" for k, v in {**r['sustained_timed']['median_ms'],
                                                    **r['sustained_timed']['median_part_ms']}.items()) + ", "
                    f"clocks {r['gpu_clocks']}, map loads {r['map_cache']['loads_timed']} and "
                    f"{r['map_cache']['missing_per_frame_timed']:.1f} missing/frame in the timed pass", flush=True)
    result = {"benchmark": "render", "version": 2, "bundle": str(bundle.root), "preset": args.preset,
              "fenced": args.fenced, "passes": args.passes,
              "machine": {"gl": renderer_info(get_context())}, "setup_s": setup, "frames": args.frames,
              "leveling": args.leveling, "walk_photos": args.walk_photos,
              "keys": str(args.keys) if args.keys else None, "counts": bundle.meta.get("counts"),
              "runs": runs}
    out = args.out / f"render-{name}.json"
    out.write_text(json.dumps(result, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
