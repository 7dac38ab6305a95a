"""Benchmark of the proxy-point labeling (paper Section 4.3; Table 3 / Fig. 7 report 3.4 min for 1M
proxies and 192 photos on the paper's machine).

    python -m bench.bench_labeling --points 1000000 --photos 192 [--out FILE.json]

The problem is synthetic but shaped like a real scan: proxy points spread uniformly over the
surfaces of a box room (floor, ceiling, four walls) and a few free-standing blocks, photos taken
from inside (1024x684, 60 deg horizontal field of view, pointed at random surface points), a point
is a candidate of every photo whose frustum holds it, that faces it and is closer than
``--max-distance`` (about 10-20 candidates per point, as in a real scan; occlusion is not
simulated). The colour of a point in a photo is a smooth albedo pattern under a per-photo
exposure / white balance plus noise, so seams between photos matter. Times ``label_points`` end
to end (kNN graph, data costs, winner-take-all, alpha-expansion sweeps).
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import time
from dataclasses import asdict

import numpy as np

from dmrt.camera import Camera
from dmrt.preprocess.labeling import (Candidates, LabelingConfig, candidate_data_costs, energy, knn_edges,
                           label_points)

BENCH_VERSION = 1

ROOM = np.array([40.0, 24.0, 8.0])
# free-standing blocks: (min corner, max corner), metres
BLOCKS = [((8.0, 6.0, 0.0), (10.0, 8.0, 3.0)), ((20.0, 14.0, 0.0), (23.0, 15.0, 5.0)),
          ((30.0, 4.0, 0.0), (31.0, 9.0, 2.0)), ((14.0, 17.0, 0.0), (15.0, 18.0, 6.0))]


def _faces():
    """Axis-aligned rectangles (origin, edge u, edge v, normal); room faces look inward."""
    X, Y, Z = ROOM
    f = [((0, 0, 0), (X, 0, 0), (0, Y, 0), (0, 0, 1)),       # floor
         ((0, 0, Z), (X, 0, 0), (0, Y, 0), (0, 0, -1)),      # ceiling
         ((0, 0, 0), (X, 0, 0), (0, 0, Z), (0, 1, 0)),       # walls
         ((0, Y, 0), (X, 0, 0), (0, 0, Z), (0, -1, 0)),
         ((0, 0, 0), (0, Y, 0), (0, 0, Z), (1, 0, 0)),
         ((X, 0, 0), (0, Y, 0), (0, 0, Z), (-1, 0, 0))]
    for lo, hi in BLOCKS:  # four sides and the top of each block, facing out
        lo, hi = np.array(lo), np.array(hi)
        d = hi - lo
        f += [(lo, (d[0], 0, 0), (0, 0, d[2]), (0, -1, 0)),
              ((lo[0], hi[1], lo[2]), (d[0], 0, 0), (0, 0, d[2]), (0, 1, 0)),
              (lo, (0, d[1], 0), (0, 0, d[2]), (-1, 0, 0)),
              ((hi[0], lo[1], lo[2]), (0, d[1], 0), (0, 0, d[2]), (1, 0, 0)),
              ((lo[0], lo[1], hi[2]), (d[0], 0, 0), (0, d[1], 0), (0, 0, 1))]
    return [tuple(np.asarray(a, np.float64) for a in x) for x in f]


def make_problem(n_points: int, n_photos: int, seed: int = 0, max_distance: float = 20.0,
                 width: int = 1024, height: int = 684, fov_x: float = 60.0):
    """Synthetic labeling input: ``(positions, normals, Candidates, cameras)``."""
    rng = np.random.default_rng(seed)
    faces = _faces()
    area = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v, _ in faces])
    face = rng.choice(len(faces), n_points, p=area / area.sum())
    st = rng.random((n_points, 2))
    pos = np.empty((n_points, 3))
    nrm = np.empty((n_points, 3))
    for k, (o, u, v, nn) in enumerate(faces):
        s = face == k
        pos[s] = o + st[s, :1] * u + st[s, 1:] * v
        nrm[s] = nn
    # albedo: smooth pattern, different per face
    ph = rng.random((len(faces), 3)) * 6.28
    albedo = 0.5 + 0.3 * np.sin(pos[:, [0]] * 0.7 + pos[:, [1]] * 0.5 + pos[:, [2]] * 0.9
                                + ph[face]) * np.array([1.0, 0.8, 0.6])

    cams, hit_pts, hit_photos = [], [], []
    X, Y, Z = ROOM
    px, py, pz = (np.ascontiguousarray(pos[:, k], np.float32) for k in range(3))
    nx, ny, nz = (np.ascontiguousarray(nrm[:, k], np.float32) for k in range(3))
    for j in range(n_photos):
        while True:  # a photo position in the room, outside the blocks
            eye = rng.uniform([1.5, 1.5, 1.2], [X - 1.5, Y - 1.5, 2.2])
            if not any(np.all((eye > np.array(lo) - 0.5) & (eye < np.array(hi) + 0.5))
                       for lo, hi in BLOCKS):
                break
        target = pos[rng.integers(n_points)]
        if np.linalg.norm(target - eye) < 2.0:
            target = eye + np.array([1.0, 0.3, 0.1])
        cam = Camera.look_at(f"IMG_{j:04d}.jpg", eye, target, width, height, fov_x)
        cams.append(cam)
        # project (float32, structure of arrays: this runs 192 times over 1M points)
        dx, dy, dz = px - np.float32(eye[0]), py - np.float32(eye[1]), pz - np.float32(eye[2])
        R = cam.R.astype(np.float32)
        z = dx * R[2, 0] + dy * R[2, 1] + dz * R[2, 2]
        zc = np.maximum(z, np.float32(1e-6))
        u = (dx * R[0, 0] + dy * R[0, 1] + dz * R[0, 2]) / zc
        v = (dx * R[1, 0] + dy * R[1, 1] + dz * R[1, 2]) / zc
        hu, hv = np.float32(cam.cx / cam.fx), np.float32(cam.cy / cam.fy)
        dist2 = dx * dx + dy * dy + dz * dz
        facing = -(dx * nx + dy * ny + dz * nz)  # n . (C - p)
        vis = (z > 0.3) & (np.abs(u) < hu) & (np.abs(v) < hv) \
            & (dist2 < np.float32(max_distance ** 2)) & (facing > 0) \
            & (facing * facing > np.float32(0.05 ** 2) * dist2)
        idx = np.flatnonzero(vis).astype(np.int32)
        hit_pts.append(idx)
        hit_photos.append(np.full(idx.size, j, np.int32))
    pts = np.concatenate(hit_pts)
    phs = np.concatenate(hit_photos)
    cands = Candidates.from_pairs(pts, phs, None, n_points, n_photos)
    # colours: per-photo exposure and white balance, plus noise
    gain = rng.uniform(0.8, 1.2, n_photos)[:, None] * rng.uniform(0.92, 1.08, (n_photos, 3))
    rows = cands.rows()
    col = albedo[rows] * gain[cands.photos] + rng.normal(0, 0.02, (cands.nnz, 3))
    cands.colors = np.clip(col, 0, 1).astype(np.float32)
    return pos.astype(np.float32), nrm.astype(np.float32), cands, cams


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=1_000_000)
    ap.add_argument("--photos", type=int, default=192)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--max-distance", type=float, default=20.0,
                    help="metres; sets the candidates per point (20 m: ~14)")
    ap.add_argument("--sweeps", type=int, default=LabelingConfig.max_sweeps)
    ap.add_argument("--tolerance", type=float, default=LabelingConfig.tolerance)
    ap.add_argument("--no-skip", action="store_true", help="expand every label in every sweep")
    ap.add_argument("--full-moves", action="store_true",
                    help="full expansion moves in every sweep (LabelingConfig.local_moves=False)")
    ap.add_argument("--check", action="store_true",
                    help="recompute the final energy independently with dmrt.preprocess.labeling.energy")
    ap.add_argument("--progress", action="store_true")
    ap.add_argument("--out", help="write the results as JSON here")
    a = ap.parse_args(argv)

    t = time.perf_counter()
    pos, nrm, cands, cams = make_problem(a.points, a.photos, a.seed, a.max_distance)
    t_gen = time.perf_counter() - t
    cnt = cands.counts()
    print(f"problem: {a.points} points, {a.photos} photos, {cands.nnz} candidates "
          f"(mean {cnt.mean():.1f}, median {np.median(cnt):.0f}, max {cnt.max()} per point, "
          f"{(cnt == 0).sum()} points without any), generated in {t_gen:.1f} s")
    cfg = LabelingConfig(max_sweeps=a.sweeps, tolerance=a.tolerance,
                         skip_unchanged_labels=not a.no_skip, local_moves=not a.full_moves)
    load0 = os.getloadavg()[0]
    rss0 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    cpu0 = time.process_time()
    res = label_points(pos, nrm, cands, cams, config=cfg, progress=a.progress)
    cpu = time.process_time() - cpu0  # all threads of this process: independent of other load
    load1 = os.getloadavg()[0]
    rss1 = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024

    print(f"\nlabel_points: {res.seconds_total:.2f} s end to end on {os.cpu_count()} CPU(s), "
          f"{cpu:.2f} CPU s; load average {load0:.1f} -> {load1:.1f} "
          f"(paper: 3.4 min for 1M proxies, 192 photos)")
    print(f"setup (Morton order, data costs, kNN graph of {res.n_edges} edges, winner-take-all): "
          f"{res.seconds_setup:.2f} s; peak RSS {rss1:.0f} MB (input alone {rss0:.0f} MB)")
    print(f"{'sweep':>5} {'seconds':>8} {'energy':>14} {'relabeled':>10} {'cuts':>5} {'skipped':>7}")
    print(f"{'init':>5} {res.seconds_setup:8.2f} {res.energy_per_sweep[0]:14.2f}")
    for i, s in enumerate(res.seconds_per_sweep):
        print(f"{i + 1:>5} {s:8.2f} {res.energy_per_sweep[i + 1]:14.2f} "
              f"{res.changed_per_sweep[i]:>10} {res.moves_per_sweep[i]:>5} "
              f"{res.skipped_per_sweep[i]:>7}")
    print(f"final: data {res.data_energy:.2f} + smoothness {res.smooth_energy:.2f}; "
          f"{np.unique(res.labels[res.labels >= 0]).size} photos used; "
          f"{res.truncated_terms} pair terms truncated")
    out = {
        "benchmark": "labeling", "version": BENCH_VERSION,
        "machine": {"node": platform.node(), "cpus": os.cpu_count(),
                    "python": platform.python_version(), "numpy": np.__version__,
                    "load_average": [load0, load1]},
        "points": a.points, "photos": a.photos, "seed": a.seed, "candidates": int(cands.nnz),
        "config": asdict(cfg), "seconds_generate": t_gen, "seconds_total": res.seconds_total,
        "cpu_seconds": cpu,
        "seconds_setup": res.seconds_setup, "seconds_per_sweep": res.seconds_per_sweep,
        "energy_per_sweep": res.energy_per_sweep, "changed_per_sweep": res.changed_per_sweep,
        "moves_per_sweep": res.moves_per_sweep, "skipped_per_sweep": res.skipped_per_sweep,
        "data_energy": res.data_energy, "smooth_energy": res.smooth_energy, "edges": res.n_edges,
        "truncated_terms": res.truncated_terms, "peak_rss_mb": rss1,
    }
    if a.check:
        C = np.array([c.center for c in cams])
        f = np.array([np.sqrt(c.fx * c.fy) for c in cams])
        cands.costs = candidate_data_costs(pos, nrm, C, f, cands, cfg)
        e = energy(res.labels, None, knn_edges(pos, cfg.k_neighbors), cands, cfg)
        print(f"check: energy recomputed independently {e[0]:.2f}")
        out["energy_check"] = e[0]
    if a.out:
        with open(a.out, "w") as fh:
            json.dump(out, fh, indent=1)
        print(f"wrote {a.out}")
    return out


if __name__ == "__main__":
    main()
