"""Benchmark of depth-map preprocessing (paper Section 4.1): one depth map per photo from one dense
cloud, with :meth:`dmrt.preprocess.depthmaps.DepthMapRenderer.render_many` (the cloud uploaded once).

    python -m bench.bench_depthmaps --points 30000000 --photos 192 --width 1024 \\
        --method compute|raster|both [--resident-mb 4096 1024] [--overlap on|off|both] \\
        [--feed-threads N] [--out FILE.json] [--stages]

The cloud is synthetic but shaped like an indoor scan: points spread uniformly over the floor and
the four walls of a 40 x 30 x 3 m box building, normals facing in, radii equal to the mean point
spacing (about 1-3 px discs seen from 2-10 m at 1024 px), generated chunk by chunk from a seed.
The photos (1024 x 684, 60 degree horizontal field of view) are taken from inside, at eye height,
each looking at a random spot on a wall. Each (method, resident budget) is timed once after a
warm-up, with GL timer queries (upload, splatting, read-back: GPU milliseconds) and the wall clock
(the whole loop over the maps, which the caller receives as numpy arrays). The headline figure is
``splats/s = points x photos / splatting GPU seconds``; ``splats/s (wall)`` divides by the whole
loop's wall time instead (uploads and read-backs included). The first map is checked to be equal,
bit for bit, to :meth:`~dmrt.preprocess.depthmaps.DepthMapRenderer.render` of the same camera.
``--overlap both`` runs each budget twice: with every map kept on the GPU and each batch splatted
into all of them as it is uploaded (mode ``overlapped``), and without (``resident`` where the cloud
fits: uploaded whole, then splatted camera by camera), so that the two shapes of the same splats can
be compared on the GPU.

``--stages`` also times, one by one, the CPU stages around the GPU that the preprocessing runs per
point (packing the chunks into GPU batches with their culling boxes, on one thread; culling each
batch for every photo, on one thread; the whole feed, those two, on ``--feed-threads`` threads; the
copy to the GPU) and per map (writing its EXR), as us/point and ms/map, the best of three.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time

import numpy as np

from dmrt.camera import Camera
from dmrt.io.exr import write_depth_exr
from dmrt.preprocess.depthmaps import DepthMapConfig, DepthMapRenderer, _batches, _Runs, depth_map_size
from dmrt.gl import GpuTimer, get_context, renderer_info

BENCH_VERSION = 1

BOX = np.array([40.0, 30.0, 3.0])  # building interior, metres
CHUNK = 1_000_000  # points generated per chunk
HEIGHT_RATIO = 684 / 1024  # the paper's 3:2 photos at 1024 px


def _faces():
    """Floor and four walls as (origin, edge u, edge v, inward normal)."""
    X, Y, Z = BOX
    f = [((0, 0, 0), (X, 0, 0), (0, Y, 0), (0, 0, 1)),
         ((0, 0, 0), (X, 0, 0), (0, 0, Z), (0, 1, 0)),
         ((0, Y, 0), (X, 0, 0), (0, 0, Z), (0, -1, 0)),
         ((0, 0, 0), (0, Y, 0), (0, 0, Z), (1, 0, 0)),
         ((X, 0, 0), (0, Y, 0), (0, 0, Z), (-1, 0, 0))]
    return [tuple(np.asarray(a, np.float64) for a in x) for x in f]


def make_cloud(n_points: int, seed: int = 0, chunk: int = CHUNK):
    """The synthetic cloud as a list of (positions (m, 3) f4, normals (m, 3) f4, radii (m,) f4)."""
    faces = _faces()
    area = np.array([np.linalg.norm(np.cross(u, v)) for _, u, v, _ in faces])
    spacing = np.sqrt(area.sum() / max(n_points, 1))
    chunks = []
    for k, start in enumerate(range(0, n_points, chunk)):
        m = min(chunk, n_points - start)
        rng = np.random.default_rng([seed, k])
        pos, nrm = [], []
        # points of a chunk come face by face (a scan's points arrive spatially grouped too)
        for (o, u, v, n), c in zip(faces, rng.multinomial(m, area / area.sum())):
            st = rng.random((c, 2), dtype=np.float32)
            pos.append(o.astype(np.float32) + st[:, :1] * u.astype(np.float32) + st[:, 1:] * v.astype(np.float32))
            nrm.append(np.broadcast_to(n.astype(np.float32), (c, 3)))
        radii = spacing * rng.uniform(0.8, 1.2, m).astype(np.float32)
        chunks.append((np.concatenate(pos), np.concatenate(nrm), radii.astype(np.float32)))
    return chunks, float(spacing)


def make_cameras(n_photos: int, width: int, seed: int = 0, fov_x: float = 60.0):
    """Photos from inside the box at eye height, each looking at a random spot on a wall."""
    rng = np.random.default_rng([seed, 1 << 20])
    X, Y, Z = BOX
    height = max(1, round(width * HEIGHT_RATIO))
    cams = []
    for j in range(n_photos):
        eye = rng.uniform([2.0, 2.0, 1.4], [X - 2.0, Y - 2.0, 1.8])
        wall = rng.integers(4)
        t = rng.uniform(0, 1)
        z = rng.uniform(0.3, 2.5)
        target = [(t * X, 0, z), (t * X, Y, z), (0, t * Y, z), (X, t * Y, z)][wall]
        cams.append(Camera.look_at(f"IMG_{j:04d}.jpg", eye, target, width, height, fov_x))
    return cams


def run_one(ctx, method: str, chunks, cameras, width: int, resident_mb: float, check: bool,
            chunk_points: int, overlap: bool = True, feed_threads: int = DepthMapConfig().feed_threads) -> dict:
    """Time one render_many over every camera; returns the measurements."""
    timer = GpuTimer(ctx)
    config = DepthMapConfig(width=width, method=method, chunk_points=chunk_points, overlap=overlap,
                            feed_threads=feed_threads)
    renderer = DepthMapRenderer(ctx, config, timer=timer)
    points = sum(len(c[0]) for c in chunks)
    try:
        # warm-up: the same paths on a small cloud and two cameras (driver state, first dispatches)
        for _ in renderer.render_many(cameras[:2], lambda: iter(chunks[:1]), resident_mb=resident_mb):
            pass
        ctx.finish()
        timer.reset()
        coverage = []
        first = None
        t0 = time.perf_counter()
        for i, depth in renderer.render_many(cameras, lambda: iter(chunks), resident_mb=resident_mb):
            coverage.append(float(np.count_nonzero(depth)) / depth.size)
            if i == 0:
                first = depth
        total_s = time.perf_counter() - t0
        stats = dict(renderer.last_stats)
        gpu = timer.ms
        counts = timer.counts
        equal = None
        if check:  # bit-identical to render() of the same camera
            equal = bool(np.array_equal(first, renderer.render(cameras[0], iter(chunks))))
    finally:
        renderer.release()
    splat_s = gpu.get("depthmap", 0.0) / 1e3
    n = len(cameras)
    return {
        "method": method, "resident_mb": resident_mb, "overlap": overlap, "feed_threads": feed_threads,
        "mode": stats["mode"], "groups": stats["groups"], "splat_wait_s": stats["splat_wait_s"],
        "points": points, "photos": n,
        "upload_gpu_ms": gpu.get("depthmap_upload", 0.0), "upload_wall_s": stats["upload_s"],
        "splat_gpu_ms": gpu.get("depthmap", 0.0), "splat_gpu_ms_per_photo": gpu.get("depthmap", 0.0) / n,
        "readback_gpu_ms": gpu.get("depthmap_readback", 0.0), "readback_wall_s": stats["readback_s"],
        "total_wall_s": total_s, "wall_ms_per_photo": 1e3 * total_s / n,
        # every point for every photo, as before the frustum culling; and what the culling sent
        "splats_per_s": points * n / splat_s if splat_s > 0 else None,
        "splats_sent": stats["splats"], "splats_sent_per_s": stats["splats"] / splat_s if splat_s > 0 else None,
        "splats_per_s_wall": points * n / total_s,
        "timer_sections": counts, "coverage_mean": float(np.mean(coverage)),
        "equal_to_render": equal,
    }


def stage_costs(ctx, chunks, chunk_points: int, cameras, width: int, feed_threads: int, depth: np.ndarray,
                folder) -> dict:
    """Best-of-three wall time of each CPU stage of the depth-map phase around the GPU: ``pack_us``
    (chunks to float32 batches with their culling buckets, one thread, us/point), ``cull_us`` (the
    runs of each batch that each of ``cameras`` splats, one thread, us/point), ``feed_us`` (both,
    as render_many's feed runs them on ``feed_threads`` threads, us/point), ``upload_us`` (the
    batches' copy into GPU buffers, finished, us/point) and ``exr_ms`` (writing ``depth`` as an
    EXR, ms/map)."""
    points = sum(len(c[0]) for c in chunks)
    cull = DepthMapConfig().cull_points
    maps = [c.scaled(*depth_map_size(c, width)) for c in cameras]
    batches = []

    def pack():
        batches[:] = list(_batches(iter(chunks), chunk_points, cull))

    def feed():
        for _ in _batches(iter(chunks), chunk_points, cull, maps, feed_threads):
            pass

    def upload():
        buffers = [ctx.buffer(rows) for rows, _, _ in batches]
        ctx.finish()
        for b in buffers:
            b.release()

    def best(fn):
        times = []
        for _ in range(3):
            t0 = time.perf_counter()
            fn()
            times.append(time.perf_counter() - t0)
        return min(times)

    return {"pack_us": 1e6 * best(pack) / points,
            "cull_us": 1e6 * best(lambda: [_Runs.of(b, len(rows), maps) for rows, b, _ in batches]) / points,
            "feed_us": 1e6 * best(feed) / points, "upload_us": 1e6 * best(upload) / points,
            "exr_ms": 1e3 * best(lambda: write_depth_exr(os.path.join(folder, "stage.exr"), depth))}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--points", type=int, default=30_000_000)
    ap.add_argument("--photos", type=int, default=192)
    ap.add_argument("--width", type=int, default=1024)
    ap.add_argument("--method", choices=["compute", "raster", "both"], default="compute")
    ap.add_argument("--resident-mb", type=float, nargs="+", default=[4096.0],
                    help="GPU budgets to run (a small one forces the grouped mode)")
    ap.add_argument("--chunk-points", type=int, default=DepthMapConfig().chunk_points,
                    help="points per GPU batch (DepthMapConfig.chunk_points)")
    ap.add_argument("--overlap", choices=["on", "off", "both"], default="on",
                    help="render_many's overlapped mode where the maps fit (DepthMapConfig.overlap); both: "
                         "each budget with and without")
    ap.add_argument("--feed-threads", type=int, default=DepthMapConfig().feed_threads,
                    help="threads that pack and cull the batches (DepthMapConfig.feed_threads)")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--no-check", action="store_true", help="skip the bit-identity check against render()")
    ap.add_argument("--out", help="write the results as JSON here")
    ap.add_argument("--stages", action="store_true", help="also time the CPU stages around the GPU")
    args = ap.parse_args(argv)

    ctx = get_context()
    info = renderer_info(ctx)
    t0 = time.perf_counter()
    chunks, spacing = make_cloud(args.points, args.seed)
    gen_s = time.perf_counter() - t0
    cameras = make_cameras(args.photos, args.width, args.seed)
    w, h = depth_map_size(cameras[0], args.width)
    print(f"{info['renderer']} | {args.points:,} points (spacing {1e3 * spacing:.1f} mm, generated in "
          f"{gen_s:.1f} s), {args.photos} photos, {w}x{h}")
    if info["is_software"]:
        print("note: software rasterizer, GPU timings are meaningless")

    methods = ["compute", "raster"] if args.method == "both" else [args.method]
    out = {
        "benchmark": "depthmaps", "version": BENCH_VERSION,
        "machine": {"gl_renderer": info["renderer"], "gl_vendor": info["vendor"], "gl_version": info["version"],
                    "is_software": info["is_software"], "node": platform.node(), "cpus": os.cpu_count(),
                    "python": platform.python_version(), "numpy": np.__version__},
        "parameters": {"points": args.points, "photos": args.photos, "width": w, "height": h,
                       "methods": methods, "resident_mb": args.resident_mb, "seed": args.seed,
                       "box_m": BOX.tolist(), "point_spacing_m": spacing, "generate_s": gen_s,
                       "chunk_points": args.chunk_points, "overlap": args.overlap,
                       "feed_threads": args.feed_threads},
        "results": [],
    }
    results = out["results"]
    if args.stages:
        import tempfile

        renderer = DepthMapRenderer(ctx, DepthMapConfig(width=args.width, chunk_points=args.chunk_points))
        try:  # a real map to compress: the first camera's
            (_, depth), = renderer.render_many(cameras[:1], lambda: iter(chunks))
        finally:
            renderer.release()
        with tempfile.TemporaryDirectory() as folder:
            out["stages"] = stage_costs(ctx, chunks, args.chunk_points, cameras, args.width, args.feed_threads,
                                        depth, folder)
        print("  stages: " + ", ".join(f"{k} {v:.4f}" for k, v in out["stages"].items()), flush=True)
    overlaps = {"on": [True], "off": [False], "both": [True, False]}[args.overlap]
    for method in methods:
        for budget in args.resident_mb:
            for overlap in overlaps:
                r = run_one(ctx, method, chunks, cameras, args.width, budget, not args.no_check, args.chunk_points,
                            overlap, args.feed_threads)
                results.append(r)
                print(f"  {method} {budget:g} MB: {r['mode']}, {r['total_wall_s']:.2f} s, "
                      f"{r['splats_per_s'] or 0:.3g} splats/s", flush=True)
                if args.out:  # after every run: a later one may not finish
                    with open(args.out, "w") as f:
                        json.dump(out, f, indent=1)

    head = ["method", "budget MB", "mode", "groups", "upload GPU ms", "upload wall s", "wait s", "splat GPU ms",
            "splat ms/photo", "readback GPU ms", "readback wall s", "total wall s", "wall ms/photo",
            "splats/s", "splats/s wall", "coverage", "== render"]
    rows = [[r["method"], f"{r['resident_mb']:g}", r["mode"], r["groups"], f"{r['upload_gpu_ms']:.1f}",
             f"{r['upload_wall_s']:.2f}", f"{r['splat_wait_s']:.2f}", f"{r['splat_gpu_ms']:.1f}", f"{r['splat_gpu_ms_per_photo']:.3f}",
             f"{r['readback_gpu_ms']:.1f}", f"{r['readback_wall_s']:.2f}", f"{r['total_wall_s']:.2f}",
             f"{r['wall_ms_per_photo']:.2f}", f"{r['splats_per_s'] or 0:.3g}", f"{r['splats_per_s_wall']:.3g}",
             f"{r['coverage_mean']:.2f}", r["equal_to_render"]] for r in results]
    widths = [max(len(str(x)) for x in col) for col in zip(head, *rows)]
    for row in [head, *rows]:
        print("  ".join(str(x).rjust(wd) for x, wd in zip(row, widths)))
    return out


if __name__ == "__main__":
    main()
