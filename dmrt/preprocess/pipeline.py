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
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from dmrt.io.bundle import BundleWriter, camera_to_json
from dmrt.preprocess.labeling import Candidates, LabelingConfig, label_points
from dmrt.io.scene import Scene, load_scene


@dataclass
class PreprocessConfig:
    """Preprocessing parameters (lengths in metres)."""

    depthmap_width: int = 1024        # paper: 1024x684 depth maps; height follows each photo's aspect
    depthmap_method: str = "compute"  # "compute" (fast on GPUs with few raster units) | "raster"
    octree_levels: int = 8            # levels of detail of P_HD
    proxy_levels: int | None = None   # P_LD = this many coarsest levels; default from proxy_factor
    proxy_count: int | None = None    # else: the LOD whose size is nearest this many proxies
    proxy_factor: float = 32.0        # else: the LOD whose |P_HD| / |P_LD| is nearest this (32M -> ~1M)
    memory_limit_mb: float = 2048     # point data held at once by the out-of-core phases
    normals_k: int = 16               # neighbours of the normal plane fit
    radius_k: int = 8                 # neighbour rank of the density-based splat radius
    radius_scale: float = 1.5         # random (scan) sampling leaves gaps a grid would not: see normals.py
    occlusion_tolerance: float = 3.0  # a proxy is visible in photo j if |z - D_j| <= this x its splat
    occlusion_texels: float = 2.0     # radius + this x the depth map's texel footprint at that depth
    candidate_min_cos: float = 0.1    # views more grazing than ~84 deg are no candidates
    # A candidate photo must also see this share of the proxy's disc rim (6 points at 0.8 of its
    # radius, same test): a photo that sees the centre but not the disc around it cannot show the
    # pixels the disc covers at runtime (holes along depth edges). Points that would lose every
    # candidate keep them. 0 = centre test only.
    candidate_rim_fraction: float = 1.0
    lowres_width: int = 256           # low-resolution photo copies (paper: 256x171)
    chunk_points: int = 1_000_000     # points read per chunk
    resident_mb: float = 4096         # GPU memory for P_HD during depth-map rendering


def _gl_renderer_string() -> str:
    from dmrt.gl import get_context, renderer_info

    info = renderer_info(get_context())
    return f"{info['renderer']} ({info['version']})"


def choose_proxy_levels(lod_counts: list[int], n_points: int, config: PreprocessConfig) -> int:
    """Number of coarsest octree levels that form P_LD."""
    if config.proxy_levels is not None:
        return max(1, min(int(config.proxy_levels), len(lod_counts)))
    factor = n_points / config.proxy_count if config.proxy_count else config.proxy_factor
    # levels of detail grow ~4x apart on surfaces: take the nearest on a log scale
    error = [abs(np.log(n_points / count / factor)) for count in lod_counts]
    return int(np.argmin(error)) + 1


def find_candidates(positions: np.ndarray, normals: np.ndarray, hd_radii: np.ndarray, cameras,
                    depth_maps, photos, config: PreprocessConfig, progress: bool = True,
                    radii: np.ndarray | None = None) -> Candidates:
    """The photos that see each proxy point, and the proxy's colour in each.

    Parameters
    ----------
    positions : (n, 3) float32, origin-relative metres.  normals : (n, 3) float32 unit.
    hd_radii : (n,) float32, the points' P_HD splat radii (the depth maps were drawn with them).
    cameras : origin-relative cameras (photo resolution).
    depth_maps : callable ``j -> (h, w) float32`` depth map of photo ``j``.
    photos : callable ``j -> (H, W, 3) uint8`` photo ``j``.
    radii : (n,) float32, optional, the proxies' own splat radii: with them a candidate must also
        see ``config.candidate_rim_fraction`` of the disc's rim.

    Returns
    -------
    Candidates (CSR over points; colours RGB 0..1).
    """
    from reference.render import sample_bilinear

    p = positions.astype(np.float64)
    rims = None
    if radii is not None and config.candidate_rim_fraction > 0:
        n = np.asarray(normals, np.float64)
        u = np.cross(n, np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]]))
        u /= np.maximum(np.linalg.norm(u, axis=1, keepdims=True), 1e-12)
        v = np.cross(n, u)
        r = 0.8 * np.asarray(radii, np.float64)[:, None]
        rims = [p + r * (np.cos(a) * u + np.sin(a) * v) for a in np.linspace(0, 2 * np.pi, 6, endpoint=False)]

    def seen(cam, depth, q, idx):
        """Which points ``q`` (m, 3) the depth map sees (its surface within the tolerance)."""
        h, w = depth.shape
        uv, z = cam.project(q)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        uvi = np.where(inside[:, None], uv, 0).astype(np.int64)
        d = np.where(inside, depth[uvi[:, 1], uvi[:, 0]], 0.0)
        # within a few splat radii (the map was drawn with discs of that size) plus a texel
        # footprint at this depth (sampling)
        tol = config.occlusion_tolerance * hd_radii[idx] + config.occlusion_texels * z / cam.fx
        return inside & (d > 0) & (np.abs(d - z) <= tol)

    pts, phs, cols, rim_ok = [], [], [], []
    for j, cam in enumerate(tqdm(cameras, desc="candidates", unit="photo", disable=not progress)):
        depth = depth_maps(j)
        h, w = depth.shape
        dm_cam = cam.scaled(w, h)
        uv, z = dm_cam.project(p)
        inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < w) & (uv[:, 1] >= 0) & (uv[:, 1] < h)
        idx = np.flatnonzero(inside)
        to_eye = cam.center - p[idx]
        cos = np.abs(np.einsum("ij,ij->i", to_eye, normals[idx])) / np.linalg.norm(to_eye, axis=1)
        idx = idx[(cos >= config.candidate_min_cos) & seen(dm_cam, depth, p[idx], idx)]
        if len(idx) == 0:
            continue
        uv_photo, _ = cam.project(p[idx])
        pts.append(idx)
        phs.append(np.full(len(idx), j))
        cols.append(sample_bilinear(photos(j), uv_photo) / 255.0)
        if rims is not None:
            frac = np.mean([seen(dm_cam, depth, rim[idx], idx) for rim in rims], axis=0)
            rim_ok.append(frac >= config.candidate_rim_fraction)
    if not pts:
        return Candidates(np.zeros(len(p) + 1, np.int64), np.zeros(0, np.int32), None, len(cameras))
    pts, phs, cols = np.concatenate(pts), np.concatenate(phs), np.concatenate(cols)
    if rims is not None:
        ok = np.concatenate(rim_ok)
        has_ok = np.zeros(len(p), bool)
        has_ok[pts[ok]] = True
        keep = ok | ~has_ok[pts]  # a point none of whose photos sees its rim keeps them all
        pts, phs, cols = pts[keep], phs[keep], cols[keep]
    return Candidates.from_pairs(pts, phs, cols, len(p), len(cameras))


