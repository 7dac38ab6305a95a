"""Point normals and splat radii (paper Section 4.1), in memory and out of core.

* Normals: "if point normals are not available, we compute them by fitting a least-square plane to
  a neighborhood of each point" — the plane through the k nearest neighbours' centroid minimising
  the squared distances has the normal of the covariance matrix's smallest eigenvector (PCA).
  A plane has no front side, so normals are oriented toward the viewpoint that saw the point (a
  scanner station or the nearest camera): ``n . (v - p) > 0``.
* Radii: "the splat radii are determined from the density of the rendered points" — from the
  distance to the k-th nearest neighbour (see :func:`splat_radii` for the factor).
* :func:`process_chunked`: both for a cloud too large for memory, by spatial buckets with a halo
  (:mod:`dmrt.preprocess.buckets`);
  equal to the in-memory results wherever the neighbourhood fits inside the halo (counted and
  reported otherwise). With a distributed executor the buckets' kNN work runs as tasks, and so do
  the input passes (bounding box, cell counts, distribution into per-bucket spill files) over the
  consecutive parts of a splittable source (``split``, e.g. ``Octree.point_range``): each part
  spills into its own files per bucket, read back in part order, i.e. in input order, so the
  results equal the serial ones bit for bit.
"""

from __future__ import annotations

import math
import os
import shutil
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np
from scipy.spatial import cKDTree

from dmrt.io.atomic import atomic_file
from dmrt.preprocess.knn import KnnTree, neighbourhoods, pca_normals, radius_factor
from dmrt.preprocess.buckets import (Buckets, FineGrid, chunk_source, coarsen, count_input, distribute, halo_schema,
                                     input_bbox, input_pass, iter_chunks, positions_dtype, progress_bar,
                                     split_input)
from dmrt.preprocess.spill import Spill

__all__ = ["estimate_normals", "splat_radii", "orient_normals", "process_chunked", "ChunkedResult",
           "iter_with_results", "radius_factor"]


def _kdtree(c: np.ndarray) -> KnnTree:
    """Exact kNN queries over ``c`` (:class:`dmrt.preprocess.knn.KnnTree`, ``cKDTree.query``'s
    signature and results)."""
    return KnnTree(c)


def _pca_normals(data: np.ndarray, idx: np.ndarray) -> np.ndarray:
    """Least-squares plane normals from neighbour indices: :func:`dmrt.preprocess.knn.pca_normals`.

    Parameters
    ----------
    data : (m, 3) float64, already centred near the origin (precision)
    idx : (b, k) int indices into ``data``

    Returns
    -------
    (b, 3) float64 unit normals (sign arbitrary).
    """
    return pca_normals(data, idx)


# ---------------------------------------------------------------------------------------------
# in memory
# ---------------------------------------------------------------------------------------------
def _as_positions(positions) -> np.ndarray:
    p = np.asarray(positions)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"positions must have shape (n, 3), got {p.shape}")
    return p.astype(np.float64, copy=False)


def orient_normals(normals: np.ndarray, positions: np.ndarray, viewpoints=None,
                   per_point: bool | None = None) -> np.ndarray:
    """Flip normals so that ``n . (v - p) > 0`` for each point's viewpoint ``v``.

    Parameters
    ----------
    normals : (n, 3) float
    positions : (n, 3) float
    viewpoints : (m, 3) or (n, 3) float, optional
        Scanner stations / camera centres (each point takes the nearest), or one viewpoint per point.
        ``None``: a deterministic but arbitrary sign (``n_z >= 0``, then ``n_y``, then ``n_x``).
    per_point : bool, optional
        Whether ``viewpoints`` is one per point; by default it is when it has ``n`` rows.
    """
    n = np.array(normals, dtype=np.float64, copy=True)
    p = _as_positions(positions)
    if viewpoints is None:
        s = np.where(n[:, 2] != 0, n[:, 2], np.where(n[:, 1] != 0, n[:, 1], n[:, 0]))
        n[s < 0] *= -1
        return n
    v = np.asarray(viewpoints, dtype=np.float64).reshape(-1, 3)
    if per_point is None:
        per_point = len(v) == len(p) and len(p) > 1
    if per_point:
        if len(v) != len(p):
            raise ValueError(f"{len(v)} per-point viewpoints for {len(p)} points")
        to_v = v - p
    elif len(v) == 1:
        to_v = v[0] - p
    else:
        _, j = cKDTree(v).query(p, k=1, workers=-1)
        to_v = v[j] - p
    n[np.einsum("ij,ij->i", n, to_v) < 0] *= -1
    return n


