"""Benchmark: DMT against DMRT - labeling time and frame rate (the paper's Table 3 and Fig. 12).

    python -m bench.bench_dmt --bundle BUNDLE --resolutions 256 512 1024 --frames 120 --out dmt.json

For each DMT depth-map resolution: the graph-cut labeling of the depth maps (one map per process
on every core, :func:`baselines.dmt.labeling.label_maps`; timed in this run unless
``--reuse-labels``) and a walkthrough rendered with :class:`baselines.dmt.DMTRenderer`; then the
same walkthrough with DMRT (:class:`dmrt.runtime.renderer.Renderer`, ``--layers`` label layers,
the bundle's own depth maps). Frame times are GPU milliseconds (GL timer queries, the sum of every
stage) per frame; fps = 1000 / that, min / avg / max as in Table 3 (avg = 1000 / mean frame time).
On a software renderer (llvmpipe) GPU timings are meaningless: ``gpu_timer_reliable`` is then
false and wall-clock milliseconds are recorded beside.

Labeling time is given twice: wall-clock seconds and CPU seconds (each map's
:func:`time.process_time` in the process that labelled it, summed). DMRT's side is its
preprocessing's labeling work (candidates + graph cut, the same work DMT's figure covers), run
again here on the bundle's proxies in one process and timed the same two ways
(:func:`dmrt_labeling`); the paper's "26x at 1024x684" compares CPU time, so the CPU ratio
DMT / DMRT is the one to set beside it, the wall ratio the one a user waits for.

``--budget-s``: when all maps of a resolution do not fit in that many wall-clock seconds (judged from
one map per process, labelled first), a seeded random subset that fits is labelled instead, its
per-map CPU seconds are reported (median, p10, p90) and extrapolated to every map (mean x maps;
wall = that / the parallelism measured on the subset); the walkthrough then renders with each
map's own photo as labels (frame rates do not depend on the labels' values). A map's CPU seconds
include decoding the photos its process has not cached yet, which a whole run shares among more
maps: a small subset's extrapolation errs high.

``--labeler wta|own`` skips the graph cuts (winner-take-all / own-photo labels: frame rates only).
The core is :func:`run`, for the harness.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import time
from pathlib import Path

import numpy as np

from dmrt.errors import ConfigError, DMRTError
from dmrt.io.atomic import write_text

VERSION = 2


def _walk(renderer, cameras, warmup: int) -> dict:
    """Render ``cameras`` after ``warmup`` frames; per-frame GPU ms, fps and statistics. The timed
    frames stay on the GPU (``readback=False``), as in interactive use; each frame's own times
    (the timer waits for them: :attr:`dmrt.gl.GpuTimer.wait`)."""
    renderer.timer.wait = True
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


# ------------------------------------------------------------------------------------------------
# labeling times
# ------------------------------------------------------------------------------------------------
def labeling_record(cpu_per_map, wall_s: float, n_total: int) -> dict:
    """Wall and CPU seconds of the labelled maps, and their extrapolation to all ``n_total`` maps.

    Parameters
    ----------
    cpu_per_map : CPU seconds of each labelled map.
    wall_s : wall clock over them (all processes together).
    n_total : the maps there are.

    Returns
    -------
    dict: ``maps``, ``maps_total``, ``extrapolated`` (fewer maps than there are), ``wall_s``,
    ``cpu_s`` (sum), ``parallelism`` (cpu_s / wall_s: the processes' effective number),
    ``cpu_s_per_map`` {mean, median, p10, p90}, ``cpu_s_all`` (mean x n_total; the sum when every
    map was labelled) and ``wall_s_all`` (cpu_s_all / parallelism; wall_s when every map was).
    """
    cpu = np.asarray(cpu_per_map, np.float64)
    if cpu.size == 0:
        raise ValueError("labeling_record needs at least one labelled map")
    wall_s = max(float(wall_s), 1e-6)  # a cache's times are rounded to ms: "own" labels can read 0
    total = float(cpu.sum())
    parallelism = total / wall_s
    complete = cpu.size >= n_total
    cpu_all = total if complete else float(cpu.mean()) * n_total
    return {"maps": int(cpu.size), "maps_total": int(n_total), "extrapolated": not complete,
            "wall_s": float(wall_s), "cpu_s": total, "parallelism": parallelism,
            "cpu_s_per_map": {"mean": float(cpu.mean()), "median": float(np.median(cpu)),
                              "p10": float(np.percentile(cpu, 10)), "p90": float(np.percentile(cpu, 90))},
            "cpu_s_all": cpu_all, "wall_s_all": float(wall_s) if complete else cpu_all / parallelism}


def subset_size(probe_cpu, probe_wall_s: float, n_total: int, budget_s: float) -> int:
    """How many maps to label, the probe's included, to stay within ``budget_s`` wall-clock seconds.

    The probe (one map per process, labelled first) gives the mean CPU seconds per map and the
    parallelism reached (summed CPU / wall; below the process count when the maps' times differ,
    so the estimate errs on the safe side). ``n_total`` when every map fits in what the probe
    left of the budget, or when the maps that do not fit would not fill one more round of the
    processes (labelling them costs at most that round: on the paper preset the estimate once
    left out 1 of 192 maps); else the probe's maps plus as many as fit in it.
    """
    cpu = np.asarray(probe_cpu, np.float64)
    mean = float(cpu.mean())
    if mean <= 0:
        return int(n_total)
    parallelism = max(float(cpu.sum()) / max(probe_wall_s, 1e-9), 1.0)
    left = budget_s - probe_wall_s
    if n_total * mean / parallelism <= left:
        return int(n_total)
    k = int(min(n_total - 1, cpu.size + max(0, math.floor(left * parallelism / mean))))
    return int(n_total) if n_total - k < cpu.size else k


def time_graphcut(bundle, width: int, workers: int | None = None, budget_s: float | None = None, seed: int = 0,
                  progress: bool = True) -> tuple[list | None, dict]:
    """DMT's graph-cut labeling of ``bundle``'s depth maps at ``width``, timed.

    ``workers`` processes (None: every core) label one map at a time each. Every map is labelled
    (and the labels cached in the bundle) when ``budget_s`` is None, when there are no more maps
    than processes (one round), or when the probe (one map per process, labelled first) says all
    fit in ``budget_s`` wall-clock seconds (:func:`subset_size`; they are then labelled again in one
    clean run); otherwise a random subset that fits: the first ``N`` of
    ``numpy.random.default_rng(seed)``'s permutation of the maps, the probe's included.

    Returns
    -------
    labels : list of (h, w) int32 per map, or None when a subset was labelled.
    record : :func:`labeling_record` plus ``workers``, ``seed``, ``budget_s``, ``probe_maps``,
        ``subset`` (the labelled maps, sorted) and per-phase wall seconds summed over the maps.
    """
    from baselines.dmt.labeling import DMTLabelingConfig, dmt_labels, label_maps
    from dmrt.preprocess.parallel import default_workers, open_executor

    n = len(bundle.cameras)
    workers = min(workers or default_workers(), n)
    config = DMTLabelingConfig(labeler="graphcut", workers=workers)
    extra = {"workers": workers, "seed": int(seed), "budget_s": budget_s, "probe_maps": 0}
    if budget_s is not None and workers < n:
        order = np.random.default_rng(seed).permutation(n)
        with open_executor(None, workers=workers) as executor:
            t0 = time.perf_counter()
            done = label_maps(bundle, width, order[:workers], config, executor, progress)
            probe_wall = time.perf_counter() - t0
            k = subset_size([st["cpu_s"] for _, st in done], probe_wall, n, budget_s)
            extra["probe_maps"] = len(done)
            if k < n:
                done += label_maps(bundle, width, order[len(done):k], config, executor, progress)
                wall = time.perf_counter() - t0
        if k < n:
            stats = [st for _, st in done]
            record = labeling_record([st["cpu_s"] for st in stats], wall, n)
            record.update(extra, subset=sorted(int(i) for i in order[:k]), cached=False,
                          texels=int(sum(st["texels"] for st in stats)),
                          **{ph: float(sum(st[ph] for st in stats)) for ph in ("candidates_s", "costs_s", "cut_s")})
            return None, record
    # every map: one clean run, whose labels are cached for --reuse-labels
    labels, meta = dmt_labels(bundle, width, config, progress=progress, recompute=True)
    return labels, _record_of_meta(meta, n, extra)


def _record_of_meta(meta: dict, n: int, extra: dict) -> dict:
    """The labeling record of a whole labeling (:func:`baselines.dmt.dmt_labels`'s meta)."""
    t = meta["timings"]
    if all("cpu_s" in m for m in meta["maps"]):
        record = labeling_record([m["cpu_s"] for m in meta["maps"]], t["total_s"], n)
    else:  # a cache written before CPU seconds were recorded
        record = {"maps": n, "maps_total": n, "extrapolated": False, "wall_s": t["total_s"], "cpu_s": None,
                  "cpu_s_all": None, "wall_s_all": t["total_s"]}
    record.update(extra, workers=meta.get("workers", extra.get("workers")), subset=None, cached=meta["cached"],
                  texels=meta["counts"]["texels"], energy=meta["energy"],
                  **{ph: t[ph] for ph in ("candidates_s", "costs_s", "cut_s")})
    return record


def _dmrt_labeling_task(root: str) -> dict:
    """:func:`dmrt_labeling`'s work, in its own process."""
    from baselines.dmt.labeling import resolve_config, warm_imports
    from dmrt.io.bundle import read_bundle
    from dmrt.preprocess.candidates import find_candidates
    from dmrt.preprocess.labeling import label_points

    warm_imports()  # as DMT's processes, before their clocks start
    b = read_bundle(root)
    p = b.proxy
    if "hd_radii" not in p:
        return {"error": f"{b.root / 'proxy.npz'}: array 'hd_radii' missing (preprocess the scene again)"}
    energy, occl, _ = resolve_config(b, None)  # the bundle's own preprocessing and labeling parameters
    cams = [c.relative_to(b.origin) for c in b.cameras]
    c0, t0 = time.process_time(), time.perf_counter()
    # as dmrt.preprocess.proxies.label_proxies runs steps 5 and 6 (the stored radii are step 4's)
    cands = find_candidates(p["positions"], p["normals"], p["hd_radii"], cams, b.depth_map, b.image, occl,
                            progress=False, radii=p["radii"])
    c1, t1 = time.process_time(), time.perf_counter()
    labels = label_points(p["positions"], p["normals"], cands, cams, config=energy, progress=False).labels
    c2, t2 = time.process_time(), time.perf_counter()
    return {"wall_s": t2 - t0, "cpu_s": c2 - c0, "candidates_wall_s": t1 - t0, "candidates_cpu_s": c1 - c0,
            "labeling_wall_s": t2 - t1, "labeling_cpu_s": c2 - c1, "proxies": int(len(labels)),
            "labels_equal_bundle": float(np.mean(labels == p["labels"]))}


def dmrt_labeling(bundle_path) -> dict:
    """DMRT's labeling work of preprocessing (candidates + graph cut on the bundle's proxies, with
    the bundle's parameters) run again in one fresh process, as DMT's maps are, and timed.

    Returns
    -------
    dict: ``wall_s``, ``cpu_s`` (:func:`time.process_time`) and the same for each step
    (``candidates_*``, ``labeling_*``), ``proxies``, ``labels_equal_bundle`` (share of proxies whose
    label equals the bundle's: 1.0 when this is the work preprocessing did); or ``error``.
    """
    from dmrt.preprocess.parallel import ProcessPool

    pool = ProcessPool(1)
    try:
        return pool.map(_dmrt_labeling_task, [str(Path(bundle_path).resolve())], desc="DMRT labeling")[0]
    finally:
        pool.close()


# ------------------------------------------------------------------------------------------------
# the benchmark
# ------------------------------------------------------------------------------------------------
def run(bundle_path, resolutions=(256, 512, 1024), frames: int = 60, width: int = 1280, height: int = 720,
        labeler: str = "graphcut", layers: int = 5, warmup: int = 5, path=None, reuse_labels: bool = False,
        epsilon: float | None = None, dmrt: bool = True, progress: bool = True, budget_s: float | None = None,
        workers: int | None = None, seed: int = 0) -> dict:
    """Labeling times and walkthrough frame rates of DMT per resolution and of DMRT, one run.

    Parameters
    ----------
    bundle_path : a preprocessed bundle (its depth maps at least as wide as the largest resolution).
    resolutions : DMT depth-map widths (heights follow the photos' aspect).
    frames, width, height : walkthrough length and frame size (default path: through every
        ``n / 12``-th photo camera, :func:`dmrt.runtime.walkthrough.camera_path`).
    labeler : "graphcut" (timing comparisons), or "wta" / "own" (frame rates only: no labeling
        time to compare).
    layers : DMRT label layers (paper's comparison: 5).
    warmup : frames rendered before timing (compilation, first allocations, photo cache).
    path : camera path JSON (``dmrt path``) instead of the default walkthrough.
    reuse_labels : load cached DMT labels (their recorded times are reported) instead of relabeling.
    epsilon : DMT stitching threshold (default DMTConfig's).
    dmrt : also run DMRT (its walkthrough and its labeling, timed again).
    budget_s : graph cuts: wall-clock seconds per resolution before a subset is labelled and
        extrapolated (:func:`time_graphcut`); None = every map.
    workers : labeling processes (None: every CPU core).  seed : the subset's random order.

    Returns
    -------
    dict (JSON-ready): ``dmt`` list per resolution {width, size, labeling (:func:`time_graphcut`'s
    record; ``seconds`` = its ``wall_s_all``), render_labeler (labels the walkthrough used),
    labeling_ratio_dmt_over_dmrt {cpu, wall}, fps_min_avg_max, gpu_ms_per_frame, fps_per_frame,
    median_ms per stage, gpu_bytes} (or {width, error}), ``dmrt`` {labeling_s (preprocessing's
    wall seconds), labeling (:func:`dmrt_labeling`), fps_min_avg_max, ...},
    ``fps_ratio_dmrt_over_dmt`` per width, machine info.
    """
    from baselines.dmt import DMTConfig, DMTLabelingConfig, DMTRenderer, dmt_labels
    from baselines.dmt.geometry import dmt_size
    from dmrt.io.bundle import read_bundle
    from dmrt.errors import InputError
    from dmrt.gl import get_context, renderer_info
    from dmrt.runtime.walkthrough import camera_path, load_path

    if budget_s is not None and not budget_s >= 0:
        raise ConfigError("budget_s", f"must be >= 0 seconds, not {budget_s}")
    if workers is not None and workers < 1:
        raise ConfigError("workers", f"must be >= 1, not {workers}")
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
    # DMRT's labeling first: the denominator of every ratio below
    dmrt_lab = dmrt_labeling(bundle.root) if dmrt and labeler == "graphcut" else None
    if dmrt_lab is not None:
        result["dmrt_labeling"] = dmrt_lab
    for w in resolutions:
        entry = {"width": int(w), "size": list(dmt_size(cams[0], int(w)))}
        try:
            if labeler != "graphcut":
                labels, meta = dmt_labels(bundle, int(w), DMTLabelingConfig(labeler=labeler, workers=workers),
                                          progress=progress, recompute=not reuse_labels)
                record = _record_of_meta(meta, len(cams), {"workers": workers})
            elif reuse_labels:
                labels, meta = dmt_labels(bundle, int(w), DMTLabelingConfig(workers=workers), progress=progress)
                record = _record_of_meta(meta, len(cams), {"workers": workers})
            else:
                labels, record = time_graphcut(bundle, int(w), workers, budget_s, seed, progress)
        except InputError as exc:
            entry["error"] = str(exc)
            result["dmt"].append(entry)
            print(f"DMT {w}: skipped ({exc})")
            continue
        entry["labeling"] = {"labeler": labeler, "seconds": record["wall_s_all"], **record}
        if dmrt_lab is not None and "cpu_s" in dmrt_lab:
            entry["labeling_ratio_dmt_over_dmrt"] = {
                "cpu": None if record.get("cpu_s_all") is None else record["cpu_s_all"] / dmrt_lab["cpu_s"],
                "wall": record["wall_s_all"] / dmrt_lab["wall_s"]}
        render_labeler = labeler
        if labels is None:  # a subset was labelled: frame rates with labels every map has
            render_labeler = "own"
            labels, _ = dmt_labels(bundle, int(w), DMTLabelingConfig(labeler="own"), progress=False)
        entry["render_labeler"] = render_labeler
        cfg = DMTConfig(width=int(w), labeler=render_labeler, progress=progress,
                        **({} if epsilon is None else {"epsilon": float(epsilon)}))
        renderer = DMTRenderer(bundle, cfg, labels=labels)
        entry.update(_walk(renderer, cameras, warmup))
        entry["config"] = {"epsilon": cfg.epsilon, "discontinuity_threshold": cfg.discontinuity_threshold}
        renderer.release()
        result["dmt"].append(entry)
    if dmrt:
        from dmrt.runtime.renderer import RenderConfig, Renderer

        renderer = Renderer(bundle, RenderConfig(layers=layers, photo_choice="labels"))  # the paper's Table 3
        result["dmrt"] = {"layers": layers, "labeling_s": dmrt_label_s, "labeling": dmrt_lab,
                          **_walk(renderer, cameras, warmup)}
        renderer.release()
        avg = result["dmrt"]["fps_min_avg_max"][1]
        result["fps_ratio_dmrt_over_dmt"] = {str(e["width"]): avg / e["fps_min_avg_max"][1]
                                             for e in result["dmt"] if "fps_min_avg_max" in e}
    return result


def print_table(result: dict) -> None:
    """Table 3 layout: labeling wall and CPU seconds, DMT/DMRT ratios, min/avg/max fps per method."""
    def fps(e):
        return "/".join(f"{v:.1f}" for v in e["fps_min_avg_max"])

    def sec(v):
        return "-" if v is None else f"{v:.1f}s"

    print(f"{'method':<18}{'wall':>10}{'CPU':>10}{'CPU ratio':>11}{'fps min/avg/max':>24}{'median GPU ms':>15}")
    for e in result["dmt"]:
        name = f"DMT {e['size'][0]}x{e['size'][1]}"
        if "error" in e:
            print(f"{name:<18}  {e['error']}")
            continue
        lab = e["labeling"]
        ratio = (e.get("labeling_ratio_dmt_over_dmrt") or {}).get("cpu")
        notes = [f"extrapolated from {lab['maps']} of {lab['maps_total']} maps" if lab.get("extrapolated") else "",
                 "labels cached" if lab.get("cached") else "",
                 f"fps with {e['render_labeler']} labels" if e.get("render_labeler") != lab["labeler"] else ""]
        print(f"{name:<18}{sec(lab['wall_s_all']):>10}{sec(lab.get('cpu_s_all')):>10}"
              f"{(f'{ratio:.1f}x' if ratio else '-'):>11}{fps(e):>24}{e['median_total_ms']:>15.2f}  "
              + "; ".join(n for n in notes if n))
    if "dmrt" in result:
        d = result["dmrt"]
        lab = d.get("labeling") or {}
        print(f"{'DMRT (' + str(d['layers']) + ' layers)':<18}{sec(lab.get('wall_s', d['labeling_s'])):>10}"
              f"{sec(lab.get('cpu_s')):>10}{'1.0x':>11}{fps(d):>24}{d['median_total_ms']:>15.2f}")
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
    p.add_argument("--no-dmrt", action="store_true", help="skip DMRT (its walkthrough and its labeling)")
    p.add_argument("--budget-s", type=float, help="graph cuts: wall seconds per resolution, then a random subset "
                                                 "of the maps is labelled and extrapolated (default: every map)")
    p.add_argument("--workers", type=int, help="labeling processes (default: every CPU core)")
    p.add_argument("--seed", type=int, default=0, help="the subset's random order")
    p.add_argument("--quiet", action="store_true")
    p.add_argument("--out", type=Path, required=True, help="results JSON file")
    args = p.parse_args(argv)
    try:
        result = run(args.bundle, args.resolutions, args.frames, args.width, args.height, args.labeler, args.layers,
                     args.warmup, args.path, args.reuse_labels, args.epsilon, not args.no_dmrt, not args.quiet,
                     args.budget_s, args.workers, args.seed)
    except DMRTError as exc:
        p.error(str(exc))
    print_table(result)
    write_text(args.out, json.dumps(result, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
