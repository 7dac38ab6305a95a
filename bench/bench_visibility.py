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
its list's statistics and GPU bytes. One JSON ``visibility-<name>.json``.
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
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    args.bundle = bundle_path(args, {})
    bundle = read_bundle(args.bundle)
    keys = bundle.cameras[:: max(1, len(bundle.cameras) // 12)]
    path = camera_path(keys, args.frames, args.width, args.height)
    configs = [("compute", mtp, 0) for mtp in args.max_thread_pixels]
    configs += [("kbuffer", args.max_thread_pixels[-1], slots) for slots in args.slots]
    # tiles-lagged: the tiles path without its end-of-stage statistics readback (dmrt.runtime.tiles)
    configs += [(m, args.max_thread_pixels[-1], 0) for m in ("tiles", "tiles-lagged")]
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
    out = args.out / f"visibility-{args.preset or bundle.root.name}.json"
    out.write_text(json.dumps({"benchmark": "visibility", "version": 1, "machine": {"gl": renderer_info(get_context())},
                               "frame_size": [args.width, args.height], "layers": args.layers,
                               "counts": bundle.meta.get("counts"), "runs": runs}, indent=1))
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