def preprocess(scene_dir, out, config: PreprocessConfig | None = None,
               labeling: LabelingConfig | None = None, force: bool = False, progress: bool = True) -> Path:
    """Preprocess ``scene_dir`` into the bundle ``out``; returns its path."""
    from PIL import Image

    from dmrt.preprocess.depthmaps import DepthMapConfig, DepthMapRenderer, write_depth_exr
    from dmrt.gl import GpuTimer, get_context
    from dmrt.preprocess.normals import process_chunked, splat_radii
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

        # 4. proxies: the k coarsest levels (first in octree order) with radii of their own density
        t0 = time.perf_counter()
        lod_counts = octree.lod_counts()
        k = choose_proxy_levels(lod_counts, octree.n_points, config)
        proxy = octree.read_lod(k)
        n_proxy = len(proxy["positions"])
        positions = proxy["positions"].astype(np.float32)
        normals = (proxy["normals"] if has_normals else np.asarray(attrs.normals[:n_proxy])).astype(np.float32)
        hd_radii = np.asarray(attrs.radii[:n_proxy], np.float32)
        radii = splat_radii(positions, k=config.radius_k, scale=config.radius_scale)
        tic("proxies_s", t0)

        # 5. candidates
        t0 = time.perf_counter()
        photos_cache: dict[int, np.ndarray] = {}

        def photo(j):
            if j not in photos_cache:
                photos_cache.clear()  # one photo at a time: 192 full photos need not sit in RAM
                photos_cache[j] = scene.read_image(j)
            return photos_cache[j]

        from dmrt.preprocess.depthmaps import read_depth_exr
        cands = find_candidates(positions, normals, hd_radii, cams_local,
                                lambda j: read_depth_exr(bw.tmp / depth_files[j]), photo, config, progress,
                                radii=radii)
        tic("candidates_s", t0)

        # 6. labeling
        t0 = time.perf_counter()
        result = label_points(positions, normals, cands, cams_local, config=labeling, progress=progress)
        tic("labeling_s", t0)

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

        bw.write_proxy(positions=positions, normals=normals, radii=radii, labels=result.labels,
                       hd_radii=hd_radii)
        shutil.rmtree(work)
        timings["total_s"] = round(time.perf_counter() - t_all, 3)
        counts = cands.counts()
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
                "points": octree.n_points, "photos": len(scene.cameras), "proxies": n_proxy,
                "proxy_levels": k, "octree_level_counts": list(octree.level_counts),
                "lod_counts": lod_counts, "subsampling_factors": octree.subsampling_factors(),
                "candidates_mean": float(counts.mean()) if n_proxy else 0.0,
                "unlabeled_proxies": int((result.labels < 0).sum()),
                "normals_estimated": not has_normals,
            },
            "labeling": {"energy_per_sweep": result.energy_per_sweep,
                         "seconds_per_sweep": result.seconds_per_sweep,
                         "data_energy": result.data_energy, "smooth_energy": result.smooth_energy,
                         "edges": result.n_edges},
        }
        return bw.finish(meta)

