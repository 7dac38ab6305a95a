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
    from dmrt.frames import write_frame
    from dmrt.scene import load_scene
    from reference.render import EmbreeReference

    scene = load_scene(args.scene)
    camera = scene.cameras[scene.camera_index(args.camera)]
    frame = EmbreeReference.from_scene(scene).render(camera, args.width, args.height)
    write_frame(args.out, frame)
    print(f"wrote {args.out} ({frame['depth'].shape[1]}x{frame['depth'].shape[0]}, "
          f"{(frame['depth'] > 0).mean():.1%} surface)")


def cmd_preprocess(args) -> None:
    from dmrt.labeling import LabelingConfig
    from dmrt.preprocess import PreprocessConfig, preprocess

    out = preprocess(args.scene, args.out, config_from_args(PreprocessConfig, args),
                     config_from_args(LabelingConfig, args), force=args.force, progress=not args.quiet)
    print(f"wrote {out}")


def cmd_scene_mesh(args) -> None:
    from dmrt.scene import load_scene
    from reference.poisson import build_scene_mesh

    out = build_scene_mesh(load_scene(args.scene, check_images=False), args.out, depth=args.depth)
    print(f"wrote {out}")


def load_pose(path) -> "Camera":
    """A camera from a JSON file in the bundle's camera format (``name, width, height, fx, fy, cx,
    cy, R, t``; world frame, COLMAP convention)."""
    import json

    from dmrt.bundle import camera_from_json

    path = Path(path)
    try:
        return camera_from_json(json.loads(path.read_text()))
    except FileNotFoundError as exc:
        raise InputError(path, "pose file not found") from exc
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(path, f"not a camera pose (JSON with name, width, height, fx, fy, cx, cy, R, t): {exc}") from exc


def cmd_render(args) -> None:
    import json

    import numpy as np

    from dmrt.bundle import read_bundle
    from dmrt.frames import write_frame
    from dmrt.renderer import RenderConfig, Renderer

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
    config = config_from_args(RenderConfig, args)
    if args.visibility:
        config = dataclasses.replace(config, method=args.visibility)
    renderer = Renderer(bundle, config)
    # A still frame: the first render tells which photos the view needs, then they are made
    # resident at full resolution and the frame is rendered again with them.
    renderer.render(camera, args.width, args.height)
    renderer.flush_photos()
    frame = renderer.render(camera, args.width, args.height)
    write_frame(args.out, frame)
    if args.dump_stages:
        from dmrt.frames import write_stage_images

        write_stage_images(args.dump_stages, frame, renderer.layers()["label"][0])
    if args.stats:
        hit = frame["depth"] > 0
        stats = {"timings_ms": frame["timings"], "width": int(frame["depth"].shape[1]),
                 "height": int(frame["depth"].shape[0]), "surface_fraction": float(hit.mean()),
                 "mean_iterations": float(frame["iterations"][hit].mean()) if hit.any() else 0.0,
                 "layer_used_histogram": np.bincount(frame["layer_used"][hit].ravel(),
                                                     minlength=config.layers).tolist(),
                 "gpu_bytes": renderer.gpu_bytes, "config": dataclasses.asdict(config)}
        Path(args.stats).write_text(json.dumps(stats, indent=1))
    t = frame["timings"]
    print(f"wrote {args.out}: " + ", ".join(f"{k} {v:.2f} ms" for k, v in t.items()))


def render_walkthrough(bundle, args) -> None:
    """Render a camera path into ``--out`` (a folder): one PNG per frame and ``timings.json``."""
    import json

    from dmrt.renderer import RenderConfig, Renderer
    from dmrt.walkthrough import load_path

    cameras = load_path(args.path)
    config = config_from_args(RenderConfig, args)
    if args.visibility:
        config = dataclasses.replace(config, method=args.visibility)
    renderer = Renderer(bundle, config)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    from tqdm import tqdm

    from dmrt.frames import write_frame

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
    from dmrt.bundle import read_bundle
    from dmrt.walkthrough import camera_path, save_path

    bundle = read_bundle(args.bundle)
    keys = bundle.cameras[:: max(1, args.every)]
    save_path(args.out, camera_path(keys, args.frames, args.width, args.height, args.fov))
    print(f"wrote {args.out}: {args.frames} cameras through {len(keys)} photo cameras")


def build_parser() -> argparse.ArgumentParser:
    from bench.scenes.synthetic import PRESETS, SynthConfig
    from dmrt.labeling import LabelingConfig
    from dmrt.preprocess import PreprocessConfig
    from dmrt.renderer import RenderConfig

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

    ren = sub.add_parser("render", help="render a frame of a bundle with DMRT")
    ren.add_argument("bundle", type=Path)
    ren.add_argument("--camera", help="image name of the photo whose camera to use")
    ren.add_argument("--pose", type=Path, help="JSON camera (bundle.json's camera format)")
    ren.add_argument("--path", type=Path, help="camera path JSON (dmrt path): --out is then a folder")
    ren.add_argument("--width", type=int, help="frame width (default: the camera's)")
    ren.add_argument("--height", type=int, help="frame height (default: keeps the camera's aspect)")
    ren.add_argument("--visibility", choices=["compute", "raster"], help="visibility-stage path")
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
