"""Held-out photographs: how close renders come to real photos (the ``real_views`` experiment).

Users judge a textured scan by how close its renders look to their photographs, and the field
measures that on held-out views: photos left out of the input, rendered at their cameras and
compared with them (PSNR, SSIM, FLIP). This experiment does the same for any scene with photos
(no reference mesh needed, so real scenes too):

1. hold out every ``holdout_every``-th photo (indices 0, N, 2N, ... of the scene's COLMAP image
   order; N = 8 is the field's habit) and preprocess the scene once without them: a derived scene
   in the work folder whose model and ``images/`` hold only the other photos (so the bundle has
   no camera, photo or depth map of a held-out one);
2. render each held-out camera (its intrinsics at the frame width, at most the photo's) with the
   chosen :data:`VARIANTS` (``dmrt bench --variants``; all by default): DMRT, DMT and the coarse
   splats (``RenderConfig(raytrace=False)``), each with the photometric gains off and on, and DMRT
   also with screen-space leveling;
3. compare each frame with the photo (area-resampled to the frame size) over the pixels the
   frame has a surface at: PSNR (dB, 8-bit), SSIM (scikit-image) and FLIP (NVIDIA's perceptual
   difference; both images masked to black outside that surface, their maps averaged over the
   surface) and the share of pixels with a surface, per photo and as means over the photos; and
   PSNR over the pixels *every* variant covers (``common``), which compares variants on the same
   pixels; and, as a diagnostic, PSNR after the per-channel gain that best maps the frame onto the
   photo (``matched``: what is left once the held-out photo's own exposure, which no renderer can
   know, is taken out);
4. the data's own bounds on the common pixels: the kept photos reprojected through the scene's
   geometry (the reference mesh when there is one, else DMRT's depth and the depth maps;
   :mod:`reference.reprojection`): the best single photo, and per pixel the photo whose ray is
   closest in angle to the view's; each variant is measured on each bound's own pixels;
5. temporal stability: a slow walkthrough through kept photos' cameras, rendered by each variant;
   the colour change between consecutive frames that the motion does not explain
   (:mod:`reference.stability`): popping seams.

A source-photo breakdown per view (which photos textured how much of it, and how well each agrees
with the held-out photo) shows where the error comes from. On a synthetic scene the solved gains
are also compared with the generator's known per-photo exposure x white balance.
"""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from bench.workspace import Workspace, _stamp_ok, write_json

# name -> (renderer, options): "dmrt" (RenderConfig), "dmt" (DMTConfig) or "splats" (RenderConfig,
# raytrace off). "dmrt" is the paper's DMRT (the fixed labels) with colours the photos' own: the
# "before" of the photometric work and of the view-dependent photo choice ("dmrt-view", the
# runtime's default); the others add the global gains and/or the screen-space leveling.
_LABELS = {"photo_choice": "labels"}
VARIANTS = {
    "dmrt": ("dmrt", {"photometric": False, **_LABELS}),
    "dmrt-view": ("dmrt", {"photometric": False, "photo_choice": "view"}),
    "dmrt-view+gains": ("dmrt", {"photometric": True, "photo_choice": "view"}),
    "dmrt+gains": ("dmrt", {"photometric": True, **_LABELS}),
    "dmrt+leveling": ("dmrt", {"photometric": False, "leveling": True, **_LABELS}),
    "dmrt+gains+leveling": ("dmrt", {"photometric": True, "leveling": True, **_LABELS}),
    "dmt": ("dmt", {"photometric": False}),
    "dmt+gains": ("dmt", {"photometric": True}),
    "splats": ("splats", {"photometric": False, **_LABELS}),
    "splats+gains": ("splats", {"photometric": True, **_LABELS}),
}
# What a variant costs, by renderer (``dmrt bench --variants`` says it; the result records each
# variant's seconds): DMT labels every kept depth map by graph cuts before its first frame.
COSTS = {"dmrt": "a frame per view and walkthrough frame (the kitchen, 2 shared CPU cores: 8 views at 512 px and "
                 "20 frames at 640 px in 80-115 s a variant)",
         "splats": "less than dmrt (no raytracing)",
         "dmt": "DMT's graph-cut labeling of every kept depth map first, once per bundle (cached in it; the "
                "kitchen's 175 maps: over 15 min on 2 CPU cores), then frames as dmrt's"}
