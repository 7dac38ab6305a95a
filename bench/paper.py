"""The paper's numbers as data (Arikan, Preiner, Wimmer, TVCG 2016; summary in ``../shared/PAPER.md``).

Everything was measured on a GeForce GTX TITAN at 1280x720 on Scene 2 (682M points, 192 photos,
proxies sub-sampled 686x = 1M) unless a note says otherwise. The report (:mod:`bench.report`)
puts these next to the measured values; nothing here is computed.
"""

from __future__ import annotations

MACHINE = "GeForce GTX TITAN, Intel i7-4770K, 1280x720 frames"

# Table 1: scene characteristics (the benchmarks compare against Scene 2).
TABLE1 = {
    "Scene 1": {"points": 35_000_000, "photos": 188},
    "Scene 2": {"points": 682_000_000, "photos": 192, "proxies": 1_000_000, "subsampling_factor": 686,
                "depthmap_size": (1024, 684)},
    "Scene 3": {"points": 1_091_000_000, "photos": 161},
}

# Table 2: ms per stage over a walkthrough of Scene 2, per layer count. The paper has no separate
# leveling stage: screen-space leveling is part of its texturing pass.
TABLE2_LAYERS = (1, 3, 5, 7, 9, 11)
TABLE2 = {
    "visibility": (2, 6, 9.8, 13.7, 17.5, 21.2),
    "raytracing": (1.2, 2, 2.3, 2.7, 3, 3.3),
    "labeling": (2, 2, 2, 2, 2, 2),
    "image_management": (2.5, 2.8, 2.9, 3.1, 3.3, 3.3),
    "texturing": (6.3, 6.4, 6.3, 6.3, 6.3, 6.3),
    "total": (14, 19.2, 23.3, 27.8, 32.1, 36.1),
    "fps": (71, 52, 43, 36, 31, 28),
}

# Table 3: DMT (per depth-map resolution, keyed by width) vs DMRT (1024x684 depth maps, 1M proxies,
# 5 layers). Labeling times in seconds; fps as (min, avg, max) over a walkthrough.
TABLE3_DMT = {
    256: {"size": (256, 171), "labeling_s": 7 * 60, "fps": (32, 45, 84)},
    512: {"size": (512, 342), "labeling_s": 23 * 60, "fps": (11, 17, 46)},
    1024: {"size": (1024, 684), "labeling_s": 87 * 60, "fps": (3, 5, 16)},
}
TABLE3_DMRT = {"size": (1024, 684), "proxies": 1_000_000, "layers": 5, "labeling_s": 3.4 * 60,
               "fps": (30, 43, 74)}

# Fig. 7: proxy-cloud size vs labeling time, layers and fps (pairs of layers and fps as shown).
FIG7 = [
    {"proxies": 4_400_000, "labeling_s": 16.4 * 60, "layers_fps": [(3, 44)]},
    {"proxies": 1_000_000, "labeling_s": 3.4 * 60, "layers_fps": [(3, 54), (4, 48)]},
    {"proxies": 200_000, "labeling_s": 0.8 * 60, "layers_fps": [(4, 49), (7, 36)]},
]

# Section 6.4 (Figs. 9 and 10): mean iterative-search steps per pixel and raytracing-pass ms, with
# 4 layers, and the worst case with splat radii x2.5 (4 layers, then the 11 it needed).
CONVERGENCE = [
    {"case": "baseline", "radius_scale": 1.0, "layers": 4, "mean_iterations": 4.6, "raytracing_ms": 2.4},
    {"case": "radii x2.5", "radius_scale": 2.5, "layers": 4, "mean_iterations": 9.5, "raytracing_ms": 4.2},
    {"case": "radii x2.5", "radius_scale": 2.5, "layers": 11, "mean_iterations": 11.0, "raytracing_ms": 8.0},
]
CONVERGENCE_MAX_STEPS = 100
CONVERGENCE_BINARY_STEPS = 20

# Fig. 8 / Section 6.3 ran with 4 layers and 1M proxies; Fig. 13 shows 1, 2 and 3 layers (no numbers:
# "two layers: barely visible artifacts, three: almost none").
FIG8_LAYERS = 4
FIG13_LAYERS = (1, 2, 3)

# Section 6.2: GPU memory. Formulas: a depth map is one float per texel; a low-resolution photo
# 256x171 RGB8; a proxy point 6 floats + 1 int; a layer pixel 2 floats; the photo cache 1 GB.
# The stated 37 MB (proxies) and 28 MB (layers) are swapped with respect to these formulas
# (1M x 28 B = 28 MB; 1280 x 720 x 8 B x 5 = 36.9 MB); the sum, 65 MB, agrees.
MEMORY_MB = {
    "depthmap_each": 2.8,
    "images_low_each": 0.13,
    "depthmaps_and_images_low": 563,
    "proxies": 37,
    "layers": 28,
    "image_cache": 1024,
}
BYTES_PER_PROXY = 6 * 4 + 4
BYTES_PER_LAYER_PIXEL = 2 * 4
LOWRES_SIZE = (256, 171)
