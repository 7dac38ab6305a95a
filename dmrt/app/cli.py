"""The ``dmrt`` command line. Options come from the configuration dataclasses, so the CLI and the
Python API never drift apart: each dataclass field becomes ``--field-name``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import typing
from pathlib import Path

from dmrt.errors import InputError


# ----------------------------------------------------------------------------------------------
# Dataclass <-> argparse
# ----------------------------------------------------------------------------------------------
def add_config_args(parser: argparse.ArgumentParser, cls, skip=()) -> None:
    """Add one ``--option`` per field of dataclass ``cls`` (defaults left to the dataclass)."""
    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        opt = "--" + f.name.replace("_", "-")
        tp = hints[f.name]
        origin = typing.get_origin(tp)
        if tp is bool:
            parser.add_argument(opt, dest=f.name, default=None, action=argparse.BooleanOptionalAction)
        elif origin is tuple:
            args = typing.get_args(tp)
            parser.add_argument(opt, dest=f.name, default=None, nargs=len(args), type=args[0], metavar=f.name.upper())
        else:
            base = next((a for a in typing.get_args(tp) if a is not type(None)), tp) if origin else tp
            parser.add_argument(opt, dest=f.name, default=None, type=base)


def config_from_args(cls, args: argparse.Namespace, base=None):
    """An instance of ``cls`` from ``base`` (or the defaults) with the options the user gave."""
    base = base if base is not None else cls()
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls)
             if getattr(args, f.name, None) is not None}
    given = {k: tuple(v) if isinstance(v, list) else v for k, v in given.items()}
    return dataclasses.replace(base, **given)


# ----------------------------------------------------------------------------------------------
# Commands
# ----------------------------------------------------------------------------------------------
def cmd_scene_synth(args) -> None:
    from bench.scenes.synthetic import PRESETS, SynthConfig, generate_scene

    config = config_from_args(SynthConfig, args, PRESETS[args.preset])
    out = generate_scene(config, args.out, force=args.force, progress=not args.quiet, workers=args.workers)
    print(f"wrote {out}")


def cmd_reference(args) -> None:
    from dmrt.io.frames import write_frame
    from dmrt.io.scene import load_scene
    from reference.render import EmbreeReference

    scene = load_scene(args.scene)
    camera = scene.cameras[scene.camera_index(args.camera)]
    frame = EmbreeReference.from_scene(scene).render(camera, args.width, args.height)
    write_frame(args.out, frame)
    print(f"wrote {args.out} ({frame['depth'].shape[1]}x{frame['depth'].shape[0]}, "
          f"{(frame['depth'] > 0).mean():.1%} surface)")


def cmd_preprocess(args) -> None:
    from dmrt.preprocess.labeling import LabelingConfig
    from dmrt.preprocess.pipeline import PreprocessConfig, preprocess

    out = preprocess(args.scene, args.out, config_from_args(PreprocessConfig, args),
                     config_from_args(LabelingConfig, args), force=args.force, progress=not args.quiet)
    print(f"wrote {out}")


def cmd_scene_mesh(args) -> None:
    from dmrt.io.scene import load_scene
    from reference.poisson import build_scene_mesh

    out = build_scene_mesh(load_scene(args.scene, check_images=False), args.out, depth=args.depth)
    print(f"wrote {out}")


def load_pose(path) -> "Camera":
    """A camera from a JSON file in the bundle's camera format (``name, width, height, fx, fy, cx,
    cy, R, t``; world frame, COLMAP convention)."""
    import json

    from dmrt.io.bundle import camera_from_json

    path = Path(path)
    try:
        return camera_from_json(json.loads(path.read_text()))
    except FileNotFoundError as exc:
        raise InputError(path, "pose file not found") from exc
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(path, f"not a camera pose (JSON with name, width, height, fx, fy, cx, cy, R, t): {exc}") from exc


def make_renderer(bundle, args):
    """The renderer ``--method`` asks for (DMRT or the DMT baseline) and its configuration."""
    if args.renderer == "dmt":
        from baselines.dmt import DMTConfig, DMTRenderer

        # RenderConfig's namesakes (cache_mb, async_photos, max_uploads_per_frame, cpu_cache_mb,
        # discontinuity_threshold, leveling) apply to DMT too; DMTConfig.width is the depth-map
        # width, not the frame's --width
        given = {k: v for k, v in (("width", args.dmt_resolution), ("epsilon", args.dmt_epsilon),
                                   ("labeler", args.dmt_labeler)) if v is not None}
        config = dataclasses.replace(config_from_args(DMTConfig, args), **{"width": None, **given})
        return DMTRenderer(bundle, config), config
    from dmrt.runtime.renderer import RenderConfig, Renderer

    config = config_from_args(RenderConfig, args)
    if args.visibility:
        config = dataclasses.replace(config, method=args.visibility)
    return Renderer(bundle, config), config


def cmd_render(args) -> None:
    import json

    import numpy as np

    from dmrt.io.bundle import read_bundle
    from dmrt.io.frames import write_frame

    bundle = read_bundle(args.bundle)
    if sum(x is not None for x in (args.camera, args.pose, args.path)) != 1:
        raise InputError(args.bundle, "give exactly one of --camera IMAGE_NAME, --pose FILE or --path FILE")
    if args.path is not None:
        return render_walkthrough(bundle, args)
    if args.camera is not None:
        names = [c.name for c in bundle.cameras]
        if args.camera not in names:
            raise InputError(args.bundle / "bundle.json", f"no photo named {args.camera!r} "
                                                          f"(e.g. {', '.join(names[:3])})")
        camera = bundle.cameras[names.index(args.camera)]
    else:
        camera = load_pose(args.pose)
    renderer, config = make_renderer(bundle, args)
    # A still frame: the first render tells which photos the view needs, then they are made
    # resident at full resolution and the frame is rendered again with them.
    renderer.render(camera, args.width, args.height)
    renderer.flush_photos()
    frame = renderer.render(camera, args.width, args.height)
    write_frame(args.out, frame)
    if args.dump_stages:
        from dmrt.io.frames import write_stage_images

        splats = renderer.layers()["label"][0] if hasattr(renderer, "layers") else None
        write_stage_images(args.dump_stages, frame, splats)
    if args.stats:
        hit = frame["depth"] > 0
        stats = {"method": renderer.name, "timings_ms": frame["timings"], "width": int(frame["depth"].shape[1]),
                 "height": int(frame["depth"].shape[0]), "surface_fraction": float(hit.mean()),
                 "gpu_bytes": renderer.gpu_bytes, "config": dataclasses.asdict(config)}
        if "iterations" in frame:  # DMRT's search statistics
            stats["mean_iterations"] = float(frame["iterations"][hit].mean()) if hit.any() else 0.0
            stats["layer_used_histogram"] = np.bincount(frame["layer_used"][hit].ravel(),
                                                        minlength=config.layers).tolist()
        if "stats" in frame:  # DMT's culling counts
            stats["dmt"] = frame["stats"]
        Path(args.stats).write_text(json.dumps(stats, indent=1))
    t = frame["timings"]
    print(f"wrote {args.out}: " + ", ".join(f"{k} {v:.2f} ms" for k, v in t.items()))


def render_walkthrough(bundle, args) -> None:
    """Render a camera path into ``--out`` (a folder): one PNG per frame and ``timings.json``."""
    import json

    from dmrt.runtime.walkthrough import load_path

    cameras = load_path(args.path)
    renderer, config = make_renderer(bundle, args)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from tqdm import tqdm

    from dmrt.io.frames import write_frame

    per_frame = []
    for n, cam in enumerate(tqdm(cameras, desc="walkthrough", unit="frame")):
        frame = renderer.render(cam, args.width, args.height)
        write_frame(out / f"frame_{n:05d}.png", frame)
        per_frame.append(frame["timings"])
    totals = [sum(t.values()) for t in per_frame]
    (out / "timings.json").write_text(json.dumps(
        {"frames": per_frame, "total_ms": totals, "config": dataclasses.asdict(config)}, indent=1))
    print(f"wrote {len(cameras)} frames to {out}: median {sorted(totals)[len(totals) // 2]:.2f} GPU ms per frame")


def cmd_path(args) -> None:
    from dmrt.io.bundle import read_bundle
    from dmrt.runtime.walkthrough import camera_path, save_path

    bundle = read_bundle(args.bundle)
    keys = bundle.cameras[:: max(1, args.every)]
    save_path(args.out, camera_path(keys, args.frames, args.width, args.height, args.fov))
    print(f"wrote {args.out}: {args.frames} cameras through {len(keys)} photo cameras")


def cmd_view(args) -> None:
    from dmrt.io.bundle import read_bundle
    from dmrt.runtime.renderer import RenderConfig
    from dmrt.app.viewer import ViewerConfig, available_methods
    from dmrt.app.viewer_window import run_viewer

    bundle = read_bundle(args.bundle)
    try:
        config = config_from_args(ViewerConfig, args)
    except ValueError as exc:
        raise InputError(None, str(exc)) from exc
    if config.method not in available_methods():
        raise InputError(None, f"--method {config.method}: not available here (have: {', '.join(available_methods())})")
    # RenderConfig options that ViewerConfig does not own (its namesakes are the viewer's)
    skip = {f.name for f in dataclasses.fields(ViewerConfig)}
    render = dataclasses.replace(RenderConfig(), **{
        f.name: getattr(args, f.name) for f in dataclasses.fields(RenderConfig)
        if f.name not in skip and getattr(args, f.name, None) is not None})
    frames = args.frames if args.frames is not None or args.window != "headless" else 1
    run_viewer(bundle, config, render, window=args.window, frames=frames, screenshot=args.screenshot)


def cmd_bench(args) -> None:
    from bench.harness import run_bench

    try:
        status = run_bench(args.preset, args.out, work=args.work, only=args.only, scene=args.scene,
                           progress=not args.quiet, machine_name=args.machine)
    except ValueError as exc:
        raise InputError(None, str(exc)) from exc
    if status["failed"]:
        raise SystemExit(f"dmrt bench: {len(status['failed'])} experiment(s) failed: "
                         f"{', '.join(status['failed'])} (see *.failed.json in {status['dir']})")


def cmd_report(args) -> None:
    from bench.report import build_report

    r = build_report(args.results, args.out, preset=args.preset, machine=args.machine)
    print(f"wrote {r.out}/index.html and {r.out}/REPORT.md from {r.result_set.dir}")
    if r.missing or r.failed:
        print(f"report INCOMPLETE: not run: {', '.join(r.missing) or '-'}; failed: {', '.join(r.failed) or '-'}",
              file=sys.stderr)
        if args.check:
            raise SystemExit(1)


def build_parser() -> argparse.ArgumentParser:
    from bench.scenes.synthetic import PRESETS, SynthConfig
    from dmrt.preprocess.labeling import LabelingConfig
    from dmrt.preprocess.pipeline import PreprocessConfig
    from dmrt.runtime.renderer import RenderConfig

    p = argparse.ArgumentParser(prog="dmrt", description="Multi-Depth-Map Raytracing suite")
    sub = p.add_subparsers(dest="command", required=True)

    scene = sub.add_parser("scene", help="scene tools").add_subparsers(dest="scene_command", required=True)
    synth = scene.add_parser("synth", help="generate a synthetic laser-scan scene")
    synth.add_argument("--preset", choices=sorted(PRESETS), default="tiny")
    synth.add_argument("--out", type=Path, required=True, help="scene directory to write")
    synth.add_argument("--force", action="store_true", help="replace an existing scene")
    synth.add_argument("--quiet", action="store_true", help="no progress bars")
    synth.add_argument("--workers", type=int, help="processes that scan and photograph (default: CPU cores)")
    add_config_args(synth, SynthConfig, skip=("name",))
    synth.set_defaults(func=cmd_scene_synth)

    mesh = scene.add_parser("mesh", help="reference mesh from the points (screened Poisson)")
    mesh.add_argument("scene", type=Path)
    mesh.add_argument("--depth", type=int, default=9, help="Poisson octree depth (default 9)")
    mesh.add_argument("--out", type=Path, help="mesh file (default SCENE/mesh.ply)")
    mesh.set_defaults(func=cmd_scene_mesh)

    pre = sub.add_parser("preprocess", help="scene -> bundle: depth maps, proxy points, labels")
    pre.add_argument("scene", type=Path)
    pre.add_argument("--out", type=Path, required=True, help="bundle directory to write")
    pre.add_argument("--force", action="store_true", help="overwrite an existing bundle")
    pre.add_argument("--quiet", action="store_true", help="no progress bars")
    add_config_args(pre, PreprocessConfig)
    add_config_args(pre, LabelingConfig)
    pre.set_defaults(func=cmd_preprocess)

    ren = sub.add_parser("render", help="render a frame (or a walkthrough) of a bundle with DMRT or DMT")
    ren.add_argument("bundle", type=Path)
    ren.add_argument("--camera", help="image name of the photo whose camera to use")
    ren.add_argument("--pose", type=Path, help="JSON camera (bundle.json's camera format)")
    ren.add_argument("--path", type=Path, help="camera path JSON (dmrt path): --out is then a folder")
    ren.add_argument("--width", type=int, help="frame width (default: the camera's)")
    ren.add_argument("--height", type=int, help="frame height (default: keeps the camera's aspect)")
    ren.add_argument("--visibility", choices=["compute", "kbuffer", "raster"], help="visibility-stage path")
    ren.add_argument("--method", dest="renderer", choices=["dmrt", "dmt"], default="dmrt",
                     help="renderer: DMRT, or the DMT baseline (depth-map triangulation + stitching)")
    ren.add_argument("--dmt-resolution", type=int, metavar="W",
                     help="DMT depth-map width (default: the bundle's); labels computed and cached on first use")
    ren.add_argument("--dmt-epsilon", type=float, help="DMT stitching threshold, metres (default 0.05)")
    ren.add_argument("--dmt-labeler", choices=["graphcut", "wta", "own"],
                     help="DMT labels: graph cut per depth map (default; cached in BUNDLE/dmt/<W>/), "
                          "winner-take-all, or each map's own photo (no labeling)")
    ren.add_argument("--out", type=Path, required=True, help="frame file, .png (colour) or .exr (all buffers)")
    ren.add_argument("--stats", type=Path, help="write per-stage GPU ms and statistics as JSON")
    ren.add_argument("--dump-stages", type=Path, metavar="DIR",
                     help="also write each stage's buffer as a PNG (Fig. 3 a-d: splat labels, raytraced "
                          "depth, per-pixel labels, textured; iteration heat map; holes)")
    add_config_args(ren, RenderConfig, skip=("method", "width", "height"))
    ren.set_defaults(func=cmd_render)

    path = sub.add_parser("path", help="a walkthrough camera path through a bundle's photo cameras")
    path.add_argument("bundle", type=Path)
    path.add_argument("--frames", type=int, default=120)
    path.add_argument("--every", type=int, default=1, help="use every n-th photo camera as a key")
    path.add_argument("--width", type=int, default=1280)
    path.add_argument("--height", type=int, default=720)
    path.add_argument("--fov", type=float, default=70.0, help="horizontal field of view, degrees")
    path.add_argument("--out", type=Path, required=True, help="path JSON to write")
    path.set_defaults(func=cmd_path)

    ref = sub.add_parser("reference", help="Embree ground-truth frame of a scene's mesh.ply")
    ref.add_argument("scene", type=Path)
    ref.add_argument("--camera", required=True, help="image name of the photo whose camera to use")
    ref.add_argument("--width", type=int, help="frame width (default: the photo's)")
    ref.add_argument("--height", type=int, help="frame height (default: keeps the photo's aspect)")
    ref.add_argument("--out", type=Path, required=True, help="frame file, .exr (all channels) or .png")
    ref.set_defaults(func=cmd_reference)

    from dmrt.app.viewer import ViewerConfig

    view = sub.add_parser("view", help="interactive viewer: fly through a bundle (DMRT, coarse splats, DMT)")
    view.add_argument("bundle", type=Path)
    view.add_argument("--window", default="pyglet", help="moderngl-window backend: pyglet (default), glfw, "
                      "sdl2, ... or headless (no display: renders --frames frames)")
    view.add_argument("--frames", type=int, help="close after this many frames (headless: default 1)")
    view.add_argument("--screenshot", type=Path, help="save a still PNG of the last view on closing")
    add_config_args(view, ViewerConfig)
    add_config_args(view, RenderConfig, skip=[f.name for f in dataclasses.fields(ViewerConfig)] + ["method", "raytrace"])
    view.set_defaults(func=cmd_view)

    from bench.experiments import EXPERIMENTS
    from bench.workspace import PRESETS as BENCH_PRESETS

    bench = sub.add_parser("bench", help="run the paper's experiments on a preset: one JSON per experiment")
    bench.add_argument("--preset", choices=list(BENCH_PRESETS), default="ci",
                       help="ci: CPU, minutes; small; paper: the paper's setting, for a GPU")
    bench.add_argument("--out", type=Path, required=True, help="results folder (RESULTS_DIR/<machine>/<commit>-<preset>/)")
    bench.add_argument("--work", type=Path, help="scene, bundles, reference frames; reused by later runs "
                       "(default: $TMPDIR/dmrt-bench/<preset>)")
    bench.add_argument("--only", nargs="+", metavar="EXPERIMENT", choices=list(EXPERIMENTS),
                       help=f"run only these experiments ({' '.join(EXPERIMENTS)})")
    bench.add_argument("--scene", type=Path, help="benchmark this scene instead of the preset's synthetic one")
    bench.add_argument("--machine", help="machine name of the results folder (default: from the GL renderer)")
    bench.add_argument("--quiet", action="store_true", help="no progress bars")
    bench.set_defaults(func=cmd_bench)

    rep = sub.add_parser("report", help="HTML + Markdown report (tables, figures, CSVs) from bench results")
    rep.add_argument("results", type=Path, help="results folder of dmrt bench")
    rep.add_argument("--out", type=Path, required=True, help="report folder, e.g. reports/<name>")
    rep.add_argument("--preset", help="report this preset's newest result set (default: the newest of all)")
    rep.add_argument("--machine", help="report this machine's newest result set")
    rep.add_argument("--check", action="store_true", help="exit 1 when an experiment is missing or failed")
    rep.set_defaults(func=cmd_report)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    try:
        args.func(args)
    except (InputError, FileExistsError) as exc:
        print(f"dmrt: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
