"""DMT preprocessing: a graph-cut labeling of every depth map's pixels (Arikan et al. 2014).

DMT textures each depth map on its own: every non-empty texel of photo ``i``'s depth map (at the
DMT resolution, :mod:`baselines.dmt.geometry`) is a 3D point; its candidates are the photos that see
it, by the same occlusion test as DMRT's proxies (:func:`dmrt.preprocess.candidates.find_candidates`, with the
bundle's own tolerances, against the bundle's stored depth maps); data costs are DMRT's
(:func:`dmrt.preprocess.labeling.candidate_data_costs`, normals from the depth-map grid) and so is the seam
term; the graph is the texel grid's 4-neighbourhood without edges to empty texels or across depth
jumps larger than the discontinuity threshold; :func:`dmrt.preprocess.labeling.alpha_expansion` minimises it.
Labeling time therefore grows with the number of texels (paper Table 3: 7 / 23 / 87 min at
256 / 512 / 1024 wide), where DMRT labels a fixed set of proxies.

The maps' graph cuts are independent of each other: ``workers`` local processes
(:func:`dmrt.preprocess.parallel.open_executor`, spawned, so a parent holding a GL context is never
forked) label one map at a time each, reading the bundle from disk once; the labels are the same
as one process's. Every map's statistics carry the CPU seconds of the process that labelled it
(``cpu_s``, :func:`time.process_time`), so the summed CPU time is known next to the wall clock.

Cheap labelers exist for frame-rate benchmarks on large scenes, where rendering cost does not
depend on the labels: ``"wta"`` (winner-take-all on the same data costs, no graph cut) and
``"own"`` (no labeling: every texel textured by its own depth map's photo, which sees it by
construction; seconds for any scene).

Cache (inside the bundle, per resolution and labeler)::

    BUNDLE/dmt/<W>/labels.npz     graph-cut labels: one (h, w) int32 array per depth map,
                                  keys map_00000, map_00001, ... (photo order), -1 = none
    BUNDLE/dmt/<W>/dmt.json       schema, width, labeler, sizes, the configuration, timings, energies
    BUNDLE/dmt/<W>-wta/...        the same for the winner-take-all labeler

Written into a temporary folder beside it and renamed when complete, so a cache folder that
exists is whole. A cache made with another configuration is recomputed; an unreadable or
inconsistent one is an error naming the file (delete the folder to recompute).
"""

from __future__ import annotations

import json
import typing
import time
import zipfile
from collections import OrderedDict
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Literal

import numpy as np

from baselines.dmt.geometry import (bounding_box, check_dmt_size, dmt_size, frustum_culled, grid_edges, grid_normals,
                                    load_depth_map, orient_normals, texel_points)
from dmrt.errors import InputError
from dmrt.io.atomic import atomic_dir
from dmrt.options import option, validate
from dmrt.preprocess.labeling import Candidates, LabelingConfig, alpha_expansion, candidate_data_costs, winner_take_all
from dmrt.preprocess.candidates import find_candidates
from dmrt.preprocess.config import PreprocessConfig

SCHEMA = "dmrt-dmt-labels"
SCHEMA_VERSION = 1
Labeler = Literal["graphcut", "wta", "own"]
LABELERS = typing.get_args(Labeler)


@dataclass
class DMTLabelingConfig:
    """How DMT labels its depth maps (lengths in metres)."""

    labeler: Labeler = option("graphcut", "graphcut: alpha-expansion per depth map (DMT's; what timing comparisons "
                                          "use); wta: winner-take-all on the same data costs; own: each map's own "
                                          "photo (both for frame-rate runs only)")
    discontinuity_threshold: float = option(0.20, "texel pairs whose depths differ by more than this are no graph "
                                                  "edge, metres (paper: 0.20, as at runtime)", minimum=0.0)
    energy: LabelingConfig | None = option(None, "energy and solver; None = the bundle's own (bundle.json "
                                                 "parameters.labeling), i.e. DMRT's")
    occlusion: PreprocessConfig | None = option(None, "occlusion test (occlusion_tolerance, occlusion_texels, "
                                                      "candidate_min_cos); None = the bundle's preprocessing "
                                                      "parameters, the very test DMRT's proxies were given")
    cache_mb: float = option(2048.0, "decoded photos and stored depth maps kept in memory while labeling, MiB "
                                     "per process", minimum=0.0)
    workers: int | None = option(None, "processes labeling depth maps at once (graph cuts and wta; the labels do "
                                       "not depend on it); None = every CPU core this process may use",
                                 minimum=1)

    def __post_init__(self):
        validate(self)