# the variants whose frames the report shows (and whose FLIP maps it draws), where run
SHOWN = ("dmrt", "dmrt-view", "dmrt+gains", "dmrt+gains+leveling", "dmt+gains", "splats+gains")
# the variants whose per-photo source breakdown the result keeps, where run
SOURCES = ("dmrt", "dmrt-view", "dmrt+gains")
# the data's own bounds: the kept photos reprojected through the geometry (reference/reprojection.py)
BOUNDS = ("best_single", "view_closest")
# the per-view measurements each variant row averages (``mean_<key>``)
MEANS = ("psnr_db", "ssim", "flip", "surface_share", "psnr_common_db", "psnr_matched_db")


@dataclass
class RealViewsParams:
    # hold out photos 0, N, 2N, ... (``dmrt bench --holdout-every N``)
    holdout_every: int = 8
    # frame width (the photo's if smaller; height: the photo's aspect)
    width: int = 512
    # DMRT's label layers
    layers: int = 5
    # DMT's per-texel labeling (bench.workspace.BenchPreset.dmt_labeler)
    dmt_labeler: str = "graphcut"
    # held-out views whose frames, photos and error images are kept for the report
    shown_views: int = 2
    # the variants run: names or shell patterns of VARIANTS (``dmrt bench --variants 'dmrt*'``);
    # empty = all
    variants: tuple[str, ...] = ()
    # the bounds: the best single kept photo, among those that see at least this share of the
    # pixels some kept photo sees (one photo that sees a corner alone must not win), and the
    # per-pixel view-closest kept photo, both reprojected through the reference mesh (Embree) when
    # the scene has one, else through DMRT's depth with the kept photos' depth maps. Cost: every
    # kept photo reprojected at every view (the kitchen, 192 photos: 33 s a view on 2 CPU cores,
    # and a mesh cast per photo once)
    bounds: bool = True
    best_single_min_share: float = 0.5
    # temporal stability: a slow walkthrough of this many frames (0: none), this wide, through the
    # cameras of the first walk_keys kept photos (consecutive photos of a capture are near)
    walk_frames: int = 24
    walk_keys: int = 2
    walk_width: int = 256

    def __post_init__(self):
        self.variants = tuple(self.variants)
        select_variants(self.variants)  # an unknown name fails before anything runs


def select_variants(patterns) -> list[str]:
    """The names of :data:`VARIANTS` that ``patterns`` (names or :mod:`fnmatch` patterns such as
    ``dmrt*``) select, in :data:`VARIANTS`' order; all of them for no pattern.

    Raises
    ------
    ValueError
        A pattern that selects nothing, naming it and the variants.
    """
    from fnmatch import fnmatchcase

    patterns = list(patterns)
    for pat in patterns:
        if not any(fnmatchcase(v, pat) for v in VARIANTS):
            raise ValueError(f"--variants {pat}: no such real_views variant (choose from {', '.join(VARIANTS)}, "
                             f"or a pattern such as 'dmrt*')")
    return [v for v in VARIANTS if not patterns or any(fnmatchcase(v, pat) for pat in patterns)]


def holdout_indices(n_photos: int, every: int) -> list[int]:
    """Indices of the held-out photos: 0, ``every``, 2 ``every``, ... below ``n_photos``.

    Raises
    ------
    ValueError
        ``every`` < 2 (no photo would be left to preprocess) or fewer than 2 photos.
    """
    if every < 2:
        raise ValueError(f"--holdout-every {every}: must be >= 2 (1 would hold out every photo)")
    if n_photos < 2:
        raise ValueError(f"the scene has {n_photos} photo(s): holding one out needs at least 2")
    return list(range(0, n_photos, every))


