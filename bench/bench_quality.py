"""Benchmark: holes and leveling at a scene's photo cameras, against the Embree reference.

    python -m bench.bench_quality --scene SCENE --bundle BUNDLE --out RESULTS.json
    python -m bench.bench_quality --preset tiny --work /tmp/q --out RESULTS.json

At every photo camera (at the photo's size): the DMRT hole rate for each layer count, number of
hole-filling passes (``RenderConfig.fill_passes``) and cap on the search's steps
(``RenderConfig.max_steps``, ``--max-steps``; the fill passes' own, ``--fill-max-steps``), over
the reference pixels the photo's own depth map holds (what DMRT can show there; the scan has
shadows the mesh has not), the depth error of the pixels both show, and how far the filled pixels
lie from the reference surface. Then (``--no-leveling``: not) screen-space leveling against the synthetic
generator's known per-photo exposure x white-balance gains (``synthetic.json``): the spread (std
over the photos covering >= 1 % of a frame, mean over channels) of the effective log gains before
and after leveling, for DMRT and for DMT at the bundle's depth-map width.
"""

from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np


def log_gain_spread(frame: dict, truth: np.ndarray) -> tuple[float, float] | None:
    """(before, after) spread of the log gains of the photos covering >= 1 % of ``frame``."""
    labels, counts = np.unique(frame["label"][frame["label"] >= 0], return_counts=True)
    big = labels[counts >= 0.01 * frame["label"].size]
    if len(big) < 2:
        return None
    gains = np.log(frame["leveling_gains"][big].astype(np.float64))
    return float(truth[big].std(axis=0).mean()), float((truth[big] + gains).std(axis=0).mean())


