"""Benchmark of the out-of-core level-of-detail build (dmrt.preprocess.octree; paper Section 4.1/4.2: P_HD in an
out-of-core octree, the proxies P_LD = its k coarsest levels, sub-sampled 87x to 2075x).

    python -m bench.bench_octree --points 20000000 --memory-limit-mb 256 --out-dir /tmp/oct [--json FILE]

The cloud is generated block by block from ``--seed`` (block ``i`` of 131072 points from
``default_rng([seed, i])``; a chunk is a run of whole blocks), never whole in RAM, and regenerated
identically on each of the build's passes; the cloud does not depend on the chunk size, so runs with
different memory limits build the same octree. It is shaped like a
terrestrial scan of a site: a 120 x 80 m ground, a 40 x 25 x 15 m building (four walls and a flat
roof), a 12 m dome and 24 columns, sampled in proportion to area with 3 mm noise, plus per-point
analytic normals (float32) and colours (uint8): 39 bytes a point, 780 MB for 20M points.

Peak memory: the script prints its own peak resident set size (``getrusage``), but the reference
measurement is the kernel's, taken from outside the process::

    /usr/bin/time -v python -m bench.bench_octree --points 20000000 --memory-limit-mb 256 --out-dir /tmp/oct

and reading "Maximum resident set size (kbytes)" (install with ``apt-get install -y time`` when
/usr/bin/time is missing). ``--memory-limit-mb`` bounds the point data and work arrays of the build;
the interpreter with numpy/scipy (~60 MB resident before any point is read, printed as
``baseline_rss_mb``) and the generator's chunk come on top of it.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import time

import numpy as np

from dmrt.preprocess.octree import Octree, OctreeConfig

BENCH_VERSION = 1
RECORD_BYTES = 24 + 12 + 3
BLOCK = 1 << 17  # points per generated block

# surfaces: (kind, parameters); areas decide how many points each gets
GROUND = (120.0, 80.0)
BUILDING = ((30.0, 20.0), (70.0, 45.0), 15.0)  # plan min, plan max, height
DOME = ((95.0, 20.0, 0.0), 12.0)  # centre, radius (upper hemisphere)
COLUMNS = [((10.0 + 4.0 * i, 65.0 + 6.0 * j), 0.4, 8.0) for i in range(12) for j in range(2)]


def _surfaces():
    (x0, y0), (x1, y1), h = BUILDING
    s = [("rect", (0, 0, 0), (GROUND[0], 0, 0), (0, GROUND[1], 0), (0, 0, 1)),
         ("rect", (x0, y0, 0), (x1 - x0, 0, 0), (0, 0, h), (0, -1, 0)),
         ("rect", (x0, y1, 0), (x1 - x0, 0, 0), (0, 0, h), (0, 1, 0)),
         ("rect", (x0, y0, 0), (0, y1 - y0, 0), (0, 0, h), (-1, 0, 0)),
         ("rect", (x1, y0, 0), (0, y1 - y0, 0), (0, 0, h), (1, 0, 0)),
         ("rect", (x0, y0, h), (x1 - x0, 0, 0), (0, y1 - y0, 0), (0, 0, 1)),
         ("dome", DOME[0], DOME[1])]
    s += [("column", c, r, hh) for c, r, hh in COLUMNS]
    return s


def _area(s):
    if s[0] == "rect":
        return float(np.linalg.norm(np.cross(s[2], s[3])))
    if s[0] == "dome":
        return 2 * np.pi * s[2] ** 2
    return 2 * np.pi * s[2] * s[3]


def _sample(s, u, rng):
    """Points and normals on surface ``s`` from uniforms ``u`` (n, 2)."""
    if s[0] == "rect":
        o, a, b, nrm = (np.asarray(x, np.float64) for x in s[1:])
        return o + u[:, :1] * a + u[:, 1:] * b, np.broadcast_to(nrm, (len(u), 3))
    if s[0] == "dome":
        c, r = np.asarray(s[1]), s[2]
        phi, z = 2 * np.pi * u[:, 0], u[:, 1]  # uniform on the hemisphere: z uniform in [0, 1]
        rho = np.sqrt(1 - z * z)
        nrm = np.c_[rho * np.cos(phi), rho * np.sin(phi), z]
        return c + r * nrm, nrm
    (cx, cy), r, h = s[1], s[2], s[3]
    phi = 2 * np.pi * u[:, 0]
    nrm = np.c_[np.cos(phi), np.sin(phi), np.zeros(len(u))]
    return np.c_[cx + r * nrm[:, 0], cy + r * nrm[:, 1], h * u[:, 1]], nrm


def make_chunk(i: int, n: int, seed: int):
    """Block ``i`` (``n`` points): ``(positions (n, 3) float64, {'normals', 'colors'})``."""
    rng = np.random.default_rng([seed, i])
    surf = _surfaces()
    w = np.array([_area(s) for s in surf])
    which = rng.choice(len(surf), size=n, p=w / w.sum())
    pos = np.empty((n, 3))
    nrm = np.empty((n, 3), np.float32)
    for j in np.flatnonzero(np.bincount(which, minlength=len(surf))):
        m = which == j
        p, q = _sample(surf[j], rng.random((int(m.sum()), 2)), rng)
        pos[m] = p + rng.normal(0, 0.003, p.shape)
        nrm[m] = q
    col = (np.abs(np.sin(pos * [0.7, 1.1, 1.9])) * 255).astype(np.uint8)
    return pos, {"normals": nrm, "colors": col}


def bbox_of_scene():
    """Analytic bounding box (noise included): no extra pass over the data needed."""
    lo = np.array([0.0, 0.0, 0.0]) - 0.05
    hi = np.array([GROUND[0], GROUND[1], max(BUILDING[2], DOME[1], 8.0)]) + 0.05
    return lo, hi


def _rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0  # Linux: kB


def _current_rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=20_000_000)
    ap.add_argument("--memory-limit-mb", type=float, default=256)
    ap.add_argument("--out-dir", default="/tmp/oct")
    ap.add_argument("--levels", type=int, default=8)
    ap.add_argument("--root-cell", type=float, default=None, help="metres; default bbox diagonal / 64")
    ap.add_argument("--chunk-size", type=int, default=None,
                    help="points per chunk, rounded down to whole blocks of 131072; default "
                         "limit / 16 bytes worth of points (at most 1M)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--delete", action="store_true", help="remove the octree afterwards")
    args = ap.parse_args(argv)

    baseline = _current_rss_mb()
    limit_b = args.memory_limit_mb * 2 ** 20
    chunk = args.chunk_size or int(min(1_000_000, max(BLOCK, limit_b / 16 / RECORD_BYTES)))
    per_chunk = max(1, chunk // BLOCK)
    chunk = per_chunk * BLOCK
    n_blocks = -(-args.points // BLOCK)
    sizes = [min(BLOCK, args.points - i * BLOCK) for i in range(n_blocks)]
    gen_s = [0.0]  # time spent generating the input, excluded from the build's own rate

    def chunks_fn():
        for c0 in range(0, n_blocks, per_chunk):
            t = time.perf_counter()
            parts = [make_chunk(i, sizes[i], args.seed) for i in range(c0, min(n_blocks, c0 + per_chunk))]
            pos = np.concatenate([p for p, _ in parts])
            attrs = {k: np.concatenate([a[k] for _, a in parts]) for k in parts[0][1]}
            del parts
            gen_s[0] += time.perf_counter() - t
            yield pos, attrs

    cfg = OctreeConfig(levels=args.levels, root_cell=args.root_cell, memory_limit_mb=args.memory_limit_mb)

    t0 = time.perf_counter()
    tree = Octree.build(chunks_fn, args.out_dir, cfg, bbox=bbox_of_scene(), progress=not args.no_progress)
    wall = time.perf_counter() - t0
    peak = _rss_mb()

    f = tree.subsampling_factors()
    res = {
        "bench": "octree", "bench_version": BENCH_VERSION,
        "machine": platform.node(), "python": platform.python_version(), "numpy": np.__version__,
        "cpu_count": os.cpu_count(),
        "points": args.points, "record_bytes": RECORD_BYTES, "data_mb": args.points * RECORD_BYTES / 2 ** 20,
        "memory_limit_mb": args.memory_limit_mb, "chunk_size": chunk, "levels": args.levels,
        "root_cell_m": tree.meta["root_cell"], "level_counts": tree.level_counts,
        "lod_counts": tree.lod_counts(), "subsampling_factors": f,
        "bucket_level": tree.meta["bucket_level"], "n_buckets": tree.meta["n_buckets"],
        "max_bucket_points": tree.meta["max_bucket_points"], "bucket_capacity": tree.meta["bucket_capacity"],
        "wall_s": wall, "generator_s": gen_s[0], "build_s": wall - gen_s[0],
        "points_per_s": args.points / (wall - gen_s[0]), "phases_s": tree.meta["timings"],
        "baseline_rss_mb": baseline, "peak_rss_mb": peak,
    }
    print(f"points {args.points:,} ({res['data_mb']:.0f} MB of records), limit {args.memory_limit_mb:g} MB, "
          f"chunks of {chunk:,}")
    print(f"levels  {tree.level_counts}")
    print(f"LOD k   {res['lod_counts']}")
    print("factors " + ", ".join(f"{x:.1f}" for x in f))
    print(f"buckets {res['n_buckets']} at level {res['bucket_level']} (largest {res['max_bucket_points']:,}, "
          f"capacity {res['bucket_capacity']:,})")
    print(f"wall    {wall:.1f} s, of which generating the input {gen_s[0]:.1f} s; build alone "
          f"{wall - gen_s[0]:.1f} s ({res['points_per_s'] / 1e6:.2f} M points/s)")
    print("phases  " + ", ".join(f"{k} {v:.1f}" for k, v in tree.meta["timings"].items())
          + " (generator time included)")
    print(f"rss     baseline {baseline:.0f} MB, peak {peak:.0f} MB (getrusage) vs limit {args.memory_limit_mb:g} MB")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=1)
    if args.delete:
        shutil.rmtree(args.out_dir, ignore_errors=True)
    return res


if __name__ == "__main__":
    main()
