"""The preprocessing configuration: one dataclass whose fields are the ``dmrt preprocess`` options."""

from __future__ import annotations

from dataclasses import dataclass


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