def estimate_normals(positions, k: int = 16, viewpoints=None, *, per_point: bool | None = None,
                     tree: KnnTree | None = None) -> np.ndarray:
    """Least-squares plane normals of the ``k`` nearest neighbours (the point itself included).

    Parameters
    ----------
    positions : (n, 3) float64 or float32
    k : int
        Neighbourhood size (clamped to ``n``). 16 balances noise (a larger k averages it out) and
        detail (a smaller k follows creases).
    viewpoints : (m, 3) or (n, 3) float, optional
        Orientation: see :func:`orient_normals`.
    per_point : bool, optional
        See :func:`orient_normals`.
    tree : KnnTree, optional
        A tree already built on ``positions`` less their mean (as :func:`_kdtree`).

    Returns
    -------
    (n, 3) float32 unit normals, ``n . (v - p) > 0`` toward each point's viewpoint.
    """
    return normals_and_radii(positions, k, None, viewpoints=viewpoints, per_point=per_point, tree=tree)[0]


def splat_radii(positions, k: int = 8, scale: float = 1.0, *, tree: KnnTree | None = None) -> np.ndarray:
    """Splat radii from the local point density.

    ``radius = scale * d_k * sqrt(8/k) / 2`` with ``d_k`` the distance to the k-th nearest other
    point; on a square grid of spacing h this is h/sqrt(2), the smallest radius whose discs cover
    the plane (comment above :func:`dmrt.preprocess.knn.radius_factor`).

    Parameters
    ----------
    positions : (n, 3) float
    k : int
        Neighbour rank (clamped to ``n - 1``).
    scale : float
        Extra factor (the paper's worst case multiplies radii by 2.5).

    Returns
    -------
    (n,) float32 radii, metres.
    """
    return normals_and_radii(positions, None, k, scale, tree=tree)[1]


def normals_and_radii(positions, k_normals: int | None, k_radius: int | None, scale: float = 1.0,
                      viewpoints=None, *, per_point: bool | None = None,
                      tree: KnnTree | None = None) -> tuple[np.ndarray | None, np.ndarray | None]:
    """:func:`estimate_normals` (``k_normals``) and/or :func:`splat_radii` (``k_radius``, ``scale``)
    from one kNN query; None skips either. Returns ``(normals, radii)``, None for the one skipped."""
    p = _as_positions(positions)
    n = len(p)
    kn = min(int(k_normals), n) if k_normals else None
    kr = min(int(k_radius), n - 1) if k_radius else None
    normals = radii = None
    if kn is not None and n < 3:  # no plane: straight up
        out = np.zeros((n, 3), np.float64)
        out[:, 2] = 1.0
        normals, kn = orient_normals(out, p, viewpoints, per_point).astype(np.float32), None
    if kr is not None and n < 2:
        radii, kr = np.zeros(n, np.float32), None
    if kn or kr:
        c = p - p.mean(axis=0)  # centred: large real-world coordinates would lose digits in the covariance
        tree = tree if tree is not None else _kdtree(c)
        out, d_k = neighbourhoods(tree, c, k_normals=kn, k_radius=kr)
        if kn:
            normals = orient_normals(out, p, viewpoints, per_point).astype(np.float32)
        if kr:
            radii = (d_k * (scale * radius_factor(kr))).astype(np.float32)
    return normals, radii


