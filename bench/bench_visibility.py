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
setting (tile side, discs in shared memory, nearest hits kept, the warps' pixel blocks: what bounds
the raster pass), its tile lists' and raster's median GPU ms over frames back to back and its
layers against the first setting's. With ``--walk-frames``, each frame's raster alone with the
linear and the sparse walk (:func:`walk_per_frame`: which walk suits which frame). One JSON
``visibility-<name>.json``.

    python -m bench.bench_visibility --bundle B --out R --width 3840 --height 2160 --no-paths \
        --tile-sweep 16:288:12 16:288:12:r 16:384:16 16:512:16 16:256:8 16:192:12 8:256:12
"""

from __future__ import annotations

import argparse
import json

import numpy as np


def main(argv=None) -> None:
    from bench.bench_render import add_source_args, open_bundle
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
    p.add_argument("--tile-sweep", nargs="*", default=["16:288:12", "16:288:12:r", "16:384:16", "16:256:8"],
                   metavar="T:B:K[:r][:s|:l]",
                   help="tiles stage settings timed alone: tile side T, B discs in shared memory, K nearest "
                        "hits kept, ':r' for warps of two pixel rows instead of 8x4 blocks, ':s' / ':l' for the "
                        "raster's sparse / linear walk instead of auto (TileVisibility tile, batch, top, "
                        "warp_blocks, walk); the first is the reference of the layers' comparison")
    p.add_argument("--no-paths", action="store_true", help="only the --tile-sweep")
    p.add_argument("--walk-frames", action="store_true", help="also each frame's tile raster alone with the linear "
                   "and the sparse walk, beside its discs a tile and the share of a tile a disc's box covers")
    args = p.parse_args(argv)
    try:
        sweep = [parse_tile_setting(spec) for spec in args.tile_sweep]
    except ValueError:
        p.error(f"--tile-sweep: settings are TILE:BATCH:TOP[:r][:s|:l] (tile 1-32, batch >= 1, top 4, 8, 12 "
                f"or 16, r: warps of pixel rows; else 8x4 blocks, for a tile a multiple of 8; s / l: the sparse "
                f"/ linear walk, else auto), e.g. 16:384:16:s, not {' '.join(args.tile_sweep)}")
    bundle = open_bundle(p, args, {})
    args.out.mkdir(parents=True, exist_ok=True)
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
            r.timer.wait = True  # each frame's own times
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
    walks = walk_per_frame(bundle, path, args.layers) if args.walk_frames else None
    out = args.out / f"visibility-{args.preset or bundle.root.name}.json"
    out.write_text(json.dumps({"benchmark": "visibility", "version": 2, "machine": {"gl": renderer_info(get_context())},
                               "frame_size": [args.width, args.height], "layers": args.layers,
                               "counts": bundle.meta.get("counts"), "runs": runs, "tile_sweep": tile_runs,
                               "walk_frames": walks}, indent=1))
    print(f"wrote {out}")


def parse_tile_setting(spec: str) -> tuple[int, int, int, bool, str]:
    """``"T:B:K"`` with optional ``:r``, then ``:s`` or ``:l`` -> (tile, batch, top, warp_blocks,
    walk); ValueError when malformed. Warps cover 8x4 pixel blocks (the default) where the tile side
    is a multiple of 8, rows with ``:r``; the raster's walk is ``"auto"``, ``"sparse"`` with ``:s``,
    ``"linear"`` with ``:l``."""
    parts = spec.split(":")
    flags = parts[3:]
    if len(parts) < 3 or flags not in ([], ["r"], ["s"], ["l"], ["r", "s"], ["r", "l"]):
        raise ValueError(spec)
    tile, batch, top = (int(x) for x in parts[:3])
    if not 1 <= tile <= 32 or batch < 1 or top not in (4, 8, 12, 16):
        raise ValueError(spec)
    walk = "sparse" if "s" in flags else "linear" if "l" in flags else "auto"
    return tile, batch, top, "r" not in flags and tile % 8 == 0, walk


SWEEP_ROUNDS = 2  # every setting timed this many times, the settings in turn (a clock drift shows)


def tile_sweep(bundle, path, layers: int, settings) -> list[dict]:
    """The tiles stage alone (:class:`dmrt.runtime.tiles.TileVisibility`, hit masks written as in a
    renderer with the labeling pass) for each (tile, batch, top, warp_blocks, walk) of ``settings`` over
    the camera ``path``: median GPU ms of ``tile_lists`` and ``tile_raster`` over frames rendered
    back to back (deferred timer queries, the list checked two frames late: no wait between frames,
    so the clocks stay up; SWEEP_ROUNDS rounds over the settings, each round's median kept) and the
    share of pixels whose layers (depth bits and labels) equal the first setting's (1.0: every
    setting is exact; compared on frames checked in the frame, as a renderer does)."""
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
    stages = [TileVisibility(ctx, splats, tile=t, batch=b, top=k, warp_blocks=wb, walk=wk)
              for t, b, k, wb, wk in settings]

    def render(stage, cam, timed):
        splats.begin_frame()
        stage.run(camera_uniforms(cam.relative_to(bundle.origin)), (w, h), layers, depth, label,
                  timer if timed else None)

    try:
        times = [[] for _ in stages]
        for _ in range(SWEEP_ROUNDS):
            for i, stage in enumerate(stages):
                stage.check = "lagged"
                for cam in path[:3]:  # warm-up, and the list sized for the path
                    render(stage, cam, False)
                timer.deferred = True
                for cam in path:
                    timer.reset()
                    render(stage, cam, True)
                timer.reset()
                frames = timer.collect()
                timer.deferred = False
                times[i].append({name: float(np.median([f.get(f"visibility:{name}", 0.0) for f in frames]))
                                 for name in ("tile_lists", "tile_raster")})
        rows, first = [], None
        for (tile, batch, top, blocks, walk), stage, t in zip(settings, stages, times):
            stage.check = "frame"
            seen = []
            for cam in path[:: max(1, len(path) // 4)][:4]:  # 4 frames' layers for the comparison
                render(stage, cam, False)
                seen.append((np.frombuffer(depth.read(), np.uint32), np.frombuffer(label.read(), np.int32)))
            first = first or seen
            row = {"tile": tile, "batch": batch, "top": top, "warp_blocks": blocks, "walk": walk,
                   **{f"{name}_ms": min(r[name] for r in t) for name in ("tile_lists", "tile_raster")},
                   "rounds_ms": t,
                   "layers_equal_to_first": float(np.mean([np.mean((da == db) & (la == lb))
                                                           for (da, la), (db, lb) in zip(first, seen)]))}
            rows.append(row)
            lists, raster = (" / ".join(f"{r[name]:.3f}" for r in t) for name in ("tile_lists", "tile_raster"))
            warps = "8x4 blocks" if blocks else "rows"
            print(f"  tiles {tile}x{tile}, batch {batch}, top {top}, warps of {warps}, walk {walk}: lists "
                  f"{lists} ms, raster {raster} ms (rounds), layers equal to the first "
                  f"{row['layers_equal_to_first']:.6f}", flush=True)
    finally:
        for stage in stages:
            stage.release()
        depth.release()
        label.release()
        splats.release()
    return rows


WALK_REPEATS = 7  # timed renders of each frame and walk (the median kept), after 3 untimed


def walk_per_frame(bundle, path, layers: int) -> list[dict]:
    """Each frame of the camera ``path``: the tile raster alone (GPU ms, median of
    :data:`WALK_REPEATS` renders back to back) with ``walk="linear"`` and ``"sparse"``, its list's
    discs a tile ``N`` and the mean share of a tile that a disc's box covers there (``cover``, 0-1:
    the sparse walk pays where a pixel's discs are a small part of its tile's). H200, session 19 of
    reports/frame-h200: sparse faster at 1280x720 above ~45 discs a tile, linear on every 3840x2160
    frame."""
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
    stages = {walk: TileVisibility(ctx, splats, walk=walk) for walk in ("linear", "sparse")}
    span = np.array([bin(i).count("1") for i in range(1 << 16)], np.int64)  # a box word's columns or rows

    def render(stage, uniforms, timed):
        splats.begin_frame()
        stage.run(uniforms, (w, h), layers, depth, label, timer if timed else None)

    try:
        rows = []
        for i, cam in enumerate(path):
            uniforms = camera_uniforms(cam.relative_to(bundle.origin))
            row = {"frame": i}
            for walk, stage in stages.items():
                stage.check = "frame"  # the list sized for this view
                render(stage, uniforms, False)
                stage.check = "lagged"
                for _ in range(3):
                    render(stage, uniforms, False)
                timer.deferred = True
                for _ in range(WALK_REPEATS):
                    timer.reset()
                    render(stage, uniforms, True)
                timer.reset()
                frames = timer.collect()
                timer.deferred = False
                row[f"{walk}_ms"] = float(np.median([f.get("visibility:tile_raster", 0.0) for f in frames]))
            tiles = stages["linear"]
            n = tiles.stats()["entries"]
            boxes = np.frombuffer(tiles.entries.read(8 * n), np.uint32).reshape(-1, 2)[:, 1]
            area = span[boxes & 0xFFFF] * span[boxes >> 16]  # pixels of the box in the tile
            row.update(N=n / (-(-w // tiles.tile) * -(-h // tiles.tile)),
                       cover=float(area.mean()) / tiles.tile ** 2 if n else 0.0)
            rows.append(row)
            print(f"  frame {i}: linear {row['linear_ms']:.3f} ms, sparse {row['sparse_ms']:.3f} ms, "
                  f"{row['N']:.1f} discs a tile, cover {row['cover']:.3f}", flush=True)
        return rows
    finally:
        for stage in stages.values():
            stage.release()
        depth.release()
        label.release()
        splats.release()


if __name__ == "__main__":
    main()