def psnr(rendered: np.ndarray, photo: np.ndarray, mask: np.ndarray) -> float:
    """PSNR in dB of two (h, w, 3) uint8 images over ``mask`` (h, w) bool: ``10 log10(255^2 / MSE)``
    over every channel of the masked pixels (inf when equal, nan when the mask is empty)."""
    d = rendered.astype(np.float64)[mask] - photo.astype(np.float64)[mask]
    if d.size == 0:
        return float("nan")
    mse = float(np.mean(d * d))
    return float("inf") if mse == 0 else float(10.0 * np.log10(255.0 ** 2 / mse))


def psnr_matched(rendered: np.ndarray, photo: np.ndarray, mask: np.ndarray) -> float:
    """:func:`psnr` after the per-channel gain that best maps ``rendered`` onto ``photo`` over
    ``mask`` (least squares, then 8-bit clipping): a diagnostic that takes the held-out photo's own
    exposure and white balance, which no renderer can know, out of the error."""
    r = rendered.astype(np.float64)[mask]
    if r.size == 0:
        return float("nan")
    p = photo.astype(np.float64)[mask]
    gain = (r * p).sum(axis=0) / np.maximum((r * r).sum(axis=0), 1e-12)
    out = rendered.astype(np.float64)
    out[mask] = np.clip(np.rint(r * gain), 0, 255)
    return psnr(out, photo, mask)


def ssim(rendered: np.ndarray, photo: np.ndarray, mask: np.ndarray) -> float:
    """SSIM (``skimage.metrics.structural_similarity``, 7x7 windows, data range 255, the channels'
    mean) of two (h, w, 3) uint8 images over ``mask`` (h, w) bool: both images are set to black
    outside the mask (so the background never differs), the SSIM map is averaged over the mask.
    1 for identical images; nan when the mask is empty or the image is smaller than a window."""
    from skimage.metrics import structural_similarity

    if not mask.any() or min(mask.shape) < 7:
        return float("nan")
    m = mask[..., None]
    a = np.where(m, rendered, 0).astype(np.float64)
    b = np.where(m, photo, 0).astype(np.float64)
    _, smap = structural_similarity(a, b, data_range=255.0, channel_axis=-1, full=True)
    return float(smap.mean(axis=-1)[mask].mean())


def photo_at(image: np.ndarray, width: int, height: int) -> np.ndarray:
    """(height, width, 3) uint8: ``image`` area-averaged (PIL box filter) to the frame size."""
    from PIL import Image

    if image.shape[:2] == (height, width):
        return image
    return np.asarray(Image.fromarray(image).resize((width, height), Image.BOX))


def write_holdout_scene(scene, keep: list[int], out: Path) -> Path:
    """A scene directory ``out`` with only the photos ``keep`` of ``scene``: their COLMAP model
    (``sparse/``, text), symbolic links to their photos and to the point cloud (and mesh)."""
    from dmrt.io.colmap import write_model

    out = Path(out)
    if out.exists():
        shutil.rmtree(out)
    (out / "images").mkdir(parents=True)
    write_model(out / "sparse", [scene.cameras[i] for i in keep], binary=False)
    for i in keep:
        dst = out / "images" / scene.cameras[i].name
        dst.parent.mkdir(parents=True, exist_ok=True)
        os.symlink(Path(scene.image_paths[i]).resolve(), dst)
    os.symlink(Path(scene.points_path).resolve(), out / scene.points_path.name)
    if scene.mesh_path is not None:
        os.symlink(Path(scene.mesh_path).resolve(), out / "mesh.ply")
    return out