@dataclass
class _Resolved:
    """The configuration with the bundle's defaults filled in (what the cache records)."""

    labeler: str
    discontinuity_threshold: float
    energy: dict = field(default_factory=dict)
    occlusion: dict = field(default_factory=dict)


def _from_meta(cls, d: dict | None):
    names = {f.name for f in fields(cls)}
    return cls(**{k: v for k, v in (d or {}).items() if k in names})


def resolve_config(bundle, config: DMTLabelingConfig | None) -> tuple[LabelingConfig, PreprocessConfig, _Resolved]:
    """The energy and occlusion configurations to use (the bundle's where ``config`` leaves them None)."""
    config = config or DMTLabelingConfig()
    params = bundle.meta.get("parameters", {})
    energy = config.energy or _from_meta(LabelingConfig, params.get("labeling"))
    occl = config.occlusion or _from_meta(PreprocessConfig, params.get("preprocess"))
    keys = ("occlusion_tolerance", "occlusion_texels", "candidate_min_cos")
    resolved = _Resolved(config.labeler, float(config.discontinuity_threshold), asdict(energy),
                         {k: getattr(occl, k) for k in keys})
    return energy, occl, resolved


def cache_dir(bundle, width: int, labeler: str = "graphcut") -> Path:
    """``BUNDLE/dmt/<W>`` (graph cut) or ``BUNDLE/dmt/<W>-<labeler>``."""
    return Path(bundle.root) / "dmt" / (str(int(width)) if labeler == "graphcut" else f"{int(width)}-{labeler}")


class _LRU:
    """Values by key up to a byte budget (least recently used dropped first)."""

    def __init__(self, load, budget_mb: float):
        self.load, self.budget, self.items = load, budget_mb * 2 ** 20, OrderedDict()

    def __call__(self, key):
        if key in self.items:
            self.items.move_to_end(key)
            return self.items[key]
        value = self.items[key] = self.load(key)
        while len(self.items) > 1 and sum(v.nbytes for v in self.items.values()) > self.budget:
            self.items.popitem(last=False)
        return value


