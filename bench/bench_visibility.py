"""Benchmark: the visibility stage's paths and settings (where its time goes).

    python -m bench.bench_visibility --bundle BUNDLE --out RESULTS_DIR
    python -m bench.bench_visibility --preset small --work /tmp/vis --out RESULTS_DIR

Renders a walkthrough at 1280x720 with 1 and ``--layers`` label layers for depth peeling by compute
passes (``compute``, per ``--max-thread-pixels``: discs with a larger pixel box are splatted by a
workgroup each), for the single-pass k-buffer (``kbuffer``, per ``--slots``) and for the
tile-binned path (``tiles``, :mod:`dmrt.runtime.tiles`; ``tiles-lagged`` without its end-of-stage
readback), and records the median GPU ms of the visibility stage and of the labeling pass (one
more splat pass). For the single passes also the agreement of their layers with the peeled ones
(share of pixels with equal label, per layer) and the pixels whose list overflowed; for ``tiles``
its list's statistics and GPU bytes. Then the tiles stage alone for each ``--tile-sweep``
setting (tile side, discs in shared memory, nearest hits kept: what bounds the raster pass), its
tile lists' and raster's median GPU ms and its layers against the first setting's. One JSON
``visibility-<name>.json``.

    python -m bench.bench_visibility --bundle B --out R --width 3840 --height 2160 \
        --tile-sweep 16:512:16 16:256:16 16:128:16 16:512:8 8:256:16
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def main(argv=None) -> None:
    from bench.bench_render import add_source_args, bundle_path
    from dmrt.io.bundle import read_bundle
    from dmrt.gl import get_context, renderer_info
    from dmrt.runtime.renderer import RenderConfig, Renderer
    from dmrt.runtime.walkthrough import camera_path

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_source_args(p, "/tmp/dmrt-vis")
    p.add_argument("--width", type=int, default=1280)
    p.add_argument("--height", type=int, default=720)
    p.add_argument("--layers", type=int, default=5)
    p.add_argument("--max-thread-pixels", type=int, nargs="+", default=[32, 256])
    p.add_argument("--slots", type=int, nargs="+", default=[12, 22, 32], help="k-buffer sizes")
    p.add_argument("--frames", type=int, default=24)
    p.add_argument("--write-normals", action="store_true")
    p.add_argument("--tile-sweep", nargs="*", default=["16:512:16", "16:256:16", "16:512:8"], metavar="T:B:K",
                   help="tiles stage settings timed alone: tile side T, B discs in shared memory, K nearest "
                        "hits kept (TileVisibility tile, batch, top); the first is the default")
    p.add_argument("--no-paths", action="store_true", help="only the --tile-sweep")
    args = p.parse_args(argv)
    try:
        sweep = [tuple(int(x) for x in spec.split(":")) for spec in args.tile_sweep]
        if any(len(t) != 3 or not 1 <= t[0] <= 32 or t[1] < 1 or t[2] not in (4, 8, 12, 16) for t in sweep):
            raise ValueError
    except ValueError:
        p.error(f"--tile-sweep: settings are TILE:BATCH:TOP (tile 1-32, batch >= 1, top 4, 8, 12 or 16), "
                f"e.g. 16:512:16, not {' '.join(args.tile_sweep)}")
    args.out.mkdir(parents=True, exist_ok=True)
    args.bundle = bundle_path(args, {})
    bundle = read_bundle(args.bundle)
    keys = bundle.cameras[:: max(1, len(bundle.cameras) // 12)]
    path = camera_path(keys, args.frames, args.width, args.height)
    configs = [("compute", mtp, 0) for mtp in args.max_thread_pixels]
    configs += [("kbuffer", args.max_thread_pixels[-1], slots) for slots in args.slots]
    # tiles-lagged: the tiles path without its end-of-stage statistics readback (dmrt.runtime.tiles)
    configs += [(m, args.max_thread_pixels[-1], 0) for m in ("tiles", "tiles-lagged")]
    if args.no_paths:
        configs = []
    reference = None
    runs = []
    for method, mtp, slots in configs:
        row = {"method": method, "max_thread_pixels": mtp, "slots": slots}
        for k in (1, args.layers):
            r = Renderer(bundle, RenderConfig(layers=k, method=method.split("-")[0], max_thread_pixels=mtp,
                                              kbuffer_slots=slots, cache_mb=0))
            if method == "tiles-lagged":
                r.visibility.tiles.check = "lagged"
            for cam in path[:3]:
                r.render(cam)
            t, labels, overflow = [], [], 0
            for cam in path:
                t.append(r.render(cam, readback=False)["timings"])
                if k == args.layers:
                    labels.append(r.layers()["label"])
                    overflow += r.visibility.read_overflow()
            row[f"visibility_{k}_ms"] = float(np.median([x["visibility"] for x in t]))
            row["labeling_ms"] = float(np.median([x["labeling"] for x in t]))
            row["n_large"] = int(np.frombuffer(r.splats.large.read(16), np.uint32)[3])
            if method.startswith("tiles"):  # the last frame's list length and capacity
                row[f"tiles_{k}"] = {**r.visibility.tiles.stats(), "bytes": r.visibility.nbytes}
            r.release()
        if reference is None:
            reference = labels  # the first configuration: compute peeling
        row["label_agreement_per_layer"] = np.mean([[np.mean(a[i] == b[i]) for i in range(args.layers)]
                                                    for a, b in zip(reference, labels)], axis=0).tolist()
        row["overflow_pixels_per_frame"] = overflow / len(path)
        runs.append(row)
        print("  ".join(f"{k} {v:.3f}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()
                        if k != "label_agreement_per_layer")
              + f"  agreement min {min(row['label_agreement_per_layer']):.4f}", flush=True)
    tile_runs = tile_sweep(bundle, path, args.layers, sweep)
    out = args.out / f"visibility-{args.preset or bundle.root.name}.json"
    out.write_text(json.dumps({"benchmark": "visibility", "version": 2, "machine": {"gl": renderer_info(get_context())},
                               "frame_size": [args.width, args.height], "layers": args.layers,
                               "counts": bundle.meta.get("counts"), "runs": runs, "tile_sweep": tile_runs}, indent=1))
    print(f"wrote {out}")


def tile_sweep(bundle, path, layers: int, settings) -> list[dict]:
    """The tiles stage alone (:class:`dmrt.runtime.tiles.TileVisibility`, hit masks written as in a
    renderer with the labeling pass) for each (tile, batch, top) of ``settings`` over the camera
    ``path``: median GPU ms of ``tile_lists`` and ``tile_raster`` and the share of pixels whose
    layers (depth bits and labels) equal the first setting's (1.0: every setting is exact)."""
    from dmrt.gl import get_context
    from dmrt.gl.timer import GpuTimer
    from dmrt.runtime.shading import camera_uniforms
    from dmrt.runtime.tiles import TileVisibility
    from dmrt.runtime.visibility import ProxySplats

    ctx = get_context()
    w, h = path[0].width, path[0].height
    splats = ProxySplats(ctx, bundle.proxy)
    depth, label = ctx.buffer(reserve=4 * layers * w * h), ctx.buffer(reserve=4 * layers * w * h)
    timer = GpuTimer(ctx)
    rows, first = [], None
    try:
        for tile, batch, top in settings:
            stage = TileVisibility(ctx, splats, tile=tile, batch=batch, top=top)
            parts, seen = [], []
            for i, cam in enumerate(path[:3] + path):  # 3 frames of warm-up
                splats.begin_frame()
                timer.reset()
                stage.run(camera_uniforms(cam.relative_to(bundle.origin)), (w, h), layers, depth, label, timer)
                if i >= 3:
                    parts.append(timer.part_ms)
                if i >= 3 and (i - 3) % max(1, len(path) // 4) == 0:  # 4 frames' layers for the comparison
                    seen.append((np.frombuffer(depth.read(), np.uint32), np.frombuffer(label.read(), np.int32)))
            stage.release()
            first = first or seen
            row = {"tile": tile, "batch": batch, "top": top,
                   **{f"{name}_ms": float(np.median([x.get(f"visibility:{name}", 0.0) for x in parts]))
                      for name in ("tile_lists", "tile_raster")},
                   "layers_equal_to_first": float(np.mean([np.mean((da == db) & (la == lb))
                                                           for (da, la), (db, lb) in zip(first, seen)]))}
            rows.append(row)
            print(f"  tiles {tile}x{tile}, batch {batch}, top {top}: lists {row['tile_lists_ms']:.3f} ms, "
                  f"raster {row['tile_raster_ms']:.3f} ms, layers equal to the first {row['layers_equal_to_first']:.6f}",
                  flush=True)
    finally:
        depth.release()
        label.release()
        splats.release()
    return rows


if __name__ == "__main__":
    main()