def holdout_bundle(ws: Workspace, every: int):
    """The scene preprocessed without its held-out photos, in ``ws.work/real_views-every<N>/``
    (made once; redone when the scene or the preset's preprocessing changed).

    Returns
    -------
    bundle : Path.  held_out, kept : the scene's photo indices.  seconds : preprocessing wall time.
    scene : the whole scene (:class:`dmrt.io.scene.Scene`).
    """
    from dmrt.io.scene import load_scene
    from dmrt.preprocess.pipeline import PreprocessConfig, preprocess

    scene = load_scene(ws.scene_dir)
    held = holdout_indices(len(scene.cameras), every)
    keep = [i for i in range(len(scene.cameras)) if i not in set(held)]
    config = PreprocessConfig(**ws.preset.preprocess)
    root = ws.work / f"real_views-every{every}"
    out, stamp = root / "bundle", root / "bundle.stamp.json"
    stamp_file = ws.work / "scene.stamp.json"
    wanted = {"scene": str(Path(ws.scene_dir).resolve()), "kept": [scene.cameras[i].name for i in keep],
              "preprocess": dataclasses.asdict(config),
              "scene_stamp": stamp_file.read_text() if stamp_file.is_file() else None}
    if not (_stamp_ok(stamp, wanted) and (out / "bundle.json").is_file()):
        stamp.unlink(missing_ok=True)
        print(f"[bench] real_views: preprocessing {len(keep)} of {len(scene.cameras)} photos (holding out "
              f"{len(held)}: every {every}th) -> {out}", flush=True)
        t0 = time.perf_counter()
        sub = write_holdout_scene(scene, keep, root / "scene")
        preprocess(sub, out, config, force=True, progress=ws.progress)
        write_json(stamp, {"config": wanted, "seconds": round(time.perf_counter() - t0, 2)})
    return out, held, keep, json.loads(stamp.read_text())["seconds"], scene


def make_renderer(bundle, kind: str, options: dict, p: RealViewsParams):
    """A renderer of ``kind`` with ``options``: synchronous photo streaming (each frame's photo cache
    holds exactly its most frequent labels, so colours do not depend on the frames before)."""
    sync = {"async_photos": False, "max_uploads_per_frame": 0}
    if kind == "dmt":
        from baselines.dmt import DMTConfig, DMTRenderer

        return DMTRenderer(bundle, DMTConfig(labeler=p.dmt_labeler, progress=False, **sync, **options))
    from dmrt.runtime.renderer import RenderConfig, Renderer

    return Renderer(bundle, RenderConfig(layers=p.layers, raytrace=kind != "splats", **sync, **options))


def source_breakdown(frame: dict, photo: np.ndarray, names: list[str]) -> list[dict]:
    """Per source photo (label) of ``frame`` (``color``, ``label``, ``mask``: the pixels with a
    surface): its share of the surface pixels and the PSNR of those pixels against the held-out
    ``photo``, most pixels first."""
    label, hit = frame["label"], frame["mask"]
    total = max(int(hit.sum()), 1)
    rows = []
    for j in np.unique(label[hit & (label >= 0)]):
        m = hit & (label == j)
        rows.append({"photo": names[int(j)], "share": float(m.sum() / total),
                     "psnr_db": psnr(frame["color"], photo, m)})
    return sorted(rows, key=lambda r: -r["share"])


def gain_recovery(scene_dir: Path, kept: list[int], gains: np.ndarray) -> dict | None:
    """On a synthetic scene: the solved gains against the generator's per-photo exposure x white
    balance (``synthetic.json`` ``photo_gains``): the spread of the true log gains over the kept
    photos, and of the corrected ones (true + solved: 0 when the photos agree), both up to the
    common scale (standard deviation over the photos, mean over the channels). None elsewhere."""
    path = Path(scene_dir) / "synthetic.json"
    if not path.is_file():
        return None
    truth = np.log(np.asarray(json.loads(path.read_text())["photo_gains"], np.float64)[kept])
    corrected = truth + np.log(np.asarray(gains, np.float64))
    return {"log_spread_before": float(truth.std(axis=0).mean()),
            "log_spread_after": float(corrected.std(axis=0).mean())}