# ------------------------------------------------------------------------------------------------
# labeling one depth map
# ------------------------------------------------------------------------------------------------
def label_depth_map(bundle, i: int, depth: np.ndarray, stored_depth, photos, energy: LabelingConfig,
                    occlusion: PreprocessConfig, labeler: str = "graphcut", threshold: float = 0.20,
                    radius: float | None = None) -> tuple[np.ndarray, dict]:
    """Label the texels of photo ``i``'s DMT depth map.

    Parameters
    ----------
    bundle : Bundle
    i : int, the photo (and depth map).
    depth : (h, w) float32, the depth map at the DMT resolution (:func:`load_depth_map`).
    stored_depth, photos : callables ``j -> (H, W) float32`` stored depth map / ``j -> (H, W, 3) uint8``
        full-resolution photo (the occlusion test and the candidates' colours).
    energy, occlusion : configurations (:func:`resolve_config`).
    labeler : "graphcut", "wta" or "own".
    threshold : float, metres: no graph edge (and no normal tangent) across a larger depth jump.
    radius : float, metres, splat radius of the scan (the occlusion tolerance's first term);
        None = a coarse texel's footprint per point.

    Returns
    -------
    labels : (h, w) int32 photo index, -1 where empty or seen by no photo.
    stats : dict of counts, energies and wall seconds (``candidates_s``, ``costs_s``, ``cut_s``) and
        ``cpu_s``: CPU seconds of this process (:func:`time.process_time`, every thread) for the map.
    """
    c0 = time.process_time()
    t0 = time.perf_counter()
    h, w = depth.shape
    valid = (depth > 0).ravel()
    labels = np.full(h * w, -1, np.int32)
    stats = {"texels": int(valid.sum()), "edges": 0, "candidates_mean": 0.0, "energy_per_sweep": [],
             "photos_tested": 0, "candidates_s": 0.0, "costs_s": 0.0, "cut_s": 0.0, "cpu_s": 0.0}
    if not valid.any():
        stats["cpu_s"] = time.process_time() - c0
        return labels.reshape(h, w), stats
    if labeler == "own":  # no geometry needed
        labels[valid] = i
        stats["cut_s"] = time.perf_counter() - t0
        stats["cpu_s"] = time.process_time() - c0
        return labels.reshape(h, w), stats
    cams = [c.relative_to(bundle.origin) for c in bundle.cameras]
    cam = cams[i].scaled(w, h)
    pts = texel_points(depth, cam)
    normals = grid_normals(pts, depth, threshold).reshape(-1, 3)[valid]
    pts = pts.reshape(-1, 3)[valid]
    normals = orient_normals(normals, pts, cam.center)
    # only photos whose frustum meets this map's bounding box can see any of its points
    box = bounding_box(pts)[None]
    near = [j for j, c in enumerate(cams) if not frustum_culled(box, c.gl_view_projection(1e-3, 1e7))[0]]
    stats["photos_tested"] = len(near)
    if radius is None:
        r = (depth.ravel()[valid] / np.sqrt(cam.fx * cam.fy)).astype(np.float32)
    else:
        r = np.full(len(pts), radius, np.float32)
    sub = find_candidates(pts.astype(np.float32), normals, r, [cams[j] for j in near],
                          lambda k: stored_depth(near[k]), lambda k: photos(near[k]), occlusion, progress=False)
    cands = Candidates(sub.indptr, np.asarray(near, np.int32)[sub.photos], sub.colors, len(cams))
    t1 = time.perf_counter()
    centers = np.array([c.center for c in cams])
    focal = np.array([np.sqrt(c.fx * c.fy) for c in cams])
    cands.costs = candidate_data_costs(pts, normals, centers, focal, cands, energy)
    vidx = np.full(h * w, -1, np.int64)
    vidx[valid] = np.arange(valid.sum())
    edges = vidx[grid_edges(depth, threshold)]
    t2 = time.perf_counter()
    if labeler == "graphcut":
        res = alpha_expansion(None, edges, cands, energy)
        lab = res.labels
        stats["energy_per_sweep"] = [float(e) for e in res.energy_per_sweep]
        stats["truncated_terms"] = int(res.truncated_terms)
    else:
        lab = winner_take_all(cands.costs, cands)
    t3 = time.perf_counter()
    labels[valid] = lab
    stats.update(edges=int(len(edges)), candidates_mean=float(cands.counts().mean()),
                 unlabeled=int((lab < 0).sum()), candidates_s=t1 - t0, costs_s=t2 - t1, cut_s=t3 - t2,
                 cpu_s=time.process_time() - c0)
    return labels.reshape(h, w), stats


# ------------------------------------------------------------------------------------------------
# the cache
# ------------------------------------------------------------------------------------------------
def read_cache(bundle, width: int, labeler: str = "graphcut") -> tuple[list[np.ndarray], dict] | None:
    """The cached labels of one resolution and labeler, or None when there is no cache.

    Raises :class:`InputError` naming the file when the cache is unreadable or does not fit the
    bundle (delete the folder to recompute).
    """
    folder = cache_dir(bundle, width, labeler)
    meta_path, npz_path = folder / "dmt.json", folder / "labels.npz"
    if not folder.is_dir():
        return None
    hint = f"; delete {folder} to recompute"
    try:
        meta = json.loads(meta_path.read_text())
    except FileNotFoundError:
        raise InputError(meta_path, f"DMT labels cache lacks dmt.json{hint}") from None
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(meta_path, f"corrupt DMT labels cache ({exc}){hint}") from exc
    if meta.get("schema") != SCHEMA or meta.get("version") != SCHEMA_VERSION:
        raise InputError(meta_path, f"not a DMT labels cache of version {SCHEMA_VERSION} "
                                    f"(schema {meta.get('schema')!r}, version {meta.get('version')!r}){hint}")
    n = len(bundle.cameras)
    sizes = [list(dmt_size(c, width)) for c in bundle.cameras]
    if meta.get("sizes") != sizes:
        raise InputError(meta_path, f"field 'sizes' does not match this bundle's {n} depth maps at width {width}{hint}")
    try:
        with np.load(npz_path) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise InputError(npz_path, f"corrupt DMT labels cache ({exc}){hint}") from exc
    labels = []
    for i, (w, h) in enumerate(sizes):
        a = arrays.get(f"map_{i:05d}")
        if a is None or a.shape != (h, w) or a.dtype != np.int32:
            what = "missing" if a is None else f"{a.shape} {a.dtype}"
            raise InputError(npz_path, f"array 'map_{i:05d}' is {what}, expected ({h}, {w}) int32{hint}")
        if a.size and (a.min() < -1 or a.max() >= n):
            raise InputError(npz_path, f"array 'map_{i:05d}' holds labels outside -1..{n - 1}{hint}")
        labels.append(a)
    return labels, meta