def main(argv=None) -> None:
    from baselines.dmt import DMTConfig, DMTRenderer
    from dmrt.io.bundle import read_bundle
    from dmrt.errors import DMRTError
    from dmrt.runtime.renderer import RenderConfig, Renderer
    from dmrt.io.scene import load_scene
    from reference.metrics import compare
    from reference.render import EmbreeReference

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--scene", type=Path)
    p.add_argument("--bundle", type=Path)
    p.add_argument("--preset", help="generate and preprocess this synthetic preset instead")
    p.add_argument("--work", type=Path, default=Path("/tmp/dmrt-quality"))
    p.add_argument("--layers", type=int, nargs="+", default=[1, 3, 5])
    p.add_argument("--fill-passes", type=int, nargs="+", default=[0, 2, 4])
    p.add_argument("--max-steps", type=int, nargs="+", default=[100],
                   help="iterative-search steps per layer (the paper: 100): what a lower cap costs in holes and depth")
    p.add_argument("--fill-max-steps", type=int, nargs="+", default=[RenderConfig().fill_max_steps],
                   help="the hole-filling passes' step cap (RenderConfig.fill_max_steps)")
    p.add_argument("--leveling", action=argparse.BooleanOptionalAction, default=True,
                   help="also measure leveling against the known photo exposures (DMRT and DMT)")
    p.add_argument("--out", type=Path, required=True)
    args = p.parse_args(argv)
    if args.preset:
        from bench.scenes.synthetic import PRESETS, generate_scene
        from dmrt.preprocess.pipeline import PreprocessConfig, preprocess

        args.scene = generate_scene(PRESETS[args.preset], args.work / "scene", force=True, progress=False)
        width = PRESETS[args.preset].photo_size[0]
        args.bundle = preprocess(args.scene, args.work / "bundle", PreprocessConfig(depthmap_width=width),
                                 force=True, progress=False)
    if args.scene is None or args.bundle is None:
        p.error("give --scene and --bundle, or --preset")
    try:
        scene, bundle = load_scene(args.scene), read_bundle(args.bundle)
    except DMRTError as exc:  # one line, exit 2, nothing written (as bench_render's open_bundle)
        p.exit(2, f"{p.prog}: error: {exc}\n")
    sync = {"async_photos": False, "max_uploads_per_frame": 0}
    reference = EmbreeReference.from_scene(scene)
    refs = []
    for j, cam in enumerate(scene.cameras):
        ref = reference.render(cam)
        # what DMRT can show here: the pixels whose depth-map texel (nearest, for maps smaller than
        # the photo) holds a depth
        held = bundle.depth_map(j) > 0
        h, w = ref["depth"].shape
        held = held[np.arange(h) * held.shape[0] // h][:, np.arange(w) * held.shape[1] // w]
        ref["depth"] = np.where(held, ref["depth"], 0)
        refs.append(ref)

    holes = []
    for k, passes, steps, fill_steps in itertools.product(args.layers, args.fill_passes, args.max_steps,
                                                          args.fill_max_steps):
        r = Renderer(bundle, RenderConfig(layers=k, fill_passes=passes, max_steps=steps, fill_max_steps=fill_steps,
                                          **sync))
        rates, filled_err, depth_err = [], [], []
        for cam, ref in zip(bundle.cameras, refs):
            frame = r.render(cam)
            rates.append(compare(frame, ref)["hole_rate"])
            filled = (frame["layer_used"] >= k) & (ref["depth"] > 0)
            filled_err.append(np.abs(frame["depth"][filled] - ref["depth"][filled]))
            both = (frame["depth"] > 0) & (ref["depth"] > 0)
            depth_err.append(np.abs(frame["depth"][both] - ref["depth"][both]))
        r.release()
        err, dz = np.concatenate(filled_err), np.concatenate(depth_err)
        row = {"layers": k, "fill_passes": passes, "max_steps": steps, "fill_max_steps": fill_steps,
               "hole_rate_per_camera": rates,
               "hole_rate_mean": float(np.mean(rates)), "filled_pixels": int(len(err)),
               "filled_within_5cm": float((err < 0.05).mean()) if len(err) else None,
               "filled_median_error_m": float(np.median(err)) if len(err) else None,
               "depth_error_mean_m": float(dz.mean()) if len(dz) else None,
               "depth_error_p95_m": float(np.percentile(dz, 95)) if len(dz) else None}
        holes.append(row)
        print(f"layers {k}  fill passes {passes}  steps {steps}  fill steps {fill_steps}: holes "
              f"{row['hole_rate_mean']:.4%} mean "
              f"({min(rates):.2%} .. {max(rates):.2%}); depth error mean {row['depth_error_mean_m'] or 0:.5f} m, "
              f"p95 {row['depth_error_p95_m'] or 0:.4f} m; filled {row['filled_pixels']} px, "
              f"{row['filled_within_5cm'] or 0:.0%} within 5 cm", flush=True)

    leveling = {}
    synth = Path(args.scene) / "synthetic.json"
    if synth.is_file() and args.leveling:
        truth = np.log(np.array(json.loads(synth.read_text())["photo_gains"], np.float64))
        # the photos' own colours (photometric off): leveling alone against the known exposures
        for name, renderer in (("dmrt", Renderer(bundle, RenderConfig(layers=3, leveling=True, photometric=False,
                                                                      **sync))),
                               ("dmt", DMTRenderer(bundle, DMTConfig(leveling=True, photometric=False, progress=False,
                                                                     **sync)))):
            pairs = [s for s in (log_gain_spread(renderer.render(cam), truth) for cam in bundle.cameras) if s]
            renderer.release()
            before, after = np.mean(pairs, axis=0)
            leveling[name] = {"views": len(pairs), "spread_before": float(before), "spread_after": float(after)}
            print(f"leveling {name}: log-gain spread {before:.3f} -> {after:.3f} over {len(pairs)} views")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps({"benchmark": "quality", "version": 2, "scene": str(args.scene),
                                    "bundle": str(args.bundle), "holes": holes, "leveling": leveling}, indent=1))
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