def quality(rendered: np.ndarray, photo: np.ndarray, mask: np.ndarray) -> tuple[dict, np.ndarray]:
    """PSNR (dB), SSIM and FLIP of ``rendered`` against ``photo`` over ``mask``, and FLIP's error map
    ((h, w) float32, 0..1; :func:`reference.metrics.flip`)."""
    from reference.metrics import flip

    f, fmap = flip(rendered, photo, mask)
    return {"psnr_db": psnr(rendered, photo, mask), "ssim": ssim(rendered, photo, mask), "flip": f}, fmap


def photo_depths(bundle, raycaster):
    """The kept photos' depth maps the bounds test visibility with: ``j -> (h, w) float32`` camera
    z. With ``raycaster`` (a :class:`reference.raycast.MeshRaycaster` of the reference mesh) Embree
    casts of the mesh at the bundle's depth-map sizes, each cast once and kept (a cast per photo
    costs far less than occlusion rays per photo and view: 8 kitchen views x 192 photos were not
    done after 17 minutes that way on 2 shared cores); else the bundle's own depth maps."""
    if raycaster is None:
        return bundle.depth_map
    sizes = bundle.meta.get("depthmap_sizes") or [[c.width, c.height] for c in bundle.cameras]
    cache: dict[int, np.ndarray] = {}

    def depth(j: int) -> np.ndarray:
        if j not in cache:
            cache[j] = raycaster.cast_camera(bundle.cameras[j].scaled(*sizes[j]))[0]
        return cache[j]

    return depth


def data_bounds(bundle, cam, photo: np.ndarray, mask: np.ndarray, depth: np.ndarray, depth_maps,
                min_share: float) -> dict:
    """The data's own bounds at held-out camera ``cam`` (its ``photo`` at the frame size), over
    ``mask`` (the pixels the renderers cover) and the surface ``depth`` ((h, w) camera z): every
    kept photo reprojected through it (:mod:`reference.reprojection`), seeing what its depth map
    (``depth_maps(j)``, :func:`photo_depths`) sees.

    Returns
    -------
    dict of :data:`BOUNDS` -> ``color`` (h, w, 3) uint8, ``pixels`` (h, w) bool (``mask`` where the
    bound has a colour) and ``photo`` (best_single: the photo's name; view_closest: None), plus
    ``photos`` (per kept photo that sees the view: ``photo``, ``share`` of ``mask``, ``psnr_db`` on
    it) and ``seconds``.
    """
    from reference.reprojection import ViewClosest, depth_map_visibility, reproject, reproject_photos

    t0 = time.perf_counter()

    def visibility(j):
        return depth_map_visibility(bundle.cameras[j], depth_maps(j))

    mask = mask & (depth > 0)
    total = max(int(mask.sum()), 1)
    closest = ViewClosest(cam.height, cam.width)
    rows = []
    for r in reproject_photos(cam, depth, bundle.cameras, bundle.image, visibility):
        closest.add(r)
        m = mask & r.seen
        if m.any():
            rows.append({"index": r.photo, "photo": bundle.cameras[r.photo].name, "share": float(m.sum() / total),
                         "psnr_db": psnr(_u8(r.color), photo, m)})
    any_share = float((mask & closest.seen).sum() / total)
    eligible = [x for x in rows if x["share"] >= min_share * any_share]
    out = {"view_closest": {"color": _u8(closest.color), "pixels": mask & closest.seen, "photo": None}}
    best = max(eligible, key=lambda x: x["psnr_db"], default=None)
    if best is not None:
        j = best["index"]
        r = reproject(cam, depth, j, bundle.cameras[j], bundle.image(j), visibility(j))
        out["best_single"] = {"color": _u8(r.color), "pixels": mask & r.seen, "photo": best["photo"]}
    out["photos"] = sorted(({k: v for k, v in x.items() if k != "index"} for x in rows), key=lambda x: -x["share"])
    out["seconds"] = time.perf_counter() - t0
    return out


