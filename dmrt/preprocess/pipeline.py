"""Preprocessing (paper Section 4): scene -> scene bundle.

Phases, each with a progress bar and a wall-clock timing in ``bundle.json``:

1. **octree** — P_HD into nested levels of detail, out of core (:mod:`dmrt.preprocess.octree`);
2. **normals/radii** — normals by plane fit where the input has none, oriented toward the nearest
   photo camera; splat radii from the local density (:mod:`dmrt.preprocess.normals`), out of core;
3. **depth maps** — P_HD splatted as oriented discs from every photo's camera (:mod:`dmrt.preprocess.depthmaps`);
4. **proxies** — P_LD = the k coarsest octree levels, with radii from their own density;
5. **candidates** — the photos that see each proxy: inside the frame, in front, not grazing, and
   not occluded according to that photo's depth map;
6. **labeling** — one photo per proxy by alpha-expansion (:mod:`dmrt.preprocess.labeling`);
7. **bundle** — written atomically (:mod:`dmrt.io.bundle`) with low-resolution photo copies.
"""

from __future__ import annotations

import resource
import shlex
import shutil
import sys
import time
from dataclasses import asdict
from pathlib import Path

import numpy as np
from tqdm import tqdm

from dmrt.io.bundle import BundleWriter, camera_to_json
from dmrt.io.exr import read_depth_exr, write_depth_exr
from dmrt.preprocess.config import PreprocessConfig
from dmrt.preprocess.labeling import LabelingConfig
from dmrt.preprocess.proxies import choose_proxy_levels, label_proxies
from dmrt.io.scene import Scene, load_scene


def _gl_renderer_string() -> str:
    from dmrt.gl import get_context, renderer_info

    info = renderer_info(get_context())
    return f"{info['renderer']} ({info['version']})"


