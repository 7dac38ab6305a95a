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

    OMP_NUM_THREADS=1 taskset -c 0 python -m bench.bench_normals --kernels --points 1000000 [--repeat 3]

``--kernels`` times the per-bucket kernel alone instead, on one bucket of all the octree's points
(float64, in octree order, as a bucket reads them), stage by stage in CPU microseconds per point
(this process's CPU seconds: steadier than wall time on a shared machine; run it on one core as
above, the kNN threads being OpenMP's): kd-tree build, one query of 16 neighbours, the PCA normals,
their orientation toward a viewpoint and the radii from the 9th column, in runs of 65,536 rows as
``process_chunked`` queries them. ``before`` is the kernel up to 1c2fa76 (scipy's cKDTree, batched
``np.linalg.eigh``), ``after`` the one in :mod:`dmrt.preprocess.knn` as ``normals._kdtree`` /
``normals._pca_normals`` give it to the buckets. Each is run ``--repeat`` times (the minimum
counts), and the two results are compared: the largest angle between the normals and the largest
relative difference of the radii.

    OMP_NUM_THREADS=1 taskset -c 0 python -m bench.bench_normals --kernels --gpu --points 1000000

``--gpu`` adds ``gpu``: the same bucket's kernel with the kNN on the GPU (:mod:`dmrt.preprocess.gpu_knn`,
a grid sorted on the CPU, then one 16-NN query of every point), in wall microseconds per point (the
GPU's time is no CPU time of this process): ``build`` sorts the points by cell and uploads them,
``query`` runs the dispatches, waits for them (``ctx.finish()``) and reads the neighbours back; the
normals, orientation and radii as ``after``'s. Its results are compared with ``after``'s as above
(on Mesa llvmpipe it runs, but its timings are no GPU's).

    OMP_NUM_THREADS=1 taskset -c 0 python -m bench.bench_normals --query-variants --points 1000000

``--query-variants`` times the kd-tree query alone (16 neighbours of every point of the same bucket,
in runs of 65,536 rows, CPU microseconds per point, best of ``--repeat``, interleaved) under the
variants that could make it cheaper: queries and/or tree points in Morton order (results mapped back
to the caller's order and checked equal to the plain query's), float32 tree and queries,
leafsizes 8 to 32, and a ``distance_upper_bound`` at the largest 16th-neighbour distance (exact).
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


import numpy as np
from scipy.spatial import cKDTree

from bench.bench_octree import BLOCK, bbox_of_scene, make_chunk
from dmrt.errors import InputError
from dmrt.morton import morton_order
from dmrt.preprocess import normals as nrm
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


def _eigh_normals(c, idx):
    """The PCA normals before dmrt.preprocess.knn: the covariances' smallest eigenvectors by LAPACK."""
    nb = c[idx]
    nb -= nb.mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("bki,bkj->bij", nb, nb))[1][:, :, 0]


KERNELS = {
    "before": (lambda c: cKDTree(c, balanced_tree=False, compact_nodes=False), _eigh_normals),
    "after": (nrm._kdtree, nrm._pca_normals),
}


def time_kernel(name: str, pos: np.ndarray, viewpoint, rows: int = 65536) -> tuple[dict, np.ndarray, np.ndarray]:
    """One bucket's normals (k = 16) and radii (k = 8) by kernel ``name``: CPU seconds per stage,
    the normals (n, 3) float32 and the radii (n,) float32."""
    build, pca = KERNELS[name]
    t = {k: 0.0 for k in ("build", "query", "normals", "orient", "radii")}
    n = len(pos)
    normals, radii = np.empty((n, 3), np.float32), np.empty(n, np.float32)
    c0 = time.process_time()
    c = pos - pos.mean(axis=0)
    tree = build(c)
    t["build"] = time.process_time() - c0
    for s in range(0, n, rows):
        c0 = time.process_time()
        d, idx = tree.query(c[s:s + rows], k=16, workers=1)
        c1 = time.process_time()
        v = pca(c, idx)
        c2 = time.process_time()
        normals[s:s + rows] = nrm.orient_normals(v, pos[s:s + rows], viewpoint, per_point=False)
        c3 = time.process_time()
        radii[s:s + rows] = d[:, 8] * nrm.radius_factor(8)
        c4 = time.process_time()
        for k, a, b in (("query", c0, c1), ("normals", c1, c2), ("orient", c2, c3), ("radii", c3, c4)):
            t[k] += b - a
    return t, normals, radii


def time_gpu_kernel(pos: np.ndarray, viewpoint) -> tuple[dict, np.ndarray, np.ndarray]:
    """``time_kernel`` with the kNN on the GPU: wall seconds per stage (``--gpu``)."""
    from dmrt.preprocess.gpu_knn import GridKnn

    t = {}
    w0 = time.perf_counter()
    c = pos - pos.mean(axis=0)
    grid = GridKnn(c)
    w1 = time.perf_counter()
    d, idx = grid.query(16)
    grid.ctx.finish()
    w2 = time.perf_counter()
    grid.release()
    v = nrm._pca_normals(c, idx)
    w3 = time.perf_counter()
    normals = nrm.orient_normals(v, pos, viewpoint, per_point=False).astype(np.float32)
    w4 = time.perf_counter()
    radii = (d[:, 8] * nrm.radius_factor(8)).astype(np.float32)
    w5 = time.perf_counter()
    for k, a, b in (("build", w0, w1), ("query", w1, w2), ("normals", w2, w3), ("orient", w3, w4),
                    ("radii", w4, w5)):
        t[k] = b - a
    return t, normals, radii


def kernels(tree: Octree, repeat: int, gpu: bool = False) -> dict:
    """``--kernels``: before / after (and ``gpu``), stage by stage, in microseconds per point (best
    of ``repeat``)."""
    pos = tree.read_lod(tree.levels)["positions"].astype(np.float64)
    n, viewpoint = len(pos), [[60.0, 40.0, 30.0]]
    timed = {name: (lambda p, v, name=name: time_kernel(name, p, v)) for name in KERNELS}
    if gpu:
        time_gpu_kernel(pos[:1000], viewpoint)  # the program's compilation is not timed
        timed["gpu"] = time_gpu_kernel
    runs = {name: [] for name in timed}
    for _ in range(repeat):  # interleaved: a neighbour's load on a shared machine hits both alike
        for name, fn in timed.items():
            t, normals, radii = fn(pos, viewpoint)
            runs[name].append(({k: round(v / n * 1e6, 3) for k, v in t.items()}, normals, radii))
    out = {}
    for name, rs in runs.items():
        total = [sum(r[0].values()) for r in rs]
        best = rs[int(np.argmin(total))]
        out[name] = {"us_per_point": best[0], "total_us_per_point": round(min(total), 3),
                     "totals": [round(x, 3) for x in total], "normals": best[1], "radii": best[2]}
        print(f"{name:6s}: {min(total):.3f} us/point (runs {', '.join(f'{x:.3f}' for x in total)}): {best[0]}")
    b, a = out["before"], out["after"]
    speedup, angle, opposite, rel = _compare(b, a)
    print(f"speed-up {speedup:.2f}x; normals: largest angle {angle:.2e} degrees, {opposite} opposite; "
          f"radii: largest relative difference {rel:.1e}")
    result = {"points": n, "omp_num_threads": os.environ.get("OMP_NUM_THREADS"),
              "cores": len(os.sched_getaffinity(0)), "speedup": round(speedup, 2), "max_angle_deg": angle,
              "opposite_normals": opposite, "max_radius_rel_diff": rel}
    if gpu:
        from dmrt.gl import get_context, renderer_info

        g = out["gpu"]
        g["renderer"] = renderer_info(get_context())["renderer"]
        g_speedup, g_angle, _, g_rel = _compare(a, g)
        # normals of a neighbourhood that differs by a tie at the 16th neighbour may tilt
        tilted = int(np.count_nonzero(_angles(a["normals"], g["normals"]) > 1e-3))
        print(f"gpu vs after: {g_speedup:.2f}x ({g['renderer']}); normals: largest angle {g_angle:.2e} degrees, "
              f"{tilted} above 1e-3; radii: largest relative difference {g_rel:.1e}")
        result["gpu_vs_after"] = {"speedup": round(g_speedup, 2), "max_angle_deg": g_angle,
                                  "normals_above_1e-3_deg": tilted, "max_radius_rel_diff": g_rel}
    for r in out.values():
        del r["normals"], r["radii"]
    return {**result, **out}


def _angles(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(n,) unoriented angles between the rows of ``u`` and ``v`` (n, 3), degrees."""
    cross = np.linalg.norm(np.cross(u.astype(np.float64), v), axis=1)
    return np.degrees(np.arcsin(np.clip(cross, 0, 1)))


def _compare(b: dict, a: dict) -> tuple[float, float, int, float]:
    """Kernel ``a`` against ``b``: speed-up, largest angle between normals (degrees), opposite
    normals, largest relative difference of the radii."""
    angle = float(_angles(a["normals"], b["normals"]).max())
    opposite = int(np.count_nonzero(np.einsum("ij,ij->i", a["normals"], b["normals"]) < 0))
    rel = float(np.max(np.abs(a["radii"] / b["radii"] - 1)))
    return b["total_us_per_point"] / a["total_us_per_point"], angle, opposite, rel


def ordered_query(data: np.ndarray, x: np.ndarray, k: int = 16, perm=None, rows_of=None, leafsize: int = 16,
                  rows: int = 65536, **kw) -> tuple[float, np.ndarray, np.ndarray]:
    """pykdtree's ``k`` nearest of the rows of ``x`` among ``data`` (both (n, 3), perhaps reordered),
    queried in runs of ``rows``, the results put back in the caller's order.

    ``perm[i]`` is the caller's index of ``data[i]``, ``rows_of[r]`` the caller's row of ``x[r]``
    (None: the caller's order). Returns the query's CPU seconds, distances (b, k) float64 and
    indices (b, k) int64.
    """
    from pykdtree.kdtree import KDTree

    t = KDTree(data, leafsize=leafsize)
    d, idx = np.empty((len(x), k), np.float64), np.empty((len(x), k), np.int64)
    c0 = time.process_time()
    for s in range(0, len(x), rows):
        d[s:s + rows], idx[s:s + rows] = t.query(x[s:s + rows], k=k, **kw)
    seconds = time.process_time() - c0
    if perm is not None:
        idx = perm[idx]
    if rows_of is not None:
        d[rows_of], idx[rows_of] = d.copy(), idx.copy()
    return seconds, d, idx


def query_variants(tree: Octree, repeat: int) -> dict:
    """``--query-variants``: CPU microseconds per point of the 16-neighbour query, per variant."""
    c = tree.read_lod(tree.levels)["positions"].astype(np.float64)
    c -= c.mean(axis=0)
    n, order = len(c), morton_order(c)
    c_sorted = np.ascontiguousarray(c[order])
    d16 = ordered_query(c, c)[1][:, -1]
    c32 = c.astype(np.float32)
    variants = {  # name: (tree points, queries, their caller indices (perm, rows_of), options)
        "plain": (c, c, {}),
        "morton queries": (c, c_sorted, {"rows_of": order}),
        "morton tree": (c_sorted, c, {"perm": order}),
        "morton tree and queries": (c_sorted, c_sorted, {"perm": order, "rows_of": order}),
        "float32": (c32, c32, {}),
        **{f"leafsize {ls}": (c, c, {"leafsize": ls}) for ls in (8, 12, 24, 32)},
        "distance_upper_bound": (c, c, {"distance_upper_bound": float(d16.max()) * (1 + 1e-9)}),
    }
    times = {name: [] for name in variants}
    ref = None
    for _ in range(repeat):  # interleaved: a neighbour's load on a shared machine hits all alike
        for name, (data, x, kw) in variants.items():
            s, d, idx = ordered_query(data, x, **kw)
            ref = (d, idx) if ref is None else ref
            if name.startswith("morton") or name == "distance_upper_bound":  # exact: the same results
                assert np.array_equal(d, ref[0]) and np.array_equal(idx, ref[1]), name
            times[name].append(round(s / n * 1e6, 3))
    out = {name: {"us_per_point": min(t), "runs": t} for name, t in times.items()}
    for name, r in out.items():
        print(f"{name:24s}: {r['us_per_point']:.3f} us/point (runs {', '.join(map(str, r['runs']))})")
    return {"points": n, "omp_num_threads": os.environ.get("OMP_NUM_THREADS"), "variants": out}


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
    ap.add_argument("--kernels", action="store_true", help="time the per-bucket kernel, before / after knn.py")
    ap.add_argument("--gpu", action="store_true", help="--kernels: also the kernel with the kNN on the GPU")
    ap.add_argument("--query-variants", action="store_true",
                    help="time the kd-tree query's variants (order, dtype, leafsize)")
    ap.add_argument("--repeat", type=int, default=3, help="--kernels, --query-variants: runs of each")
    args = ap.parse_args(argv)

    out = Path(args.out_dir)
    t = time.perf_counter()
    tree = build_octree(out / "octree", args.points, args.seed, args.levels)
    build_s = time.perf_counter() - t
    if args.kernels or args.query_variants:
        if args.kernels:
            name, res = "normals-kernels", kernels(tree, args.repeat, gpu=args.gpu)
        else:
            name, res = "knn-query-variants", query_variants(tree, args.repeat)
        result = {"bench": name, "machine": platform.node(), **res}
        if args.json:
            Path(args.json).write_text(json.dumps(result, indent=1))
        return result
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