def _u8(color: np.ndarray) -> np.ndarray:
    return np.clip(np.rint(color), 0, 255).astype(np.uint8)


def walk_cameras(scene, kept: list[int], p: RealViewsParams) -> tuple[list, list[str]]:
    """The stability walkthrough: ``p.walk_frames`` cameras gliding through the first
    ``p.walk_keys`` (at least 2) kept photos' cameras, at ``p.walk_width`` with the first key's
    field of view and aspect, and the keys' names; ([], []) when there are none."""
    from dmrt.runtime.walkthrough import camera_path

    keys = [scene.cameras[i] for i in kept[:max(p.walk_keys, 2)]]
    if p.walk_frames < 2 or len(keys) < 2:
        return [], []
    k = keys[0]
    fov = float(np.degrees(2 * np.arctan(0.5 * k.width / k.fx)))
    height = max(1, round(p.walk_width * k.height / k.width))
    return camera_path(keys, p.walk_frames, p.walk_width, height, fov), [c.name for c in keys]


def render_variants(bundle, chosen: list[str], cams, walk, p: RealViewsParams, depth_of: str) -> dict:
    """Render the held-out cameras ``cams`` and the walkthrough ``walk`` with each variant of
    ``chosen``. Returns ``frames`` {variant: per view {color, label, mask}}, ``depths`` (variant
    ``depth_of``'s depth per view), ``stability`` {variant: :func:`reference.stability.walkthrough_change`}
    and ``seconds`` {variant: the renderer made, the views and the walkthrough rendered}."""
    from reference.stability import walkthrough_change

    out = {"frames": {}, "depths": [], "stability": {}, "seconds": {}}
    for name in chosen:
        kind, options = VARIANTS[name]
        t0 = time.perf_counter()
        renderer = make_renderer(bundle, kind, options, p)
        try:
            # only what is measured: a frame's other buffers would take GBs at the paper's scale
            views = out["frames"][name] = []
            for cam in cams:
                f = renderer.render(cam)
                views.append({"color": f["color"], "label": f["label"], "mask": f["depth"] > 0})
                if name == depth_of:
                    out["depths"].append(f["depth"])
            if walk:
                path = [{"color": f["color"], "depth": f["depth"]} for f in map(renderer.render, walk)]
                out["stability"][name] = walkthrough_change(path, walk)
        finally:
            renderer.release()
        out["seconds"][name] = time.perf_counter() - t0
        print(f"  {name}: {len(cams)} views + {len(walk)} walkthrough frames in {out['seconds'][name]:.1f} s", flush=True)
    return out


def variant_views(frames: list[dict], photos, common, bounds) -> tuple[list[dict], list[np.ndarray]]:
    """Per held-out view, one variant's ``frames`` against the ``photos``: :func:`quality`, surface
    share, PSNR on the ``common`` pixels, exposure-matched PSNR, and PSNR and FLIP on each bound's
    own pixels (``<bound>_pixels``; FLIP: its map over the frame's surface averaged over them:
    like against like). Returns the rows and the FLIP maps."""
    rows, fmaps = [], []
    for k, (f, photo) in enumerate(zip(frames, photos)):
        q, fmap = quality(f["color"], photo, f["mask"])
        row = {**q, "surface_share": float(f["mask"].mean()), "psnr_common_db": psnr(f["color"], photo, common[k]),
               "psnr_matched_db": psnr_matched(f["color"], photo, f["mask"])}
        for b in BOUNDS:
            if bounds and b in bounds[k]:
                px = bounds[k][b]["pixels"]
                row[f"{b}_pixels"] = {"psnr_db": psnr(f["color"], photo, px),
                                      "flip": float(fmap[px].mean()) if px.any() else float("nan")}
        rows.append(row)
        fmaps.append(fmap)
    return rows, fmaps