def _write_cache(folder: Path, labels: list[np.ndarray], meta: dict) -> None:
    with atomic_dir(folder, what="DMT label cache") as tmp:
        np.savez(tmp / "labels.npz", **{f"map_{i:05d}": a for i, a in enumerate(labels)})
        (tmp / "dmt.json").write_text(json.dumps(meta, indent=1))


def warm_imports() -> None:
    """Import what labeling imports on first use (solver, sparse graphs, image and EXR readers), so
    that the first map a fresh process labels is not charged for it."""
    import importlib

    from PIL import Image

    for name in ("maxflow", "OpenEXR", "scipy.sparse", "scipy.spatial"):
        importlib.import_module(name)
    Image.preinit()  # the common image plugins


# In an executor's worker process: the bundle and its caches of decoded photos and depth maps,
# kept from one task to the next (a worker labels many maps, which share photos).
_WORKER: dict = {}


def _label_maps(maps, root, width: int, energy: LabelingConfig, occlusion: PreprocessConfig, labeler: str,
                threshold: float, radius: float | None, cache_mb: float) -> list[tuple[np.ndarray, dict]]:
    """:func:`label_depth_map` of the depth maps ``maps`` of the bundle at ``root`` (an executor's
    task: the bundle is read from the (shared) file system once per process)."""
    if _WORKER.get("key") != (root, cache_mb):
        from dmrt.io.bundle import read_bundle

        warm_imports()
        bundle = read_bundle(root)
        _WORKER.update(key=(root, cache_mb), bundle=bundle, stored=_LRU(bundle.depth_map, cache_mb / 2),
                       photos=_LRU(bundle.image, cache_mb / 2))
    bundle, stored, photos = _WORKER["bundle"], _WORKER["stored"], _WORKER["photos"]
    return [label_depth_map(bundle, i, load_depth_map(bundle, i, width, stored(i)), stored, photos, energy,
                            occlusion, labeler, threshold, radius) for i in maps]


def splat_radius(bundle) -> float | None:
    """The scan's splat radius (median of the proxies' P_HD radii), metres; None without them."""
    hd = bundle.proxy.get("hd_radii")
    return float(np.median(hd)) if hd is not None and len(hd) else None


def check_width(bundle, width: int) -> None:
    """Raise :class:`InputError` naming the depth-map file when DMT width ``width`` exceeds a
    stored depth map's resolution (``bundle.json``'s ``depthmap_sizes``, else the file's)."""
    sizes = bundle.meta.get("depthmap_sizes")
    for i in range(len(bundle.cameras)):
        check_dmt_size(bundle, i, width, tuple(sizes[i]) if sizes else bundle.depth_map(i).shape[::-1])


def label_maps(bundle, width: int, maps, config: DMTLabelingConfig | None = None, executor=None,
               progress: bool = False) -> list[tuple[np.ndarray, dict]]:
    """:func:`label_depth_map` of the depth maps ``maps`` (photo indices), in that order.

    Parameters
    ----------
    bundle : Bundle.  width : int, DMT width.  maps : iterable of int.
    config : DMTLabelingConfig (its ``workers`` is not read here: the executor decides).
    executor : optional, :mod:`dmrt.preprocess.parallel` (``open_executor``): one map per task, to
        the processes as they free up, each reading the bundle from its folder once; None = one
        after the other in this process.
    progress : bool, a tqdm bar over the maps.

    Returns
    -------
    list of (labels, stats) as :func:`label_depth_map`'s; ``stats["cpu_s"]`` is the CPU time of the
    process that labelled the map. The labels do not depend on the executor.
    """
    from tqdm.auto import tqdm

    config = config or DMTLabelingConfig()
    energy, occl, _ = resolve_config(bundle, config)
    maps = [int(i) for i in maps]
    check_width(bundle, width)  # here, before any process starts on a map
    task = dict(width=int(width), energy=energy, occlusion=occl, labeler=config.labeler,
                threshold=config.discontinuity_threshold, radius=splat_radius(bundle), cache_mb=config.cache_mb)
    if executor is not None and executor.distributed:
        parts = executor.map(_label_maps, [[i] for i in maps], desc=f"DMT labeling {width}", progress=progress,
                             root=str(Path(bundle.root).resolve()), **task)
        return [r for part in parts for r in part]
    stored = _LRU(bundle.depth_map, config.cache_mb / 2)
    photos = _LRU(bundle.image, config.cache_mb / 2)
    return [label_depth_map(bundle, i, load_depth_map(bundle, i, width, stored(i)), stored, photos, energy, occl,
                            config.labeler, config.discontinuity_threshold, task["radius"])
            for i in tqdm(maps, desc=f"DMT labeling {width}", unit="map", disable=not progress)]


