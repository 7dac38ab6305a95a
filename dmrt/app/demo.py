"""``dmrt demo``: the suite's main job on the built-in scene, ending in a page a person looks at.

It makes the ``tiny`` synthetic scene (a scanned two-room interior with 12 photographs),
preprocesses it, renders one novel view (a photo camera stepped forward and turned) with DMRT, with the
DMT baseline and with the Embree ray-cast ground truth, and writes::

    OUT/index.html      the three frames side by side, depth-error and hole maps, a metrics table
    OUT/compare.png     the same figure as one picture
    OUT/metrics.json    depth error, holes, colour PSNR against Embree; per-stage GPU milliseconds
                        (null where not measured: on a software rasterizer)
    OUT/scene/, OUT/bundle/   the scene and its bundle (reused by a later run)

About a minute on 2 CPU cores (Mesa llvmpipe); the milliseconds are then CPU time, not a GPU's.
"""

from __future__ import annotations

import html
import time
from pathlib import Path

import numpy as np

from dmrt.errors import ConfigError
from dmrt.io.atomic import atomic_file, write_json, write_text
from dmrt.io.frames import heat_colors

#: shown in the figure, left to right
METHODS = ("dmrt", "dmt", "embree")
TITLES = {"dmrt": "DMRT (5 layers)", "dmt": "DMT (256-wide maps)", "embree": "Embree ground truth"}
# The frame width at most, pixels: the ground truth is ray-cast on the CPU, and a 4096-wide frame
# already takes minutes there; wider ones only grind.
MAX_WIDTH = 4096


def check_width(width: int) -> None:
    """:class:`ConfigError` naming ``--width`` unless 1 <= ``width`` <= :data:`MAX_WIDTH`."""
    if not 1 <= width <= MAX_WIDTH:
        raise ConfigError("width", f"must be between 1 and {MAX_WIDTH} pixels (the demo ray-casts its ground truth "
                                   f"on the CPU), not {width}")


def _log(progress: bool, text: str) -> None:
    if progress:
        print(f"[demo] {text}", flush=True)


def run_demo(out, width: int = 480, progress: bool = True) -> Path:
    """Run the demo into folder ``out``; returns the path of ``index.html``. A ``width`` out of
    range is a :class:`ConfigError` before any work (:func:`check_width`)."""
    from baselines.dmt import DMTConfig, DMTRenderer
    from bench.scenes.synthetic import PRESETS, generate_scene
    from dmrt.io.bundle import read_bundle
    from dmrt.io.scene import load_scene
    from dmrt.preprocess.pipeline import PreprocessConfig, preprocess
    from dmrt.runtime.renderer import RenderConfig, Renderer
    from reference.metrics import compare
    from reference.render import EmbreeReference

    check_width(width)
    out = Path(out)
    t0 = time.perf_counter()
    scene_dir, bundle_dir = out / "scene", out / "bundle"
    if not (scene_dir / "synthetic.json").is_file():
        _log(progress, "generating the tiny scene (laser scan + 12 photos)")
        generate_scene(PRESETS["tiny"], scene_dir, force=True, progress=progress)
    if not (bundle_dir / "bundle.json").is_file():
        _log(progress, "preprocessing: depth maps, proxies, labels")
        preprocess(scene_dir, bundle_dir, PreprocessConfig(depthmap_width=256), force=True, progress=progress)
    bundle = read_bundle(bundle_dir)
    reference = EmbreeReference.from_scene(load_scene(scene_dir))
    height = max(1, round(width * bundle.cameras[0].height / bundle.cameras[0].width))
    # a novel view: a photo camera stepped 0.6 m forward and turned 15 degrees, so that no photo
    # was taken from it; of those whose surface the photos see, the one that looks furthest
    views = [_novel_view(c.resized(width, height)) for c in bundle.cameras]
    camera = max(views, key=lambda c: _view_score(reference.render(c, 96)))

    # colours as the photos have them, like the reference's (no photometric gains): a like-for-like
    # comparison of what each method textures where
    renderers = {"dmrt": lambda: Renderer(bundle, RenderConfig(async_photos=False, photometric=False)),
                 "dmt": lambda: DMTRenderer(bundle, DMTConfig(progress=progress, async_photos=False,
                                                              photometric=False)),
                 "embree": lambda: reference}
    frames, wall_ms = {}, {}
    for name in METHODS:
        _log(progress, f"rendering with {TITLES[name]}")
        renderer = renderers[name]()
        if hasattr(renderer, "timer"):  # this frame's own GPU times (Embree's are CPU wall times)
            renderer.timer.wait = True
        renderer.render(camera, width, height)
        renderer.flush_photos()  # a still: every photo the view needs at full resolution
        t = time.perf_counter()
        frames[name] = renderer.render(camera, width, height)
        wall_ms[name] = (time.perf_counter() - t) * 1e3
        renderer.release()
    ref = frames["embree"]
    metrics = {name: compare(frames[name], ref) for name in ("dmrt", "dmt")}
    summary = {name: {k: v for k, v in m.items() if k != "maps"} for name, m in metrics.items()}
    summary["embree"] = {}
    for name in METHODS:
        summary[name].update(wall_ms=wall_ms[name], stage_ms=frames[name]["timings"])

    figure = _figure(frames, metrics)
    with atomic_file(out / "compare.png") as tmp:
        from PIL import Image

        Image.fromarray(figure).save(tmp)
    write_json(out / "metrics.json", {"camera": camera.name, "size": [width, height], "methods": summary})
    page = write_text(out / "index.html", _page(summary, width, height, time.perf_counter() - t0))
    return page


