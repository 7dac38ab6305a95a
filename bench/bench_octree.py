"""Benchmark of the out-of-core level-of-detail build (dmrt.preprocess.octree; paper Section 4.1/4.2: P_HD in an
out-of-core octree, the proxies P_LD = its k coarsest levels, sub-sampled 87x to 2075x).

    python -m bench.bench_octree --points 20000000 --memory-limit-mb 256 --out-dir /tmp/oct [--workers N] [--json FILE]
                                 [--ply FILE]

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

``--workers N`` (N > 1) runs the bucket passes (candidates, select) in a
:class:`~dmrt.preprocess.parallel.ProcessPool` of N processes, each within ``limit / N``; they are
spawned before the clock starts (as the pipeline's pool is), and the largest one's peak RSS is
printed as ``worker_peak_rss_mb``. The generated input is generated and read in this process, so
the passes that read it (count, distribute) are printed with and without the generator's time.

``--profile N`` profiles the build (cProfile, in this process: with ``--workers 1``) and prints its N
costliest functions in microseconds a point; e.g. the select of a bucket as dense per cell as the
683M-point scan's (levels of about the same sizes, scaled: a root cell of 20 m, 9x the default)::

    OMP_NUM_THREADS=1 taskset -c 0 python -m bench.bench_octree --points 3000000 --memory-limit-mb 2048 \
        --root-cell 20 --ply /tmp/cloud.ply --out-dir /tmp/oct --profile 30 --no-progress

``--ply FILE`` writes the generated cloud to a binary PLY once (unless FILE already holds
``--points`` points; not timed) and builds from it through
:func:`~dmrt.io.pointcloud.point_range`, as the preprocessing pipeline reads a scene: that source
splits into record ranges, so with ``--workers N`` the passes that read the input (count,
distribute) run in the N processes too, one range each.
"""

from __future__ import annotations

import argparse
import cProfile
import json
import os
import platform
import pstats
import resource
import shutil
import time

import numpy as np

from dmrt.io.pointcloud import PointCloud, PointWriter, count_points, point_range
from dmrt.preprocess.octree import Octree, OctreeConfig
from dmrt.preprocess.parallel import open_executor

BENCH_VERSION = 3
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


def _rss_mb(who=resource.RUSAGE_SELF) -> float:
    return resource.getrusage(who).ru_maxrss / 1024.0  # Linux: kB


def _cpu_s(who=resource.RUSAGE_SELF) -> float:
    r = resource.getrusage(who)
    return r.ru_utime + r.ru_stime


def _current_rss_mb() -> float:
    with open("/proc/self/status") as f:
        for line in f:
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024.0
    return float("nan")


