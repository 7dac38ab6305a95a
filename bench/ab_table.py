"""The trees of one ``bench/ab_run.sh`` run side by side: a Markdown table per frame size.

    python -m bench.ab_table RESULTS [--trees base new ...]

RESULTS holds one folder per tree, each with the ``render-*.json`` of ``bench.bench_render``. Per
tree and frame size: the GPU total's median and p95 and the sustained wall ms per frame (frames back
to back), the render call's median (CPU), the stages' parts (GPU ms), and the mean search steps and
surface fraction, which equal trees must share (a change meant to keep the frames must not move
them). The first tree is the reference of the ``GPU / first`` column. Where a tree has tile sweeps
(``bench/ab_run.sh`` with ``SWEEP``: ``sweep-<width>/visibility-*.json``), also a table per frame
size of the tile raster's ms per setting (``T:B:K[:r][:s|:l]``) and tree, with the layers' agreement with
the sweep's first setting where it is not 1. Where a tree's tile lists were timed pass by pass
(``bench_render --passes``, ``bench/ab_run.sh`` with ``PASSES=1``), also a table per frame size of
those passes.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

PARTS = ("visibility:tile_lists", "visibility:tile_raster", "raytracing:search", "raytracing:hole_fill",
         "image_management:histogram", "image_management:label_finalize")
STAGES = ("labeling", "texturing")


def load(results: Path, trees: list[str] | None) -> dict[str, list[dict]]:
    """``{tree: runs of its render JSON}`` in the order asked (default: folder names, sorted)."""
    names = trees or sorted(p.name for p in results.iterdir() if p.is_dir() and any(p.glob("render-*.json")))
    out = {}
    for name in names:
        files = sorted((results / name).glob("render-*.json"))
        if not files:
            raise FileNotFoundError(f"{results / name}: no render-*.json")
        out[name] = json.loads(files[0].read_text())["runs"]
    return out


def load_sweeps(results: Path, names) -> dict[tuple[int, int], dict[str, dict[str, dict]]]:
    """``{(w, h): {setting: {tree: sweep entry}}}`` from the trees' ``sweep-*/visibility-*.json``."""
    out: dict = {}
    for name in names:
        for f in sorted((results / name).glob("sweep-*/visibility-*.json")):
            d = json.loads(f.read_text())
            for e in d["tile_sweep"]:
                key = (f"{e['tile']}:{e['batch']}:{e['top']}" + ("" if e["warp_blocks"] else ":r")
                       + {"sparse": ":s", "linear": ":l"}.get(e.get("walk", "auto"), ""))
                out.setdefault(tuple(d["frame_size"]), {}).setdefault(key, {})[name] = e
    return out


def sweep_table(settings: dict[str, dict[str, dict]], names) -> str:
    """The Markdown table of the tile raster's ms per setting (rows) and tree (columns)."""
    lines = ["| setting | " + " | ".join(names) + " |", "|" + "---|" * (len(names) + 1)]
    for key, by_tree in settings.items():
        cells = []
        for name in names:
            e = by_tree.get(name)
            if e is None:
                cells.append("-")
                continue
            agree = e["layers_equal_to_first"]
            cells.append(f"{e['tile_raster_ms']:.3f}" + ("" if agree == 1.0 else f" (layers {agree:.6f})"))
        lines.append(f"| {key} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def table(runs: dict[str, list[dict]], size: tuple[int, int]) -> str:
    """The Markdown table of every tree's run at ``size`` (w, h)."""
    head = (["tree", "GPU median", "GPU / first", "GPU p95", "sustained", "call median"]
            + [p.split(":")[1] for p in PARTS] + list(STAGES) + ["steps", "surface"])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    first = None
    for name, rs in runs.items():
        r = next((r for r in rs if tuple(r["frame_size"]) == size), None)
        if r is None:
            continue
        s = r["sustained_timed"]
        first = first if first is not None else s["median_total_ms"]
        ratio = f"{s['median_total_ms'] / first:.3f}" if first > 0 else "-"  # software GL: no times
        cells = [name, f"{s['median_total_ms']:.3f}", ratio,
                 f"{s['p95_total_ms']:.3f}", f"{r['sustained_ms']:.3f}", f"{r['sustained_call_ms']['median']:.3f}"]
        cells += [f"{s['median_part_ms'].get(p, 0.0):.3f}" for p in PARTS]
        cells += [f"{s['median_ms'].get(st, 0.0):.3f}" for st in STAGES]
        cells += [f"{r['mean_iterations']:.4f}", f"{r['surface_fraction']:.6f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines)


def passes_table(runs: dict[str, list[dict]], size: tuple[int, int]) -> str | None:
    """The Markdown table of the tile lists' passes (``visibility:lists_*``) of the trees that timed
    them at ``size``, with their sum; None if none did."""
    rows = {}
    for name, rs in runs.items():
        r = next((r for r in rs if tuple(r["frame_size"]) == size), None)
        parts = {} if r is None else {k.split(":lists_")[1]: v for k, v in r["sustained_timed"]["median_part_ms"].items()
                                      if k.startswith("visibility:lists_")}
        if parts:
            rows[name] = parts
    if not rows:
        return None
    names = list(dict.fromkeys(p for parts in rows.values() for p in parts))
    lines = ["| " + " | ".join(["tree", *names, "sum"]) + " |", "|" + "---|" * (len(names) + 2)]
    for name, parts in rows.items():
        cells = [f"{parts.get(p, 0.0):.4f}" for p in names] + [f"{sum(parts.values()):.3f}"]
        lines.append("| " + " | ".join([name, *cells]) + " |")
    return "\n".join(lines)


def main(argv=None) -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("results", type=Path, help="bench/ab_run.sh's OUT_DIR/results")
    p.add_argument("--trees", nargs="+", help="tree folders in this order (default: all, sorted)")
    args = p.parse_args(argv)
    try:
        runs = load(args.results, args.trees)
    except (OSError, ValueError, KeyError) as exc:
        print(f"ab_table: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    if not runs:
        print(f"ab_table: {args.results}: no tree folder with a render-*.json", file=sys.stderr)
        raise SystemExit(2)
    sizes = list(dict.fromkeys(tuple(r["frame_size"]) for rs in runs.values() for r in rs))
    for w, h in sizes:
        print(f"\n{w}x{h}, ms (GPU: the sustained pass's timer queries; sustained: wall per frame)\n")
        print(table(runs, (w, h)))
        lists = passes_table(runs, (w, h))
        if lists is not None:
            print(f"\n{w}x{h}, the tile lists pass by pass, ms (sustained timed pass)\n")
            print(lists)
    for (w, h), settings in load_sweeps(args.results, list(runs)).items():
        print(f"\n{w}x{h}, the tile raster alone, ms per setting T:B:K[:r][:s|:l] (bench_visibility --tile-sweep)\n")
        print(sweep_table(settings, list(runs)))


if __name__ == "__main__":
    main()