def _novel_view(photo, step: float = 0.6, yaw_degrees: float = 15.0):
    """``photo``'s camera moved ``step`` metres along its optical axis and turned about its own
    vertical axis (image y)."""
    import dataclasses

    a = np.radians(yaw_degrees)
    turn = np.array([[np.cos(a), 0.0, -np.sin(a)], [0.0, 1.0, 0.0], [np.sin(a), 0.0, np.cos(a)]])
    centre = photo.center + step * photo.R[2]  # R's third row: the optical axis in world coordinates
    R = turn @ photo.R
    return dataclasses.replace(photo, name=f"novel view near {photo.name}", R=R, t=-R @ centre)


def _view_score(ref: dict) -> tuple:
    """How good a demo view an Embree frame makes: (the photos see >= 97 % of its surface and
    nothing is closer than 1 m, the median depth in metres)."""
    depth = ref["depth"]
    surface = depth > 0
    if not surface.any():
        return (False, 0.0)
    clear = (ref["label"][surface] >= 0).mean() >= 0.97 and np.percentile(depth[surface], 2) >= 1.0
    return (bool(clear), float(np.median(depth[surface])))


def _figure(frames: dict, metrics: dict) -> np.ndarray:
    """(rows, cols, 3) uint8: colour frames on top; depth error (0..5 cm) and holes below."""
    from PIL import Image, ImageDraw

    h, w = frames["embree"]["depth"].shape
    pad, bar = 4, 16
    tiles = [[frames[m]["color"] for m in METHODS], []]
    for m in ("dmrt", "dmt"):
        maps = metrics[m]["maps"]
        err = heat_colors(np.nan_to_num(maps["depth_error_m"], nan=0.0), vmax=0.05)
        err[maps["holes"] > 0] = (40, 120, 255)   # reference surface the method left empty
        err[maps["holes"] < 0] = (255, 0, 255)    # surface where the reference has none
        tiles[1].append(err)
    ref_depth = frames["embree"]["depth"]
    shade = np.where(ref_depth > 0, 255 - 200 * ref_depth / max(float(ref_depth.max()), 1e-6), 0)
    tiles[1].append(np.repeat(shade[..., None], 3, axis=2).astype(np.uint8))
    canvas = Image.new("RGB", (3 * w + 4 * pad, 2 * (h + bar) + 3 * pad), (255, 255, 255))
    draw = ImageDraw.Draw(canvas)
    captions = [[TITLES[m] for m in METHODS],
                ["DMRT depth error 0-5 cm, holes blue", "DMT depth error 0-5 cm, holes blue", "Embree depth"]]
    for r in range(2):
        for c in range(3):
            x, y = pad + c * (w + pad), pad + r * (h + bar + pad)
            draw.text((x, y), captions[r][c], fill=(0, 0, 0))
            canvas.paste(Image.fromarray(np.ascontiguousarray(tiles[r][c])), (x, y + bar))
    return np.asarray(canvas)


def _page(summary: dict, width: int, height: int, seconds: float) -> str:
    def f(v, fmt):
        return "-" if v is None or (isinstance(v, float) and not np.isfinite(v)) else format(v, fmt)

    rows = []
    for m in METHODS:
        s = summary[m]
        depth, holes = s.get("depth_median_m"), s.get("hole_rate")
        cells = [html.escape(TITLES[m]), f(None if depth is None else 1e3 * depth, ".1f"),
                 f(None if holes is None else 100 * holes, ".2f"), f(s.get("psnr_db"), ".1f"),
                 f(s["wall_ms"], ".0f")]
        rows.append("<tr>" + "".join(f"<td>{c}</td>" for c in cells) + "</tr>\n")
    return f"""<!doctype html>
<html><head><meta charset="utf-8"><title>DMRT demo</title>
<style>body{{font-family:sans-serif;margin:2em}}td,th{{padding:.3em .8em;text-align:right}}
td:first-child,th:first-child{{text-align:left}}</style></head><body>
<h1>DMRT vs DMT vs Embree on the tiny scene</h1>
<p>One novel view ({width}&times;{height}) of the built-in scene
(a photo camera stepped forward and turned: no photo was taken from it) rendered from the
preprocessed bundle by Multi-Depth-Map Raytracing (DMRT) and by its predecessor
DMT, and ray-cast by Embree on the reference mesh (the ground truth the metrics compare with). All three
take colours from the photos as they are (no photometric gains), so the colour PSNR compares what
each method textures where.</p>
<img src="compare.png" alt="colour frames, depth-error and hole maps">
<table><tr><th>method</th><th>depth error, median (mm)</th><th>holes (% of surface)</th>
<th>colour PSNR vs Embree (dB)</th><th>frame, wall-clock (ms)</th></tr>
{''.join(rows)}
</table>
<p>Wall-clock milliseconds of one frame on this machine: on a CPU renderer (Mesa llvmpipe) the GPU
stages run on the CPU, so they say nothing about GPU speed (that is <code>dmrt bench</code>'s work).
Made in {seconds:.0f} s. Numbers in <code>metrics.json</code>; the paper's experiments:
<code>dmrt bench</code> and <code>dmrt report</code>.</p>
</body></html>
"""