# ---------------------------------------------------------------------------------------------
# out of core
# ---------------------------------------------------------------------------------------------
@dataclass
class ChunkedResult:
    """Output of :func:`process_chunked`: arrays indexed by the input's point order.

    Attributes
    ----------
    normals : (n, 3) float32 memmap (``work_dir/normals.npy``), or None
    radii : (n,) float32 memmap (``work_dir/radii.npy``), or None
    n_points : int
    margin : float
        Halo width, metres (inf when the cloud fit in memory and was processed whole).
    n_unverified : int
        Points whose neighbourhood (k-th neighbour distance) exceeded the margin: their neighbours
        outside the halo were not seen, so they may differ from the in-memory result (sparse
        outliers). 0 means the results equal the in-memory ones.
    n_buckets : int
    max_bucket_points : int
        Core + halo points of the largest bucket.
    seconds : float
        Wall time.
    timings : dict
        Wall seconds per pass of the bucketed path: ``bbox_s`` (0 with a given bbox), ``count_s``,
        ``distribute_s``, ``buckets_s``; empty for a cloud processed whole.

    Limitations: the halo's share of a bucket grows with ``margin`` / bucket size, so tiny budgets
    with sparse clouds process many halo points; a single grid cell denser than the bucket capacity
    is still processed in one piece (above the budget).
    """

    normals: np.ndarray | None
    radii: np.ndarray | None
    n_points: int
    margin: float
    n_unverified: int
    n_buckets: int
    max_bucket_points: int
    seconds: float
    timings: dict = field(default_factory=dict)


def _margin_from_counts(keys, cnts, cell, k, extent):
    """Halo width from the per-cell counts: 2.5x the k-th neighbour distance at the density of the
    sparse end (5th percentile, weighted by points) of the cells.

    A surface crossing a cube of side ``s`` has about ``s^2`` of area in it, so ``c`` points there
    mean a density of ``c / s^2`` and a k-th neighbour distance ``sqrt(k / (pi c / s^2))``. The
    cells are coarsened until that percentile holds ``4k`` points, so the count is not dominated by
    sampling noise. Partly filled cells (a surface clipping a corner) only lower the density
    estimate, which widens the margin: the safe side.
    """
    while True:
        order = np.argsort(cnts)
        cs = cnts[order]
        cum = np.cumsum(cs)
        c05 = float(cs[np.searchsorted(cum, 0.05 * cum[-1])])
        if c05 >= 4 * k or cell >= extent or len(keys) == 1:
            break
        keys, cnts = coarsen(keys, cnts)
        cell *= 2
    return 2.5 * math.sqrt(k / (math.pi * c05)) * cell


