"""Radii and normals from the scan's grid (dmrt.preprocess.scangrid) against the kNN path
(dmrt.preprocess.normals.process_chunked), on a synthetic scene where both apply: speed and agreement.

    python -m bench.bench_scangrid --preset small --scene /tmp/small [--workers N | --threads N] [--json FILE]

The scene is generated once into ``--scene`` (reused when it is there) with the preset's scanner
and a single small photo: the points are the preset's own (the photos come after the scan in
the generator), and photos are not needed here. Both paths run as the pipeline runs them, on the
same points, default options (``--radius-scale`` 1.5, ``--normals-k`` 16, ``--radius-k`` 8,
``--memory-limit-mb`` 2048; the scan path computes normals even where the file has some):

* scan: one streamed pass over ``points.ply`` (:func:`~dmrt.preprocess.scangrid.scan_attributes`),
  on ``--threads`` threads, or in ``--workers`` processes (a record range each, as the pipeline
  runs it; spawned before the clock starts);
* knn: :func:`~dmrt.preprocess.normals.process_chunked` over the points relative to the scene
  origin, oriented toward the nearest photo camera (in memory when the cloud fits the budget, else
  in buckets; ``--knn-memory-mb`` sets the budget).

Printed: points per second of each (wall time, this machine's cores) and CPU microseconds per
point (this process's threads together: steadier than wall time on a shared machine); the ratio of the radii
(scan / knn: median and 5th-95th percentiles, overall and by the angle between surface and beam);
the angle between the two paths' normals and between each and the true surface normals (the
mesh's face hit by the point's beam, Embree), as medians and 90th percentiles (orientation
ignored: the paths face different viewpoints); both also by the beam's elevation (world z: the
synthetic scanners stand upright; below the horizon are floors and the lower walls, which photos
see most; near the zenith the beams crowd into rings).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from bench.scenes.synthetic import PRESETS, generate_scene
from dmrt.io.scene import load_scene
from dmrt.preprocess.normals import process_chunked
from dmrt.preprocess.parallel import open_executor
from dmrt.preprocess.scangrid import scan_attributes
from reference.raycast import MeshRaycaster


def _scene(preset: str, path: Path) -> Path:
    if not (path / "scans.json").exists():
        # the preset's cloud; one tiny photo (the photos are placed and rendered after the scan)
        generate_scene(replace(PRESETS[preset], photos=1, photo_size=(32, 22), supersample=1), path, force=True)
    return path


def _cpu_s() -> float:
    """CPU seconds of this process (and of worker processes that have ended)."""
    r = [resource.getrusage(who) for who in (resource.RUSAGE_SELF, resource.RUSAGE_CHILDREN)]
    return sum(x.ru_utime + x.ru_stime for x in r)


def _angles(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Unsigned angles between unit normals, degrees."""
    return np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", a, b)), 0.0, 1.0)))


def _stats(x: np.ndarray, q=(5, 50, 95)) -> dict:
    return {f"p{p}": round(float(np.percentile(x, p)), 4) for p in q}


