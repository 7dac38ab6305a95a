"""Benchmark of the out-of-core normals and splat radii (dmrt.preprocess.normals.process_chunked)
over an octree's points, as the pipeline runs it, serial and with worker processes.

    python -m bench.bench_normals --points 4000000 --memory-limit-mb 128 --workers 1,2 [--json FILE]

The cloud is bench_octree's generated site (block ``i`` from ``default_rng([seed, i])``), built once
into an octree in ``--out-dir`` (reused when it holds ``--points`` points; its build is not timed).
Each ``--workers`` count then runs ``process_chunked(octree.point_range(...), executor=...)``
(the bucketed path: pick ``--memory-limit-mb`` so that the cloud does not fit in it) and prints
the wall time of each pass: bbox, count and distribute read the input (as tasks over the
octree's point ranges when workers > 1), buckets is the kNN work (tasks per bucket). Worker
processes are spawned (and import the module) before the clock starts, as the pipeline's pool is
after the octree build. CPU seconds are this process's and the workers' together (the workers'
count once they are joined, at the pool's close). The results of every worker count are checked
equal to the first's, bit for bit.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import resource
import shutil
import time
from pathlib import Path


from bench.bench_octree import BLOCK, bbox_of_scene, make_chunk
from dmrt.errors import InputError
from dmrt.preprocess.normals import process_chunked
from dmrt.preprocess.octree import Octree, OctreeConfig
from dmrt.preprocess.parallel import open_executor


def _warm(seconds: float) -> float:
    """In a worker: import the module the tasks run (so the clock does not count it), wait (so that
    each worker takes one of these), and return the worker's CPU seconds so far."""
    import dmrt.preprocess.normals  # noqa: F401

    time.sleep(seconds)
    r = resource.getrusage(resource.RUSAGE_SELF)
    return r.ru_utime + r.ru_stime


def _cpu_s() -> float:
    return sum(r.ru_utime + r.ru_stime for r in map(resource.getrusage, (resource.RUSAGE_SELF,
                                                                         resource.RUSAGE_CHILDREN)))


def build_octree(out: Path, points: int, seed: int, levels: int) -> Octree:
    """bench_octree's cloud of ``points`` points as an octree at ``out`` (reused if it matches)."""
    if (out / "octree.json").exists():
        try:
            tree = Octree.open(out)
            if tree.n_points == points and tree.levels == levels:
                return tree
        except InputError:  # written by another version: rebuilt
            pass
    sizes = [min(BLOCK, points - i * BLOCK) for i in range(-(-points // BLOCK))]

    def chunks_fn():
        for i, n in enumerate(sizes):
            pos, attrs = make_chunk(i, n, seed)
            yield pos, {"colors": attrs["colors"]}  # normals are left for process_chunked

    return Octree.build(chunks_fn, out, OctreeConfig(levels=levels, memory_limit_mb=512), bbox=bbox_of_scene(),
                        progress=False)


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=4_000_000)
    ap.add_argument("--memory-limit-mb", type=float, default=128)
    ap.add_argument("--workers", default="1,2", help="comma-separated worker counts (1: serial)")
    ap.add_argument("--chunk-size", type=int, default=1_000_000, help="points per chunk of the octree's range")
    ap.add_argument("--radii-only", action="store_true", help="no normals (as for a cloud that has them)")
    ap.add_argument("--out-dir", default="/tmp/bench_normals")
    ap.add_argument("--levels", type=int, default=6)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", default=None, help="write the results here")
    args = ap.parse_args(argv)

    out = Path(args.out_dir)
    t = time.perf_counter()
    tree = build_octree(out / "octree", args.points, args.seed, args.levels)
    build_s = time.perf_counter() - t
    src = tree.point_range(chunk_size=args.chunk_size)
    runs, first = [], None
    for workers in (int(w) for w in args.workers.split(",")):
        work = out / f"attrs-{workers}"
        shutil.rmtree(work, ignore_errors=True)
        with open_executor(None, workers=workers) as executor:
            # spawn the workers before the clock starts; their CPU seconds until then are not counted
            warm_cpu = sum(executor.map(_warm, [0.5] * workers)) if workers > 1 else 0.0
            cpu0 = _cpu_s() + warm_cpu
            res = process_chunked(src, work, normals=not args.radii_only, radii=True, viewpoints=[[60, 40, 30]],
                                  memory_limit_mb=args.memory_limit_mb, progress=False, executor=executor)
        cpu = _cpu_s() - cpu0
        arrays = [a for a in (res.normals, res.radii) if a is not None]
        if first is None:
            first = arrays
        equal = all(a.tobytes() == b.tobytes() for a, b in zip(arrays, first))
        run = {"workers": workers, "seconds": round(res.seconds, 3), **res.timings, "cpu_s": round(cpu, 2),
               "n_buckets": res.n_buckets,
               "max_bucket_points": res.max_bucket_points, "n_unverified": res.n_unverified,
               "equal_to_first": equal}
        runs.append(run)
        input_s = sum(res.timings.get(k, 0.0) for k in ("bbox_s", "count_s", "distribute_s"))
        print(f"workers {workers}: {res.seconds:.2f} s, {cpu:.1f} CPU s (input passes {input_s:.2f} s = "
              f"{input_s / res.n_points * 1e6:.2f} us/point; {res.timings}), {res.n_buckets} buckets, "
              f"equal to the first run: {equal}")
        del res, arrays
        shutil.rmtree(work, ignore_errors=True)
    result = {"bench": "normals", "points": tree.n_points, "memory_limit_mb": args.memory_limit_mb,
              "radii_only": args.radii_only, "octree_build_s": round(build_s, 3), "cpus": os.cpu_count(),
              "machine": platform.node(), "runs": runs}
    if args.json:
        Path(args.json).write_text(json.dumps(result, indent=1))
    return result


if __name__ == "__main__":
    main()