def dmt_labels(bundle, width: int, config: DMTLabelingConfig | None = None, progress: bool = True,
               recompute: bool = False, executor=None) -> tuple[list[np.ndarray], dict]:
    """The DMT labels of every depth map at width ``width``: loaded from the bundle's cache, or
    computed (with a progress bar) and cached.

    Parameters
    ----------
    bundle : Bundle
    width : int, DMT depth-map width in texels (heights follow each photo's aspect); at most the
        stored depth maps' width.
    config : DMTLabelingConfig (``workers``: local processes when no ``executor`` is given)
    progress : bool, a tqdm bar over the depth maps
    recompute : bool, ignore (and replace) an existing cache
    executor : optional, :mod:`dmrt.preprocess.parallel`: the per-map labelings (graph cuts) as
        its tasks (a Dask cluster's, reading the bundle from the shared file system), instead of
        ``config.workers`` local processes (:func:`label_maps`); the labels are the same (each
        map's cut is independent of the others)

    Returns
    -------
    labels : list of (h_i, w_i) int32 arrays, photo order, -1 = none.
    meta : dict, the cache's ``dmt.json`` (``timings`` in seconds: ``total_s`` wall clock, ``cpu_s``
        the maps' CPU seconds summed over the processes, and the per-phase wall seconds summed over
        the maps; ``workers``; per-map ``maps`` statistics; ``config``) plus ``cached`` (True when
        loaded).
    """
    from tqdm.auto import tqdm

    config = config or DMTLabelingConfig()
    energy, occl, resolved = resolve_config(bundle, config)
    n = len(bundle.cameras)
    width = int(width)
    if not recompute:
        found = read_cache(bundle, width, config.labeler)
        if found is not None and found[1].get("config") == json.loads(json.dumps(asdict(resolved))):
            found[1]["cached"] = True
            return found
        if found is not None and progress:
            tqdm.write(f"{cache_dir(bundle, width, config.labeler)}: made with another configuration, recomputing")
    t_start = time.perf_counter()
    if executor is not None:
        workers = executor.workers
        results = label_maps(bundle, width, range(n), config, executor, progress)
    else:
        from dmrt.preprocess.parallel import default_workers, open_executor

        # "own" labels take microseconds a map: processes would only cost their start
        workers = 1 if config.labeler == "own" else min(config.workers or default_workers(), n)
        with open_executor(None, workers=workers) as local:
            results = label_maps(bundle, width, range(n), config, local, progress)
    labels = [lab for lab, _ in results]
    per_map = [st for _, st in results]
    total = time.perf_counter() - t_start
    meta = {
        "schema": SCHEMA, "version": SCHEMA_VERSION, "width": width, "labeler": config.labeler,
        "sizes": [list(dmt_size(c, width)) for c in bundle.cameras],
        "config": asdict(resolved), "splat_radius_m": splat_radius(bundle), "workers": workers,
        "timings": {"total_s": round(total, 3),
                    **{k: round(sum(m[k] for m in per_map), 3) for k in ("cpu_s", "candidates_s", "costs_s", "cut_s")}},
        "counts": {"texels": int(sum(m["texels"] for m in per_map)),
                   "edges": int(sum(m["edges"] for m in per_map)),
                   "unlabeled": int(sum(m.get("unlabeled", 0) for m in per_map))},
        "energy": {"initial": float(sum(m["energy_per_sweep"][0] for m in per_map if m["energy_per_sweep"])),
                   "final": float(sum(m["energy_per_sweep"][-1] for m in per_map if m["energy_per_sweep"]))},
        "maps": per_map,
        "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
    }
    _write_cache(cache_dir(bundle, width, config.labeler), labels, meta)
    meta["cached"] = False
    return labels, meta