def main(argv=None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--preset", default="small", choices=sorted(PRESETS))
    ap.add_argument("--scene", type=Path, required=True, help="the generated scene's folder (reused)")
    ap.add_argument("--threads", type=int, default=None, help="scan pass threads (default: one per core)")
    ap.add_argument("--workers", type=int, default=1, help="scan pass processes (>1: a record range each)")
    ap.add_argument("--knn-memory-mb", type=float, default=2048)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)

    scene = load_scene(_scene(args.preset, args.scene), check_images=False)
    n = scene.n_points
    work = Path(tempfile.mkdtemp(prefix="bench-scangrid-"))
    try:
        with open_executor(None, workers=args.workers) as ex:
            c0, t0 = _cpu_s(), time.perf_counter()
            scan = scan_attributes(scene.point_range(), scene.scan_structure, n, work / "scan", scale=1.5,
                                   k_normals=16, normals=True, threads=args.threads, executor=ex)
            scan_s, scan_cpu = time.perf_counter() - t0, _cpu_s() - c0
        origin = scene.origin

        def chunks():
            for pc in scene.point_range()():
                yield pc.positions - origin, {}

        centres = np.array([c.center for c in scene.cameras]) - origin
        c0, t0 = _cpu_s(), time.perf_counter()
        knn = process_chunked(chunks, work / "knn", k_normals=16, k_radii=8, scale=1.5, viewpoints=centres,
                              memory_limit_mb=args.knn_memory_mb, progress=False)
        knn_s, knn_cpu = time.perf_counter() - t0, _cpu_s() - c0

        r_scan = np.load(work / "scan" / "radii.npy")
        n_scan = np.load(work / "scan" / "normals.npy")
        r_knn, n_knn = np.asarray(knn.radii), np.asarray(knn.normals)
        # the truth: the face each point's beam hit
        pos = scene.read_points().positions
        st = scene.scan_structure
        station = np.repeat(np.arange(len(st.stations)), [s.points[1] - s.points[0] for s in st.stations])
        beam = pos - st.positions[station]
        rc = MeshRaycaster.from_file(scene.mesh_path, origin=origin)
        truth = np.zeros_like(beam)
        for k, s in enumerate(st.positions):
            sel = station == k
            _, face = rc.intersect(s, beam[sel] * 1.05)  # a little past the noisy point
            truth[sel] = rc.face_normals[np.maximum(face, 0)]
        u = beam / np.linalg.norm(beam, axis=1, keepdims=True)
        cos = np.abs(np.einsum("ij,ij->i", truth, u))
        ratio = r_scan / r_knn
        elevation = np.degrees(np.arcsin(np.clip(u[:, 2], -1.0, 1.0)))
        out = {
            "preset": args.preset, "points": n, "stations": len(st.stations), "machine": platform.node(),
            "cores": len(os.sched_getaffinity(0)), "threads": args.threads, "workers": args.workers,
            "scan_s": round(scan_s, 3), "knn_s": round(knn_s, 3), "knn_buckets": knn.n_buckets,
            "scan_points_per_s": round(n / scan_s), "knn_points_per_s": round(n / knn_s),
            "speedup": round(knn_s / scan_s, 2),
            # (worker processes' CPU is not seen until they end: only without them)
            "scan_cpu_us_per_point": round(1e6 * scan_cpu / n, 3) if args.workers == 1 else None,
            "knn_cpu_us_per_point": round(1e6 * knn_cpu / n, 3),
            "cpu_ratio": round(knn_cpu / scan_cpu, 2) if args.workers == 1 else None,
            "scan_counts": scan.counts,
            "radius_ratio_scan_over_knn": _stats(ratio),
            "radius_ratio_by_incidence": {
                label: _stats(ratio[sel]) for label, sel in (("facing (<30 deg)", cos > np.cos(np.radians(30))),
                                                             ("oblique (30-60)", (cos <= np.cos(np.radians(30)))
                                                              & (cos > 0.5)),
                                                             ("grazing (>60)", cos <= 0.5)) if sel.any()},
            "normal_angle_deg": {
                "scan_vs_knn": _stats(_angles(n_scan, n_knn), (50, 90)),
                "scan_vs_truth": _stats(_angles(n_scan, truth), (50, 90)),
                "knn_vs_truth": _stats(_angles(n_knn, truth), (50, 90)),
            },
            "by_elevation": {
                f"{lo} to {hi} deg": {"points": round(float(sel.mean()), 4),
                                      "radius_ratio_scan_over_knn": _stats(ratio[sel]),
                                      "normal_angle_to_truth": {
                                          "scan": _stats(_angles(n_scan[sel], truth[sel]), (50, 90)),
                                          "knn": _stats(_angles(n_knn[sel], truth[sel]), (50, 90))}}
                for lo, hi in ((-90, -45), (-45, 0), (0, 60), (60, 75), (75, 90))
                for sel in [(elevation >= lo) & (elevation < hi) if hi < 90 else elevation >= lo] if sel.any()},
        }
    finally:
        shutil.rmtree(work, ignore_errors=True)
    print(json.dumps(out, indent=1))
    if args.json:
        args.json.write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
