"""Depth maps made with the scan-grid radii and normals against those made with kNN's, each against
Embree on the scene's mesh: what ``--radii scan`` changes in the maps the renderer and DMT rely on.

    python -m bench.bench_radii_depthmaps --preset tiny --work /tmp/radii [--width 256] [--scan-scale 1.06]
        [--json FILE]

The preset's scene is generated into ``--work`` (reused when it is there) and preprocessed twice,
``--radii knn`` and ``--radii scan``, with ``--depthmap-width`` ``--width`` and the other options at
their defaults. For every photo, its depth map against the mesh's camera z at the same pixels
(``reference.raycast.MeshRaycaster``); printed per path: |dz| over the pixels where both hit
(median, 90th and 99th percentiles, mm: the last are silhouettes, where a disc overhangs an edge),
the share of the mesh's pixels the map covers, and the proxies' splat radii (median, mm).
``--scan-scale S`` adds a third path, ``--radii scan --radius-scale S``: whether the tail follows the
discs' size (the scan's radii exceed kNN's near the scanners' zenith and where stations overlap).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np


def main(argv=None) -> dict:
    from bench.scenes.synthetic import PRESETS, generate_scene
    from dmrt.io.bundle import read_bundle
    from dmrt.io.scene import load_scene
    from dmrt.preprocess.pipeline import PreprocessConfig, preprocess
    from reference.raycast import MeshRaycaster

    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--preset", default="tiny", choices=sorted(PRESETS))
    ap.add_argument("--work", type=Path, required=True, help="folder for the scene (reused) and the two bundles")
    ap.add_argument("--width", type=int, default=256, help="depth-map width (--depthmap-width)")
    ap.add_argument("--scan-scale", type=float, help="also the scan path at this --radius-scale")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)

    scene_dir = args.work / "scene"
    if not (scene_dir / "points.ply").is_file():
        generate_scene(PRESETS[args.preset], scene_dir, progress=False)
    scene = load_scene(scene_dir)
    mesh = MeshRaycaster.from_file(scene.mesh_path)
    out = {"preset": args.preset, "width": args.width, "points": scene.n_points, "paths": {}}
    default_scale = PreprocessConfig().radius_scale
    paths = [("knn", "knn", default_scale), ("scan", "scan", default_scale)]
    if args.scan_scale:
        paths.append((f"scan-{args.scan_scale:g}", "scan", args.scan_scale))
    for name, radii, scale in paths:
        config = PreprocessConfig(depthmap_width=args.width, radii=radii, radius_scale=scale)
        bundle = read_bundle(preprocess(scene_dir, args.work / name, config, force=True, progress=False))
        dz, cover = [], []
        for j, cam in enumerate(bundle.cameras):
            d = bundle.depth_map(j)
            ref, face, _ = mesh.cast_camera(cam.resized(d.shape[1], d.shape[0]))
            both = (d > 0) & (face >= 0)
            dz.append(np.abs(d[both] - ref[both]))
            cover.append(both.sum() / max(int((face >= 0).sum()), 1))
        dz = np.concatenate(dz) * 1e3
        row = {"dz_mm": {f"p{q}": float(np.percentile(dz, q)) for q in (50, 90, 99)},
               "coverage": float(np.mean(cover)), "radius_mm_median": float(np.median(bundle.proxy["hd_radii"]) * 1e3)}
        out["paths"][name] = row
        print(f"{name:4s}: |dz| median {row['dz_mm']['p50']:.2f} mm, p90 {row['dz_mm']['p90']:.1f}, "
              f"p99 {row['dz_mm']['p99']:.1f} mm; coverage {row['coverage']:.4f}; proxies' splat radius median "
              f"{row['radius_mm_median']:.2f} mm", flush=True)
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