def run_real_views(ws: Workspace, p: RealViewsParams, out: Path) -> dict:
    from dmrt.io.bundle import read_bundle
    from reference.reprojection import DEPTH_TOLERANCE_REL, DEPTH_TOLERANCE_TEXELS

    path, held, kept, prep_s, scene = holdout_bundle(ws, p.holdout_every)
    bundle = read_bundle(path)
    names = [c.name for c in bundle.cameras]
    held_names = [scene.cameras[i].name for i in held]
    leak = set(held_names) & set(names)
    if leak:
        raise RuntimeError(f"{path}: held-out photos {sorted(leak)} are in the bundle")
    cams, photos = [], []
    for i in held:
        cam = scene.cameras[i].resized(min(p.width, scene.cameras[i].width), None)
        cams.append(cam)
        photos.append(photo_at(scene.read_image(i), cam.width, cam.height))
    chosen = select_variants(p.variants)
    walk, walk_keys = walk_cameras(scene, kept, p)
    # the depth the bounds reproject through where the scene has no mesh: the first DMRT variant's
    depth_of = next((v for v in chosen if VARIANTS[v][0] == "dmrt"), chosen[0])
    rendered = render_variants(bundle, chosen, cams, walk, p, depth_of)
    frames = rendered["frames"]

    common = [np.logical_and.reduce([frames[v][k]["mask"] for v in chosen]) for k in range(len(cams))]
    bounds, raycaster = [], None
    if p.bounds and scene.mesh_path is not None:
        from reference.raycast import MeshRaycaster

        raycaster = MeshRaycaster.from_file(scene.mesh_path, origin=scene.origin)
    depth_maps = photo_depths(bundle, raycaster)
    for k, cam in enumerate(cams if p.bounds else []):
        # the surface at the view: the mesh's, else the DMRT frame's
        depth = raycaster.cast_camera(cam)[0] if raycaster is not None else rendered["depths"][k]
        bounds.append(data_bounds(bundle, cam, photos[k], common[k], depth, depth_maps, p.best_single_min_share))

    # the report's pictures: the views with the most common surface first
    shown = sorted(range(len(cams)), key=lambda k: -common[k].mean())[:max(0, p.shown_views)]
    maps = {}
    for k in shown:
        maps[f"photo_{k}"] = photos[k]
    rows = []
    measured = [b for b in BOUNDS if bounds]
    for name in chosen:
        per, fmaps = variant_views(frames[name], photos, common, bounds)
        for k in shown if name in SHOWN else ():
            maps[f"{name}_color_{k}"], maps[f"{name}_mask_{k}"] = frames[name][k]["color"], frames[name][k]["mask"]
            maps[f"{name}_flip_{k}"] = fmaps[k].astype(np.float16)
        st = rendered["stability"].get(name)
        rows.append({"variant": name, "renderer": VARIANTS[name][0], **VARIANTS[name][1],
                     "seconds": rendered["seconds"][name], "cost": COSTS[VARIANTS[name][0]], "views": per,
                     "stability": st, **{f"mean_{key}": _nanmean([v[key] for v in per]) for key in MEANS},
                     **{f"mean_{b}_pixels_{key}": _nanmean([v.get(f"{b}_pixels", {}).get(key) for v in per])
                        for b in measured for key in ("psnr_db", "flip")}})
        r = {k: (np.nan if v is None else v) for k, v in rows[-1].items() if k.startswith("mean_")}
        print(f"  {name:20s} PSNR {r['mean_psnr_db']:.2f} dB, SSIM {r['mean_ssim']:.3f}, FLIP {r['mean_flip']:.3f}, "
              f"surface {r['mean_surface_share']:.1%} (pixels every variant covers: {r['mean_psnr_common_db']:.2f} dB; "
              f"exposure-matched {r['mean_psnr_matched_db']:.2f} dB); walkthrough change "
              f"{_fmt((st or {}).get('mean'))} levels (max {_fmt((st or {}).get('max'))})", flush=True)

    views, bound_rows = [], {b: [] for b in measured}
    for k, cam in enumerate(cams):
        view = {"photo": cam.name, "frame_size": [cam.width, cam.height], "common_share": float(common[k].mean()),
                "sources": {v: source_breakdown(frames[v][k], photos[k], names) for v in SOURCES if v in frames}}
        if bounds:
            view["bounds"] = {"photos": bounds[k]["photos"], "seconds": bounds[k]["seconds"]}
            for b in measured:
                got = bounds[k].get(b)
                view["bounds"][b] = None
                if got is None:
                    continue
                q, fmap = quality(got["color"], photos[k], got["pixels"])
                view["bounds"][b] = {**q, "photo": got["photo"],
                                     "share": float(got["pixels"].sum() / max(common[k].sum(), 1))}
                bound_rows[b].append(view["bounds"][b])
                if k in shown:
                    maps[f"{b}_color_{k}"], maps[f"{b}_mask_{k}"] = got["color"], got["pixels"]
                    maps[f"{b}_flip_{k}"] = fmap.astype(np.float16)
        views.append(view)
    summary = None
    if bounds:
        summary = {"geometry": "the reference mesh: Embree casts at the view and at each kept photo"
                   if raycaster is not None else f"{depth_of}'s depth and the bundle's depth maps",
                   "depth_tolerance": {"relative": DEPTH_TOLERANCE_REL, "texels": DEPTH_TOLERANCE_TEXELS},
                   "best_single_min_share": p.best_single_min_share,
                   "seconds_per_view": float(np.mean([x["seconds"] for x in bounds]))}
        for b in measured:
            summary[b] = {f"mean_{key}": _nanmean([x[key] for x in bound_rows[b]])
                          for key in ("psnr_db", "ssim", "flip", "share")} | {"views": len(bound_rows[b])}
            mb = summary[b]
            print(f"  bound {b:13s} PSNR {_fmt(mb['mean_psnr_db'])} dB, FLIP {_fmt(mb['mean_flip'], 3)} on "
                  f"{_fmt(100 * (mb['mean_share'] or np.nan), 1)} % of the common pixels "
                  f"({mb['views']} of {len(cams)} views)", flush=True)

    if maps:
        Path(out).mkdir(parents=True, exist_ok=True)
        np.savez_compressed(Path(out) / "real_views.npz", **maps)
    meta = bundle.meta
    return {"scene": str(Path(ws.scene_dir).resolve()), "bundle": str(path), "holdout_every": p.holdout_every,
            "held_out": held_names, "kept": len(kept), "photos": len(scene.cameras),
            "proxies": meta["counts"]["proxies"], "points": meta["counts"]["points"],
            "preprocess_s": prep_s, "photometric": meta.get("photometric"),
            "photo_gains": bundle.photo_gains.tolist(),
            "gain_recovery": gain_recovery(ws.scene_dir, kept, bundle.photo_gains),
            "variants": rows, "views": views, "shown_views": shown,
            "shown_variants": [v for v in SHOWN if v in frames], "bounds": summary,
            "walkthrough": {"frames": len(walk), "keys": walk_keys, "frame_size": [walk[0].width, walk[0].height]}
            if walk else None,
            "maps_file": "real_views.npz" if maps else None, "maps": sorted(maps)}


def _fmt(v, digits: int = 2) -> str:
    return "nan" if v is None or not np.isfinite(v) else f"{v:.{digits}f}"


def _nanmean(values) -> float | None:
    a = np.asarray([np.nan if v is None else v for v in values], np.float64)
    a = a[np.isfinite(a)]
    return float(a.mean()) if a.size else None