def preprocess(scene_dir, out, config: PreprocessConfig | None = None,
               labeling: LabelingConfig | None = None, force: bool = False, progress: bool = True) -> Path:
    """Preprocess ``scene_dir`` into the bundle ``out``; returns its path."""
    from PIL import Image

    from dmrt.preprocess.depthmaps import DepthMapConfig, DepthMapRenderer
    from dmrt.gl import GpuTimer, get_context
    from dmrt.preprocess.normals import process_chunked
    from dmrt.preprocess.octree import Octree, OctreeConfig

    config = config or PreprocessConfig()
    labeling = labeling or LabelingConfig()
    t_all = time.perf_counter()
    scene: Scene = load_scene(scene_dir, chunk_size=config.chunk_points)
    origin = scene.origin
    timings: dict[str, float] = {}
    cams_local = [c.relative_to(origin) for c in scene.cameras]

    peak_rss: dict[str, float] = {}

    def tic(name, t0):
        timings[name] = round(time.perf_counter() - t0, 3)
        # peak resident memory so far (MiB), so the phase that raised it can be read off
        peak_rss[name] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)

    with BundleWriter(out, force=force) as bw:
        work = bw.tmp / "work"
        # 1. octree (positions relative to the origin keep float32 safe later; float64 here)
        t0 = time.perf_counter()
        def scene_chunks():
            for pc in scene.iter_points(config.chunk_points):
                yield pc.positions - origin, {"normals": pc.normals, "colors": pc.colors}
        octree = Octree.build(scene_chunks, work / "octree",
                              OctreeConfig(levels=config.octree_levels, memory_limit_mb=config.memory_limit_mb),
                              progress=progress)
        tic("octree_s", t0)

        # 2. normals (if missing) and splat radii over P_HD, in octree order (coarsest level first)
        t0 = time.perf_counter()
        has_normals = octree.read_level(0).get("normals") is not None
        centers = np.array([c.center for c in cams_local])
        attrs = process_chunked(lambda: octree.iter_levels(chunk_size=config.chunk_points), work / "attrs",
                                normals=not has_normals, radii=True, k_normals=config.normals_k,
                                k_radii=config.radius_k, scale=config.radius_scale, viewpoints=centers,
                                memory_limit_mb=config.memory_limit_mb, progress=progress)
        tic("normals_radii_s", t0)

        def hd_chunks():
            g = 0
            for ch in octree.iter_levels(chunk_size=config.chunk_points):
                m = len(ch["positions"])
                nrm = ch["normals"] if has_normals else attrs.normals[g:g + m]
                yield ch["positions"].astype(np.float32), np.asarray(nrm, np.float32), np.asarray(attrs.radii[g:g + m])
                g += m

        # 3. depth maps
        t0 = time.perf_counter()
        ctx = get_context()
        timer = GpuTimer(ctx)
        # GPU batches of one read chunk: on a CPU renderer (llvmpipe) GPU buffers are host memory
        renderer = DepthMapRenderer(ctx, DepthMapConfig(width=config.depthmap_width, method=config.depthmap_method,
                                                        chunk_points=config.chunk_points), timer=timer)
        depth_files, depth_sizes = [], []
        bar = tqdm(total=len(cams_local), desc="depth maps", unit="map", disable=not progress)
        for j, depth in renderer.render_many(cams_local, hd_chunks, resident_mb=config.resident_mb):
            rel = f"depthmaps/{Path(scene.cameras[j].name).stem}.exr"
            write_depth_exr(bw.tmp / rel, depth)
            depth_files.append(rel)
            depth_sizes.append([depth.shape[1], depth.shape[0]])
            bar.update()
        bar.close()
        renderer.release()
        tic("depthmaps_s", t0)
        timings["depthmaps_gpu_ms"] = {k: round(v, 3) for k, v in timer.ms.items()}

        # 4-6. proxies (the k coarsest levels, first in octree order) with radii of their own
        # density, their candidate photos and labels
        t0 = time.perf_counter()
        lod_counts = octree.lod_counts()
        k = choose_proxy_levels(lod_counts, octree.n_points, config)
        proxy = octree.read_lod(k)
        n_proxy = len(proxy["positions"])
        proxy = {"positions": proxy["positions"],
                 "normals": proxy["normals"] if has_normals else np.asarray(attrs.normals[:n_proxy]),
                 "hd_radii": np.asarray(attrs.radii[:n_proxy], np.float32)}
        read_s = time.perf_counter() - t0
        photos_cache: dict[int, np.ndarray] = {}

        def photo(j):
            if j not in photos_cache:
                photos_cache.clear()  # one photo at a time: 192 full photos need not sit in RAM
                photos_cache[j] = scene.read_image(j)
            return photos_cache[j]

        proxies = label_proxies(proxy, cams_local, lambda j: read_depth_exr(bw.tmp / depth_files[j]), photo,
                                config, labeling, progress=progress)
        timings.update(proxies.timings, proxies_s=round(proxies.timings["proxies_s"] + read_s, 3))
        for name in ("proxies_s", "candidates_s", "labeling_s"):
            peak_rss[name] = round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024, 1)

        # 7. photos and their low-resolution copies
        t0 = time.perf_counter()
        images, images_low = [], []
        for j, cam in enumerate(tqdm(scene.cameras, desc="photos", unit="photo", disable=not progress)):
            images.append(bw.add_image(scene.image_paths[j], cam.name))
            low_h = max(1, round(config.lowres_width * cam.height / cam.width))
            rel = f"images_low/{Path(cam.name).stem}.png"
            Image.fromarray(scene.read_image(j)).resize((config.lowres_width, low_h), Image.BOX).save(bw.tmp / rel)
            images_low.append(rel)
        tic("photos_s", t0)

        bw.write_proxy(**proxies.proxy)
        shutil.rmtree(work)
        timings["total_s"] = round(time.perf_counter() - t_all, 3)
        meta = {
            "scene": str(Path(scene_dir).resolve()),
            "command": " ".join(shlex.quote(a) for a in sys.argv),
            "created": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
            "gl_renderer": _gl_renderer_string(),
            "origin": origin.tolist(),
            "cameras": [camera_to_json(c) for c in scene.cameras],
            "images": images, "images_low": images_low, "depthmaps": depth_files,
            "depthmap_sizes": depth_sizes,
            "parameters": {"preprocess": asdict(config), "labeling": asdict(labeling)},
            "timings": timings,
            "peak_rss_mb_after": peak_rss,
            "counts": {
                "points": octree.n_points, "photos": len(scene.cameras), **proxies.counts(),
                "proxy_levels": k, "octree_level_counts": list(octree.level_counts),
                "lod_counts": lod_counts, "subsampling_factors": octree.subsampling_factors(),
                "normals_estimated": not has_normals,
            },
            "labeling": proxies.labeling_meta(),
        }
        return bw.finish(meta)