def _print_profile(profiler, points: int, top: int):
    """The ``top`` functions of the profile by cumulative time, in microseconds a point."""
    rows = sorted(pstats.Stats(profiler).stats.items(), key=lambda kv: -kv[1][3])[:top]
    print("profile (us/pt cumulative, own; calls; function):")
    for (path, line, name), (_, calls, own, cum, _) in rows:
        print(f"  {cum * 1e6 / max(1, points):7.3f} {own * 1e6 / max(1, points):7.3f} {calls:7d}  "
              f"{name} ({os.path.basename(path)}:{line})")


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
    ap.add_argument("--workers", type=int, default=1,
                    help="processes for the bucket passes (1: all in this process, the serial build)")
    ap.add_argument("--ply", default=None,
                    help="build from this binary PLY (written from the generated cloud first unless it "
                         "holds --points points): a source that splits for the workers")
    ap.add_argument("--json", default=None, help="write the results here")
    ap.add_argument("--no-progress", action="store_true")
    ap.add_argument("--delete", action="store_true", help="remove the octree afterwards")
    ap.add_argument("--profile", type=int, default=0, metavar="N",
                    help="profile the build in this process (cProfile; use with --workers 1) and print its N "
                         "costliest functions in microseconds a point, cumulative and own")
    args = ap.parse_args(argv)

    baseline = _current_rss_mb()
    limit_b = args.memory_limit_mb * 2 ** 20
    chunk = args.chunk_size or int(min(1_000_000, max(BLOCK, limit_b / 16 / RECORD_BYTES)))
    per_chunk = max(1, chunk // BLOCK)
    chunk = per_chunk * BLOCK
    n_blocks = -(-args.points // BLOCK)
    sizes = [min(BLOCK, args.points - i * BLOCK) for i in range(n_blocks)]
    gen_calls = []  # seconds spent generating the input, per call of chunks_fn (one per pass reading it)

    def chunks_fn():
        gen_calls.append(0.0)
        for c0 in range(0, n_blocks, per_chunk):
            t = time.perf_counter()
            parts = [make_chunk(i, sizes[i], args.seed) for i in range(c0, min(n_blocks, c0 + per_chunk))]
            pos = np.concatenate([p for p, _ in parts])
            attrs = {k: np.concatenate([a[k] for _, a in parts]) for k in parts[0][1]}
            del parts
            gen_calls[-1] += time.perf_counter() - t
            yield pos, attrs

    source = chunks_fn
    if args.ply:
        if not os.path.exists(args.ply) or count_points(args.ply) != args.points:
            with PointWriter(args.ply, normals=True, colors=True) as w:
                for pos, attrs in chunks_fn():
                    w.write(PointCloud(pos, attrs["normals"], attrs["colors"]))
        gen_calls.clear()  # writing the file is not part of the build
        source = point_range(args.ply, chunk)

    cfg = OctreeConfig(levels=args.levels, root_cell=args.root_cell, memory_limit_mb=args.memory_limit_mb)

    with open_executor(None, workers=args.workers) as executor:
        t = time.perf_counter()
        executor.map(time.sleep, [0.2] * args.workers)  # spawn the workers before the clock starts
        spawn_s = time.perf_counter() - t
        t0, cpu0, workers_cpu0 = time.perf_counter(), _cpu_s(), _cpu_s(resource.RUSAGE_CHILDREN)
        profiler = cProfile.Profile() if args.profile else None
        if profiler:
            profiler.enable()
        tree = Octree.build(source, args.out_dir, cfg, bbox=bbox_of_scene(), progress=not args.no_progress,
                            executor=executor)
        if profiler:
            profiler.disable()
        wall, cpu = time.perf_counter() - t0, _cpu_s() - cpu0
    # the workers' CPU time counts once they are joined (at the executor's close), spawning included
    workers_cpu = _cpu_s(resource.RUSAGE_CHILDREN) - workers_cpu0
    peak = _rss_mb()
    worker_peak = _rss_mb(resource.RUSAGE_CHILDREN) if args.workers > 1 else None
    gen_s = sum(gen_calls)
    # the passes that read the input: the first call(s) (schema, bbox) count in bbox_s, then count, distribute
    phases = dict(tree.meta["timings"])
    own = dict(phases)
    reading = [k for k in ("count_s", "distribute_s") if k in phases]
    head = gen_calls[:len(gen_calls) - len(reading)]
    own["bbox_s"] = phases["bbox_s"] - sum(head)
    for name, g in zip(reading, gen_calls[len(head):]):
        own[name] = phases[name] - g
    own["total_s"] = phases["total_s"] - gen_s

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
        "wall_s": wall, "generator_s": gen_s, "build_s": wall - gen_s,
        "points_per_s": args.points / (wall - gen_s), "phases_s": phases,
        "phases_without_generator_s": own,
        "phases_us_per_point": {k[:-2]: v * 1e6 / max(1, args.points) for k, v in own.items()}, "generator_per_pass_s": gen_calls,
        "input": args.ply or "generated", "input_parts": tree.meta["input_parts"],
        "workers": args.workers, "worker_spawn_s": spawn_s, "cpu_s": cpu, "workers_cpu_s": workers_cpu,
        "baseline_rss_mb": baseline, "peak_rss_mb": peak, "worker_peak_rss_mb": worker_peak,
    }
    print(f"points {args.points:,} ({res['data_mb']:.0f} MB of records), limit {args.memory_limit_mb:g} MB, "
          f"chunks of {chunk:,}")
    print(f"levels  {tree.level_counts}")
    print(f"LOD k   {res['lod_counts']}")
    print("factors " + ", ".join(f"{x:.1f}" for x in f))
    print(f"buckets {res['n_buckets']} at level {res['bucket_level']} (largest {res['max_bucket_points']:,}, "
          f"capacity {res['bucket_capacity']:,})")
    print(f"wall    {wall:.1f} s, of which generating the input {gen_s:.1f} s; build alone "
          f"{wall - gen_s:.1f} s ({res['points_per_s'] / 1e6:.2f} M points/s)")
    print(f"input   {res['input']} in {res['input_parts']} part(s)")
    print(f"cpu     this process {cpu:.1f} s (generator included)"
          + (f", the {args.workers} workers {workers_cpu:.1f} s (spawned in {spawn_s:.1f} s, before the clock)"
             if args.workers > 1 else ""))
    print("phases  " + ", ".join(f"{k} {v:.2f}" for k, v in phases.items()) + " (generator time included)")
    print("own     " + ", ".join(f"{k} {v:.2f}" for k, v in own.items()) + " (generator time excluded)")
    print("us/pt   " + ", ".join(f"{k[:-2]} {v * 1e6 / max(1, args.points):.3f}" for k, v in own.items())
          + " (microseconds a point, generator time excluded)")
    print(f"rss     baseline {baseline:.0f} MB, peak {peak:.0f} MB (getrusage) vs limit {args.memory_limit_mb:g} MB"
          + (f"; largest worker {worker_peak:.0f} MB" if worker_peak is not None else ""))
    if profiler:
        _print_profile(profiler, args.points, args.profile)
    if args.json:
        with open(args.json, "w") as fh:
            json.dump(res, fh, indent=1)
    if args.delete:
        shutil.rmtree(args.out_dir, ignore_errors=True)
    return res


if __name__ == "__main__":
    main()
