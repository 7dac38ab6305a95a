"""The ``dmrt`` command line: its commands, the parser and ``main``. Options come from the
configuration dataclasses (:mod:`dmrt.app.args`), so the CLI and the Python API never drift apart:
each dataclass field becomes ``--field-name``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import typing
from pathlib import Path

from dmrt.app.args import (FRAME_SUFFIXES, add_config_args, check_output, check_positive, check_reference_size,
                           check_render_size, config_from_args)
from dmrt.camera import Camera
from dmrt.errors import ConfigError, DMRTError, InputError, require


# the bench extra's packages (pyproject.toml): the synthetic scenes' textures and real_views' SSIM
# (scikit-image), the report (pandas, matplotlib)
BENCH_EXTRA = ("skimage", "pandas", "matplotlib")
# the argument group of RenderConfig's knobs, listed last in --help
TUNING = ("tuning (the renderer)",
          "knobs of the renderer's stages: speed, memory, the paper's variants; the defaults suit most scenes")


# ----------------------------------------------------------------------------------------------
# Commands
# ----------------------------------------------------------------------------------------------
def cmd_scene_synth(args) -> None:
    from bench.scenes.synthetic import PRESETS, SynthConfig, generate_scene

    check_positive(args, "workers")
    config = config_from_args(SynthConfig, args, PRESETS[args.preset])
    require("skimage", "dmrt scene synth (the synthetic scenes' textures)", "bench")
    out = generate_scene(config, args.out, force=args.force, progress=not args.quiet, workers=args.workers)
    print(f"wrote {out}")


def cmd_demo(args) -> None:
    from dmrt.app.demo import check_width, run_demo

    check_width(args.width)
    check_output(args.out, folder=True)
    page = run_demo(args.out, width=args.width, progress=not args.quiet)
    print(f"open {page}  (DMRT vs DMT vs Embree: frames, depth-error and hole maps, metrics)")


def cmd_reference(args) -> None:
    from dmrt.io.frames import write_frame
    from dmrt.io.scene import load_scene
    from reference.render import EmbreeReference

    check_positive(args, "width", "height")
    check_output(args.out, suffixes=FRAME_SUFFIXES, what="frame file")
    scene = load_scene(args.scene)
    camera = scene.cameras[scene.camera_index(args.camera)]
    size = camera.resized(args.width, args.height)
    check_reference_size(size.width, size.height)
    frame = EmbreeReference.from_scene(scene).render(camera, args.width, args.height)
    write_frame(args.out, frame)
    print(f"wrote {args.out} ({frame['depth'].shape[1]}x{frame['depth'].shape[0]}, "
          f"{(frame['depth'] > 0).mean():.1%} surface)")


def cmd_preprocess(args) -> None:
    import shutil

    from dmrt.io.atomic import partial_dir
    from dmrt.preprocess.labeling import LabelingConfig
    from dmrt.preprocess.pipeline import PreprocessConfig, preprocess

    from dmrt.preprocess.parallel import check_gpus_per_host, open_executor

    config, labeling = config_from_args(PreprocessConfig, args), config_from_args(LabelingConfig, args)
    check_positive(args, "workers")
    check_gpus_per_host(args.dask, args.dask_gpus)
    check_output(args.out, folder=True)
    if args.out.exists() and not args.force:  # refused before the scene is read (minutes on big clouds)
        raise InputError(args.out, "bundle exists (use --force to replace it)")
    try:
        with open_executor(args.dask, workers=args.workers, gpus_per_host=args.dask_gpus) as executor:
            out = preprocess(args.scene, args.out, config, labeling, force=args.force, progress=not args.quiet,
                             executor=executor)
    except BaseException:
        # the bundle's .partial folder is gone, but a worker process finishing its task (the pool
        # waits for them) may have written into it again (Ctrl-C, or a task that failed)
        shutil.rmtree(partial_dir(args.out), ignore_errors=True)
        raise
    print(f"wrote {out}")


def cmd_scene_rgbd(args) -> None:
    from dmrt.io.rgbd import RGBDConfig, rgbd_scene

    check_output(args.out, folder=True)
    made = rgbd_scene(args.frames, args.out, config_from_args(RGBDConfig, args), force=args.force,
                      progress=not args.quiet)
    print(f"wrote {args.out}: {made['points']:,} points (voxel filter of {made['readings']:,} depth readings from "
          f"{made['frames']} of the {made['photos']} frames)")


def cmd_scene_mesh(args) -> None:
    from dmrt.io.scene import load_scene
    from reference.poisson import build_scene_mesh

    check_positive(args, "depth")
    if args.out is not None:
        check_output(args.out, suffixes=(".ply",), what="mesh file")
    require("pymeshlab", "dmrt scene mesh (screened Poisson reconstruction)", "poisson")
    out = build_scene_mesh(load_scene(args.scene, check_images=False), args.out, depth=args.depth)
    print(f"wrote {out}")


def load_pose(path) -> "Camera":
    """A camera from a JSON file in the bundle's camera format (``name, width, height, fx, fy, cx,
    cy, R, t``; world frame, COLMAP convention)."""
    from dmrt.io.bundle import camera_from_json, read_json

    doc = read_json(path, "camera pose", "JSON with name, width, height, fx, fy, cx, cy, R, t")
    return camera_from_json(doc, path)


def make_renderer(bundle, args):
    """The renderer ``--method`` asks for (DMRT or the DMT baseline) and its configuration."""
    if args.renderer == "dmt":
        from baselines.dmt import DMTConfig, DMTRenderer

        # RenderConfig's namesakes (cache_mb, async_photos, max_uploads_per_frame, cpu_cache_mb,
        # discontinuity_threshold, leveling) apply to DMT too; DMTConfig.width is the depth-map
        # width, not the frame's --width
        given = {k: v for k, v in (("width", args.dmt_resolution), ("epsilon", args.dmt_epsilon),
                                   ("labeler", args.dmt_labeler)) if v is not None}
        try:
            config = dataclasses.replace(config_from_args(DMTConfig, args), **{"width": None, **given})
        except ConfigError as exc:  # name the option the user typed, not DMTConfig's field
            renamed = {"width": "dmt-resolution", "epsilon": "dmt-epsilon", "labeler": "dmt-labeler"}
            if exc.option in given and exc.option in renamed:
                raise ConfigError(renamed[exc.option], str(exc).split(": ", 1)[1]) from None
            raise
        return DMTRenderer(bundle, config), config
    from dmrt.runtime.renderer import RenderConfig, Renderer

    config = config_from_args(RenderConfig, args)
    if args.visibility:
        config = dataclasses.replace(config, method=args.visibility)
    return Renderer(bundle, config), config


def cmd_render(args) -> None:
    import numpy as np

    from dmrt.gl.timer import format_timings
    from dmrt.io.atomic import write_json
    from dmrt.io.bundle import read_bundle
    from dmrt.io.frames import write_frame

    # everything the user gave is checked before the bundle is read and long before anything is
    # rendered or written
    given = [o for o in ("camera", "pose", "path") if getattr(args, o) is not None]
    if len(given) != 1:
        raise ConfigError(given[1] if given else "camera", "give exactly one of --camera IMAGE_NAME, --pose FILE "
                          "or --path FILE" + (f", not {' and '.join('--' + o for o in given)}" if given else ""))
    check_positive(args, "width", "height")
    if args.path is not None:
        check_output(args.out, folder=True)
    else:
        check_output(args.out, suffixes=FRAME_SUFFIXES, what="frame file")
    if args.stats is not None:
        check_output(args.stats, "stats", suffixes=(".json",), what="statistics file")
    if args.dump_stages is not None:
        check_output(args.dump_stages, "dump-stages", folder=True)
    bundle = read_bundle(args.bundle)
    if args.path is not None:
        return render_walkthrough(bundle, args)
    if args.camera is not None:
        names = [c.name for c in bundle.cameras]
        if args.camera not in names:
            raise ConfigError("camera", f"no photo named {args.camera!r} in {args.bundle / 'bundle.json'} "
                                        f"(e.g. {', '.join(names[:3])})")
        camera = bundle.cameras[names.index(args.camera)]
    else:
        camera = load_pose(args.pose)
    size = camera.resized(args.width, args.height)
    check_render_size(size.width, size.height, args)
    renderer, config = make_renderer(bundle, args)
    # A still frame: the first render tells which photos the view needs, then they are made
    # resident at full resolution and the frame is rendered again with them; its own GPU times
    # (waiting for them costs nothing after the read-back)
    renderer.timer.wait = True
    renderer.render(camera, args.width, args.height)
    renderer.flush_photos()
    frame = renderer.render(camera, args.width, args.height)
    write_frame(args.out, frame)
    if args.dump_stages:
        from dmrt.io.frames import write_stage_images

        from dmrt.runtime.protocol import LayeredRenderer

        splats = renderer.layers()["label"][0] if isinstance(renderer, LayeredRenderer) else None
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
        if "maps_missing" in frame:  # DMRT's depth-map cache (more photos than one texture array holds)
            stats["maps"] = {"slots": renderer.maps.n_slots, "loads": renderer.maps.loads,
                             "missing": frame["maps_missing"], "rerendered": bool(frame.get("rerendered"))}
        write_json(args.stats, stats)
    print(f"wrote {args.out}: {format_timings(frame['timings'])}")


def render_walkthrough(bundle, args) -> None:
    """Render a camera path into ``--out`` (a folder): one PNG per frame and ``timings.json`` (each
    frame's own GPU ms; null where not measured)."""
    from dmrt.gl.timer import format_ms, is_measured
    from dmrt.io.atomic import atomic_dir, json_text
    from dmrt.runtime.walkthrough import load_path

    cameras = load_path(args.path)
    sizes = [c.resized(args.width, args.height) for c in cameras]
    check_render_size(max(c.width for c in sizes), max(c.height for c in sizes), args)
    out = Path(args.out)
    # the frames are rendered into OUT.partial, renamed to OUT when all are written: an earlier
    # walkthrough there is replaced, any other folder with files in it is refused
    if out.is_dir() and any(out.iterdir()) and not (out / "timings.json").is_file():
        raise InputError(out, "folder exists and holds files that are not a walkthrough (no timings.json): "
                              "give a new or empty --out folder")
    renderer, config = make_renderer(bundle, args)
    renderer.timer.wait = True  # each frame's own times (read back anyway: no wait is added)
    from tqdm import tqdm

    from dmrt.io.frames import write_frame

    per_frame = []
    with atomic_dir(out, force=True, what="walkthrough") as tmp:
        # on a terminal only, and erased when it ends: an error stays the one line on stderr
        for n, cam in enumerate(tqdm(cameras, desc="walkthrough", unit="frame", leave=False, disable=None)):
            frame = renderer.render(cam, args.width, args.height)
            write_frame(tmp / f"frame_{n:05d}.png", frame)
            per_frame.append(frame["timings"])
        totals = [sum(t.values()) for t in per_frame]
        (tmp / "timings.json").write_text(json_text(
            {"frames": per_frame, "total_ms": totals, "config": dataclasses.asdict(config)}))
    measured = sorted(t for t in totals if is_measured(t))
    median = measured[len(measured) // 2] if measured else None
    print(f"wrote {len(cameras)} frames to {out}: median GPU time per frame {format_ms(median)}")


def cmd_path(args) -> None:
    from dmrt.io.bundle import read_bundle
    from dmrt.runtime.walkthrough import camera_path, save_path

    check_positive(args, "frames", "every", "width", "height")
    if not 0 < args.fov < 180:
        raise ConfigError("fov", f"must be between 0 and 180 degrees, not {args.fov}")
    check_output(args.out, suffixes=(".json",), what="camera path file")
    bundle = read_bundle(args.bundle)
    keys = bundle.cameras[:: args.every]
    if len(keys) < 2:
        if len(bundle.cameras) >= 2:
            raise ConfigError("every", f"every {args.every}th of the bundle's {len(bundle.cameras)} photo cameras "
                                       f"leaves {len(keys)}; a path needs at least 2 key cameras")
        raise InputError(Path(args.bundle) / "bundle.json", "a camera path needs at least 2 photo cameras; "
                                                            f"the bundle has {len(bundle.cameras)}")
    save_path(args.out, camera_path(keys, args.frames, args.width, args.height, args.fov))
    print(f"wrote {args.out}: {args.frames} cameras through {len(keys)} photo cameras")


def cmd_view(args) -> None:
    from dmrt.io.bundle import read_bundle

    check_positive(args, "frames")
    if args.screenshot is not None:
        check_output(args.screenshot, "screenshot", suffixes=(".png",), what="screenshot")
    bundle = read_bundle(args.bundle)
    from dmrt.runtime.renderer import RenderConfig
    from dmrt.app.viewer import ViewerConfig, available_methods, check_photo
    from dmrt.app.viewer_window import run_viewer

    try:
        config = config_from_args(ViewerConfig, args)
    except ValueError as exc:
        raise InputError(None, str(exc)) from exc
    if config.method not in available_methods():
        raise InputError(None, f"--method {config.method}: not available here (have: {', '.join(available_methods())})")
    check_photo(config.photo, bundle)  # before a window opens
    # RenderConfig options that ViewerConfig does not own (its namesakes are the viewer's)
    skip = {f.name for f in dataclasses.fields(ViewerConfig)}
    render = dataclasses.replace(RenderConfig(), **{
        f.name: getattr(args, f.name) for f in dataclasses.fields(RenderConfig)
        if f.name not in skip and getattr(args, f.name, None) is not None})
    frames = args.frames if args.frames is not None or args.window != "headless" else 1
    run_viewer(bundle, config, render, window=args.window, frames=frames, screenshot=args.screenshot)


def cmd_bench(args) -> None:
    for module in BENCH_EXTRA:  # before any work: else each experiment fails alike
        require(module, "dmrt bench", "bench")
    from bench.harness import run_bench

    try:
        status = run_bench(args.preset, args.out, work=args.work, only=args.only, scene=args.scene,
                           progress=not args.quiet, machine_name=args.machine, holdout_every=args.holdout_every,
                           variants=args.variants)
    except ValueError as exc:
        raise InputError(None, str(exc)) from exc
    if status["failed"]:
        raise SystemExit(f"dmrt bench: {len(status['failed'])} experiment(s) failed: "
                         f"{', '.join(status['failed'])} (see *.failed.json in {status['dir']})")


def cmd_report(args) -> None:
    check_output(args.out, folder=True)
    for module in ("pandas", "matplotlib"):
        require(module, "dmrt report", "bench")
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
    from dmrt.runtime.renderer import RenderConfig, Visibility

    from dmrt.app.demo import MAX_WIDTH as DEMO_MAX_WIDTH

    p = argparse.ArgumentParser(prog="dmrt", description="Multi-Depth-Map Raytracing suite")
    p.add_argument("--version", action="version", version=f"%(prog)s {version()}")
    sub = p.add_subparsers(dest="command", required=True)

    demo = sub.add_parser("demo", help="the main job on the built-in scene: a page comparing DMRT, DMT and Embree")
    demo.add_argument("--out", type=Path, default=Path("out/demo"), help="folder to write (default: out/demo)")
    demo.add_argument("--width", type=int, default=480,
                      help=f"frame width in pixels, at most {DEMO_MAX_WIDTH} (default: 480)")
    demo.add_argument("--quiet", action="store_true", help="no progress output")
    demo.set_defaults(func=cmd_demo)

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

    from dmrt.app.check import cmd_check
    from dmrt.preprocess.registration import CheckConfig

    chk = sub.add_parser("check", help="registration check: do the photos fit the points? (verdicts, a page)")
    chk.add_argument("scene", type=Path)
    chk.add_argument("--out", type=Path, help="folder for the page (default: out/check/<scene folder name>)")
    chk.add_argument("--strict", action="store_true", help="exit 1 when a photo fails (bad input: 2)")
    chk.add_argument("--quiet", action="store_true", help="no progress bar")
    add_config_args(chk.add_argument_group("measures and thresholds"), CheckConfig)
    chk.set_defaults(func=cmd_check)

    from dmrt.io.rgbd import RGBDConfig

    rgbd = scene.add_parser("rgbd", help="a scene from RGB-D frames (depth/ 16-bit PNGs, images/, sparse/)")
    rgbd.add_argument("frames", type=Path, help="folder with depth/, images/, sparse/ and optionally mesh.ply")
    rgbd.add_argument("--out", type=Path, required=True, help="scene directory to write")
    rgbd.add_argument("--force", action="store_true", help="replace an existing scene")
    rgbd.add_argument("--quiet", action="store_true", help="no progress bar")
    add_config_args(rgbd, RGBDConfig)
    rgbd.set_defaults(func=cmd_scene_rgbd)

    pre = sub.add_parser("preprocess", help="scene -> bundle: depth maps, proxy points, labels")
    pre.add_argument("scene", type=Path)
    pre.add_argument("--out", type=Path, required=True, help="bundle directory to write")
    pre.add_argument("--force", action="store_true", help="overwrite an existing bundle")
    pre.add_argument("--quiet", action="store_true", help="no progress bars")
    pre.add_argument("--dask", metavar="SPEC", help="run the parallel phases as Dask tasks: local:N (a LocalCluster "
                     "of N worker processes) or tcp://HOST:PORT (a running scheduler; workers with --nthreads 1 "
                     "that see the scene and --out at the same paths); needs dmrt[dask]")
    pre.add_argument("--dask-gpus", type=int, metavar="N", help="with --dask: workers per host that render depth "
                     "maps, one per GPU (default: the host's NVIDIA GPUs, at least 1); all workers run the CPU "
                     "phases")
    pre.add_argument("--workers", type=int, help="without --dask: local processes for the CPU phases (octree, "
                     "normals/radii, candidates; default: CPU cores; 1 = all in this process); the bundle does "
                     "not depend on it")
    add_config_args(pre, PreprocessConfig, tuning=pre.add_argument_group("preprocessing"))
    add_config_args(pre, LabelingConfig, tuning=pre.add_argument_group("proxy labeling"))
    pre.set_defaults(func=cmd_preprocess)

    ren = sub.add_parser("render", help="render a frame (or a walkthrough) of a bundle with DMRT or DMT",
                         usage="%(prog)s BUNDLE (--camera NAME | --pose FILE | --path FILE) --out OUT [options]")
    ren.add_argument("bundle", type=Path)
    ren.add_argument("--camera", help="image name of the photo whose camera to use")
    ren.add_argument("--pose", type=Path, help="JSON camera (bundle.json's camera format)")
    ren.add_argument("--path", type=Path, help="camera path JSON (dmrt path): --out is then a folder")
    ren.add_argument("--width", type=int, help="frame width (default: the camera's)")
    ren.add_argument("--height", type=int, help="frame height (default: keeps the camera's aspect)")
    ren.add_argument("--method", dest="renderer", choices=["dmrt", "dmt"], default="dmrt",
                     help="renderer: DMRT, or the DMT baseline (depth-map triangulation + stitching)")
    ren.add_argument("--out", type=Path, required=True, help="frame file, .png (colour) or .exr (all buffers)")
    ren.add_argument("--stats", type=Path, help="write per-stage GPU ms and statistics as JSON")
    ren.add_argument("--dump-stages", type=Path, metavar="DIR",
                     help="also write each stage's buffer as a PNG (Fig. 3 a-d: splat labels, raytraced "
                          "depth, per-pixel labels, textured; iteration heat map; holes)")
    dmt = ren.add_argument_group("the DMT baseline (--method dmt)")
    dmt.add_argument("--dmt-resolution", type=int, metavar="W",
                     help="DMT depth-map width (default: the bundle's); labels computed and cached on first use")
    dmt.add_argument("--dmt-epsilon", type=float, help="DMT stitching threshold, metres (default 0.05)")
    dmt.add_argument("--dmt-labeler", choices=["graphcut", "wta", "own"],
                     help="DMT labels: graph cut per depth map (default; cached in BUNDLE/dmt/<W>/), "
                          "winner-take-all, or each map's own photo (no labeling)")
    tuning = ren.add_argument_group(*TUNING)
    method = next(f for f in dataclasses.fields(RenderConfig) if f.name == "method")
    tuning.add_argument("--visibility", choices=typing.get_args(Visibility), help=method.metadata["help"])
    add_config_args(ren, RenderConfig, skip=("method", "width", "height"), tuning=tuning)
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

    view = sub.add_parser("view", help="interactive viewer: fly through a bundle (DMRT, coarse splats, DMT)",
                          usage="%(prog)s BUNDLE [options]")
    view.add_argument("bundle", type=Path)
    view.add_argument("--window", default="pyglet", help="moderngl-window backend: pyglet (default), glfw, "
                      "sdl2, ... or headless (no display: renders --frames frames)")
    view.add_argument("--frames", type=int, help="close after this many frames (headless: default 1)")
    view.add_argument("--screenshot", type=Path, help="save a still PNG of the last view on closing")
    add_config_args(view, ViewerConfig, tuning=view.add_argument_group("viewer settings"))
    add_config_args(view, RenderConfig, skip=[f.name for f in dataclasses.fields(ViewerConfig)] + ["method", "raytrace"],
                    tuning=view.add_argument_group(*TUNING))
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
    bench.add_argument("--holdout-every", type=int, metavar="N",
                       help="real_views: hold out photos 0, N, 2N, ... of the scene (N >= 2; default 8, the field's "
                            "habit; a scene of few photos needs a smaller N to hold out more than photo 0)")
    from bench.real_views import COSTS, VARIANTS

    costs = "; ".join(f"{k}*: {v}" for k, v in COSTS.items())  # by renderer: a variant's name starts with it
    bench.add_argument("--variants", nargs="+", metavar="NAME",
                       help=f"real_views: run only these renderer variants, names or patterns ({' '.join(VARIANTS)}; "
                            f"e.g. 'dmrt*'; default all). What each costs: {costs}")
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


def error_line(exc: BaseException) -> str:
    """``exc``'s message on one line (a message spanning lines is joined with "; ")."""
    lines = [ln.strip() for ln in str(exc).splitlines() if ln.strip()]
    return "; ".join(lines) or type(exc).__name__


def version() -> str:
    """The installed distribution's version (``pyproject.toml``), or a note that it is not installed."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as dist_version

    try:
        return dist_version("dmrt")
    except PackageNotFoundError:
        return "(not installed: pip install -e . in the suite's checkout)"


def main(argv=None) -> int:
    """The ``dmrt`` command: 0 on success; bad input (any :class:`DMRTError`) is printed as one
    line ``dmrt: error: <message>`` on stderr and answered with 2, as argparse answers bad usage;
    Ctrl-C with one line and 130 (128 + SIGINT, as a shell reports it). Every output is written
    whole or not at all (:mod:`dmrt.io.atomic`), so an interrupted command leaves nothing half-written."""
    try:
        args = build_parser().parse_args(argv)
        args.func(args)
    except (DMRTError, FileExistsError) as exc:
        print(f"dmrt: error: {error_line(exc)}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("dmrt: error: interrupted (Ctrl-C); no output was left half-written", file=sys.stderr)
        return 130
    return 0


if __name__ == "__main__":
    sys.exit(main())
