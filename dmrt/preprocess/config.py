"""The preprocessing configuration: one dataclass whose fields are the ``dmrt preprocess`` options."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from dmrt.options import option, validate


@dataclass
class PreprocessConfig:
    """Preprocessing parameters (lengths in metres)."""

    depthmap_width: int = option(1024, "depth-map width in texels (paper: 1024x684); the height follows each "
                                       "photo's aspect", minimum=2)
    depthmap_method: Literal["compute", "raster"] = option(
        "compute", "depth-map splatting: compute (atomicMin; fast on GPUs with few raster units) or raster "
                   "(GL_POINTS); bit-identical maps")
    octree_levels: int = option(8, "levels of detail of P_HD", minimum=1)
    proxy_levels: int | None = option(None, "P_LD = this many coarsest octree levels; default from "
                                            "--proxy-count or --proxy-factor", minimum=1)
    proxy_count: int | None = option(None, "else: the level of detail whose size is nearest this many proxies",
                                     minimum=1)
    proxy_factor: float = option(32.0, "else: the level of detail whose |P_HD| / |P_LD| is nearest this "
                                       "(32M points -> ~1M proxies)", minimum=1.0)
    memory_limit_mb: float = option(2048, "point data held in memory at once by the out-of-core phases, MiB",
                                    minimum=0.01)
    # knn by default although the scan path preprocesses Scene 2's size in 123.9 s (issue #40): its depth
    # maps have the longer error tail (tiny, bench_radii_depthmaps: |dz| p90 19.5 mm against 10.9),
    # and with auto test_dmt's leveling test fails; auto is the intended default once that is mended
    radii: Literal["auto", "scan", "knn"] = option(
        "knn", "where splat radii and normals come from: scan (the scan's grid of beams: scans.json beside "
                "the cloud or structured E57 scans; range x angular step, no neighbour search), knn (the "
                "nearest neighbours), auto (scan where the scene has the structure, else knn)")
    normals_k: int = option(16, "neighbours of the normal plane fit", minimum=3)
    radius_k: int = option(8, "neighbour rank of the density-based splat radius", minimum=1)
    radius_scale: float = option(1.5, "splat radius = this x the radius_k-th neighbour distance (random scan "
                                      "sampling leaves gaps a grid would not: see dmrt/preprocess/normals.py)",
                                 minimum=0.0)
    occlusion_tolerance: float = option(3.0, "a proxy is visible in photo j if |z - D_j| <= this x its P_HD "
                                             "splat radius + --occlusion-texels x the depth map's texel "
                                             "footprint at that depth", minimum=0.0)
    occlusion_texels: float = option(2.0, "see --occlusion-tolerance", minimum=0.0)
    candidate_min_cos: float = option(0.1, "views more grazing than this cosine (~84 degrees) are no candidates",
                                      minimum=0.0, maximum=1.0)
    candidate_rim_fraction: float = option(
        1.0, "a candidate photo must also see this share of the proxy's disc rim (6 points at 0.8 of its "
             "radius): a photo that sees the centre but not the disc around it cannot show the pixels the disc "
             "covers (holes along depth edges); points that would lose every candidate keep them; 0 = centre "
             "test only", minimum=0.0, maximum=1.0)
    lowres_width: int = option(256, "width of the low-resolution photo copies (paper: 256x171)", minimum=1)
    chunk_points: int = option(1_000_000, "points read per chunk", minimum=1)
    resident_mb: float = option(4096, "GPU memory for P_HD while the depth maps are rendered, MiB", minimum=1.0)
    cull_points: int = option(4096, "frustum culling: each photo's depth map splats, and its candidate test "
                                    "projects, only the runs of this many consecutive points (octree order) whose "
                                    "box meets its frustum; 0 = every point for every photo (the same result, "
                                    "slower)", minimum=0)

    def __post_init__(self):
        validate(self)