def process_chunked(chunks_fn, work_dir, *, normals: bool = True, radii: bool = True, k_normals: int = 16,
                    k_radii: int = 8, scale: float = 1.0, viewpoints=None, margin: float | None = None,
                    memory_limit_mb: float = 1024, bbox=None, progress: bool = True,
                    executor=None) -> ChunkedResult:
    """Normals and/or radii of a cloud too large for memory.

    The cloud is cut into spatial buckets (consecutive Morton cells of a grid whose cells are wider
    than ``2 * margin``); each bucket is processed with its *halo*, every point within ``margin`` of
    the bucket's occupied cells (a point's margin box overlaps at most 2 cells per axis). For a point whose
    k-th neighbour lies within ``margin`` the neighbourhood is complete, so the result equals the
    in-memory :func:`estimate_normals` / :func:`splat_radii` up to floating-point noise; the others
    are counted in ``n_unverified``.

    Passes over the input: bounding box (without ``bbox``), point counts per grid cell, and the
    distribution of core and halo copies into per-bucket spill files in ``work_dir``; then the kNN
    work per bucket.

    Parameters
    ----------
    chunks_fn : callable returning an iterator of chunks (as :meth:`dmrt.preprocess.octree.Octree.build`;
        e.g. ``lambda: octree.iter_levels(range(k))`` for the radii of a level of detail)
        Read 2 or 3 times, in the same order each time. A *splittable* source (a picklable
        callable with ``split(parts)`` returning consecutive sub-sources that together yield the
        same points in the same order, e.g. :meth:`dmrt.preprocess.octree.Octree.point_range` or
        :class:`dmrt.io.pointcloud.PointRange`) lets a distributed ``executor`` run the input
        passes too.
    work_dir : path
        Receives ``normals.npy`` / ``radii.npy`` (renamed into place when complete) and temporary
        spill files.
    viewpoints : (m, 3) float, optional
        Scanner stations / camera centres; each point is oriented toward the nearest.
    margin : float, optional
        Halo width in metres; default from the point counts per grid cell (2.5x the k-th neighbour
        distance at the density of the sparsest 5 % of the points, see ``_margin_from_counts``).
        When neither ``margin`` nor ``bbox`` is given and the cloud fits in the memory budget, it is
        processed whole, in memory (no buckets).
    memory_limit_mb : float
        Budget for the points of one bucket with its halo and the kNN work arrays (per task when
        tasks run at once: see ``executor``).
    executor : optional, :mod:`dmrt.preprocess.parallel`
        When distributed: the buckets' kNN work as tasks, one per bucket, and, for a splittable
        source, the input passes as tasks, one per part of ``chunks_fn.split(executor.workers)``
        (each counting task may hold a cell table as large as the serial pass's; the spill
        buffers are shared out). Workers read and write the spill files in ``work_dir``, so it
        must be on a file system they share. Results are written here, as without it, and equal
        the serial ones bit for bit. A cloud processed whole (above) stays in this process.

    Returns
    -------
    ChunkedResult
    """
    t0 = time.perf_counter()
    src = chunk_source(chunks_fn)
    work = Path(work_dir)
    work.mkdir(parents=True, exist_ok=True)
    if not (normals or radii):
        raise ValueError("nothing to compute: normals and radii are both False")
    kmax = max(k_normals if normals else 1, k_radii + 1 if radii else 1)  # kNN columns, self included
    budget = int(memory_limit_mb * 2 ** 20)
    # per point of a bucket: record 33 B, centred copy 24, kd-tree ~48, kNN batch rows are bounded
    # separately (knn_rows), so ~150 B/point within half the budget
    capacity = max(4096, int(budget * 0.5 / 150))
    slice_points = max(1024, budget // 8 // 256)
    knn_rows = max(1024, int(budget * 0.25 / (kmax * 3 * 8 * 3 + kmax * 16)))
    # the input passes run as tasks over consecutive parts of a splittable source, else here
    parts = split_input(src, executor)
    timings = {}

    tic = time.perf_counter()
    if bbox is None:
        lo, hi, n = input_bbox(parts, executor, desc="normals: bbox", progress=progress)
    else:
        lo, hi = (np.asarray(b, np.float64).reshape(3) for b in bbox)
        n = None
    if n is not None and n <= capacity and margin is None:
        # the whole cloud fits in the budget: one kd-tree, no buckets, no halos, no spill files
        return _process_in_memory(src, n, work, normals, radii, k_normals, k_radii, scale, viewpoints,
                                  progress, t0)
    extent = float(np.max(hi - lo)) or 1.0
    timings["bbox_s"], tic = time.perf_counter() - tic, time.perf_counter()

    # points per cell of a fine grid, coarsened (cells doubled) while the table is large. Each part
    # is counted against the whole cap, so the parts' tables add up to the serial table
    # (dmrt.preprocess.buckets); a part capped at a share cap / W could stop past the serial
    # shift, which no later step undoes.
    grid = FineGrid(lo, extent / ((1 << 20) - 1))
    counts, part_n, _ = count_input(parts, executor, grid, max(4096, budget // 256), slice_points,
                                    desc="normals: count", progress=progress, total=n)
    keys, cnts, shift = counts.keys, counts.counts, counts.shift
    del counts
    cell = grid.cell * 2.0 ** shift  # exactly the serial pass's repeated doubling
    timings["count_s"], tic = time.perf_counter() - tic, time.perf_counter()
    if n is not None and sum(part_n) != n:
        raise RuntimeError("chunks_fn must yield the same points on every call")
    n = sum(part_n)
    if n == 0:
        raise ValueError("the point source yielded no points")
    if margin is None:
        margin = _margin_from_counts(keys, cnts, cell, kmax, extent)
    margin = float(margin)
    if not margin > 0:
        raise ValueError(f"margin must be > 0, got {margin}")
    # bucket grid: cells wider than 2 margins, so a point's margin box overlaps <= 2 cells per axis
    while cell <= 2.0 * margin and shift < 20:
        cell, shift = cell * 2, shift + 1
        keys, cnts = coarsen(keys, cnts)
    # halos add points: leave room for them in a bucket
    buckets = Buckets.cut(grid, shift, keys, cnts, max(1, capacity // 2), halos=True)
    del keys, cnts
    nb = len(buckets)

    spill = Spill(str((work / f".spill-{os.getpid()}").resolve()), halo_schema(positions_dtype(src)), len(parts))
    shutil.rmtree(spill.root, ignore_errors=True)
    names = {"normals": work / "normals.npy", "radii": work / "radii.npy"}
    tmp_names = {k: work / f".{k}.npy.tmp-{os.getpid()}" for k in names}
    try:
        # distribute: core copy to the own bucket, halo copies to the other buckets in the margin
        # box; each part into its own spill folder per bucket, a share of the buffer budget each
        spill.create(nb)
        firsts = np.cumsum([0] + part_n[:-1]).tolist()  # each part's first global point index
        written = [m for m, _ in input_pass(distribute, parts, executor, "normals: distribute", progress, n,
                                            buckets=buckets, spill=spill, slice_points=slice_points,
                                            buffer_bytes=budget // 4 // len(parts), margin=margin,
                                            firsts=firsts)]
        if written != part_n:
            raise RuntimeError("chunks_fn must yield the same points on every call")
        timings["distribute_s"], tic = time.perf_counter() - tic, time.perf_counter()

        out_n = np.lib.format.open_memmap(tmp_names["normals"], "w+", np.float32, (n, 3)) if normals else None
        out_r = np.lib.format.open_memmap(tmp_names["radii"], "w+", np.float32, (n,)) if radii else None
        n_unverified = 0
        max_bucket = 0
        task = dict(spill=spill, normals=normals, radii=radii, k_normals=k_normals, k_radii=k_radii, scale=scale,
                    viewpoints=viewpoints, margin=margin, knn_rows=knn_rows)
        if executor is None or not executor.distributed:
            results = (_bucket_attrs(b, **task) for b in range(nb))
        else:
            results = executor.imap(_bucket_attrs, range(nb), desc="normals: buckets", progress=progress, **task)
        with progress_bar(n, "normals: buckets", progress and not getattr(executor, "distributed", False)) as bar:
            for gidx, nrm, rad, unverified, size in results:
                max_bucket = max(max_bucket, size)
                n_unverified += unverified
                if normals:
                    out_n[gidx] = nrm
                if radii:
                    out_r[gidx] = rad
                bar.update(len(gidx))
        for arr in (out_n, out_r):
            if arr is not None:
                arr.flush()
        del out_n, out_r
        timings["buckets_s"] = time.perf_counter() - tic
        shutil.rmtree(spill.root, ignore_errors=True)
        for k, path in names.items():
            if tmp_names[k].exists():
                os.replace(tmp_names[k], path)
    except BaseException:
        shutil.rmtree(spill.root, ignore_errors=True)
        for p in tmp_names.values():
            p.unlink(missing_ok=True)
        raise
    return ChunkedResult(
        normals=np.load(names["normals"], mmap_mode="r") if normals else None,
        radii=np.load(names["radii"], mmap_mode="r") if radii else None,
        n_points=n, margin=margin, n_unverified=n_unverified, n_buckets=nb,
        max_bucket_points=max_bucket, seconds=time.perf_counter() - t0,
        timings={k: round(v, 3) for k, v in timings.items()})


def _bucket_attrs(b: int, spill: Spill, normals: bool, radii: bool, k_normals: int, k_radii: int, scale: float,
                  viewpoints, margin: float, knn_rows: int):
    """The normals and radii of bucket ``b``'s core points (its spill folder is removed).

    The bucket's parts are read in part order, i.e. its points in input order, as one serial
    distribute pass writes them: the kd-tree and the results do not depend on the parts.

    Returns
    -------
    gidx : (m,) int64 the core points' indices in the input.  normals : (m, 3) float32 or None.
    radii : (m,) float32 or None.  n_unverified : int.  size : int, core + halo points.
    """
    rec = spill.read(b)
    spill.remove(b)
    # float64 as every other path computes (float32 spills hold float32 inputs exactly)
    pos, gidx, core = rec["positions"].astype(np.float64), rec["gidx"], rec["core"].astype(bool)
    qi = np.flatnonzero(core)
    out_n = np.empty((len(qi), 3), np.float32) if normals else None
    out_r = np.empty(len(qi), np.float32) if radii else None
    n_unverified = 0
    if len(qi) == 0:
        return gidx[qi], out_n, out_r, 0, len(pos)
    c = pos - pos.mean(axis=0)
    tree = _kdtree(c)
    kn = min(k_normals, len(pos))  # neighbours of the plane fit, the point included
    kr = min(k_radii, len(pos) - 1)  # rank of the radius neighbour, the point excluded
    kq = max(kn if normals else 1, kr + 1 if radii else 1)  # kNN columns needed
    for s in range(0, len(qi), knn_rows):
        rows = qi[s:s + knn_rows]
        d, idx = tree.query(c[rows], k=kq, workers=-1)
        d = d.reshape(len(rows), kq)
        idx = idx.reshape(len(rows), kq)
        # complete neighbourhood <=> its farthest member lies within the halo margin
        n_unverified += int(np.count_nonzero(~(d[:, -1] <= margin)))
        if normals:
            if kn >= 3:
                nrm = _pca_normals(c, idx[:, :kn])
            else:
                nrm = np.tile([0.0, 0.0, 1.0], (len(rows), 1))
            nrm = orient_normals(nrm, pos[rows], viewpoints, per_point=False)
            out_n[s:s + len(rows)] = nrm.astype(np.float32)
        if radii:
            rad = d[:, kr] * (scale * radius_factor(kr)) if kr >= 1 else np.zeros(len(rows))
            out_r[s:s + len(rows)] = rad.astype(np.float32)
    return gidx[qi], out_n, out_r, n_unverified, len(pos)


def _process_in_memory(src, n, work, normals, radii, k_normals, k_radii, scale, viewpoints, progress,
                       t0) -> ChunkedResult:
    """:func:`process_chunked` for a cloud that fits in memory: the in-memory functions on one tree,
    results written as ``process_chunked`` writes them (renamed into place when complete)."""
    pos = np.empty((n, 3), np.float64)
    g = 0
    with progress_bar(n, "normals: read", progress) as bar:
        for p, _ in iter_chunks(src):
            if g + len(p) > n:
                raise RuntimeError("chunks_fn must yield the same points on every call")
            pos[g:g + len(p)] = p
            g += len(p)
            bar.update(len(p))
    if g != n:
        raise RuntimeError("chunks_fn must yield the same points on every call")
    found = normals_and_radii(pos, k_normals if normals else None, k_radii if radii else None, scale, viewpoints,
                              per_point=False)
    results = {name: a for name, a in zip(("normals", "radii"), found) if a is not None}
    for name, a in results.items():
        with atomic_file(work / f"{name}.npy") as tmp, open(tmp, "wb") as fh:
            np.save(fh, a, allow_pickle=False)
    done = {name: np.load(work / f"{name}.npy", mmap_mode="r") for name in results}
    return ChunkedResult(normals=done.get("normals"), radii=done.get("radii"), n_points=n,
                         margin=float("inf"), n_unverified=0, n_buckets=1, max_bucket_points=n,
                         seconds=time.perf_counter() - t0)


def iter_with_results(chunks_fn, result: ChunkedResult) -> Iterator[tuple[np.ndarray, dict]]:
    """The input chunks again, with ``normals`` and/or ``radii`` attributes from ``result`` added
    (ready for :meth:`dmrt.preprocess.octree.Octree.build`)."""
    g = 0
    for pos, attrs in iter_chunks(chunk_source(chunks_fn)):
        m = len(pos)
        attrs = dict(attrs)
        if result.normals is not None:
            attrs["normals"] = np.array(result.normals[g:g + m])
        if result.radii is not None:
            attrs["radii"] = np.array(result.radii[g:g + m])
        g += m
        yield pos, attrs
