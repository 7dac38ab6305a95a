"""Nested levels of detail of a point cloud, built out of core (the paper's out-of-core octree).

The paper (Section 4.1/4.2) keeps P_HD in an out-of-core octree in the style of Scheiblauer &
Wimmer / Potree and takes the proxy cloud P_LD as the union of its k top-most (coarsest) levels.
This module builds that structure for clouds far larger than memory.

Levels
------
Level ``l`` (``0 <= l < levels - 1``) has a grid of cell size ``s_l = root_cell / 2**l`` laid over the
cloud's bounding box (origin = bbox minimum). Every occupied level-``l`` cell receives exactly one
point: among the points of that cell that no coarser level has taken, the one **closest to the cell
centre** (ties broken by x, then y, then z). Points that no grid level takes form the last level,
``levels - 1`` (the remainder). Cells are defined by the integer coordinates of the finest grid
level, ``floor((p - origin) / s_finest)``, shifted right by ``finest - l`` bits for level ``l``, so the
grids nest exactly (no second rounding). Hence

* every input point is in exactly one level (the levels partition the cloud);
* no two points of level ``l`` share a level-``l`` cell (each level is spatially even);
* ``LOD k`` = levels ``0 .. k-1`` holds a point in every occupied level-``(k-1)`` cell, and each
  ``LOD k+1`` is a superset of ``LOD k`` (nested), roughly 4x denser for surfaces (8x for volumes).

Positions
---------
The octree holds positions as **float32** (12 bytes a point instead of 24: for a 683M-point cloud of
39-byte float64 records, 8.2 GB less in the level files and as much again in the spill files). The
input's positions are rounded to float32 (to nearest) as they enter the build, in every pass that
reads the input, and the octree is that of the rounded points: the bbox, the cells, the "closest
to the cell centre" selection, the candidates and the spill files all see the same float32 values
(distances are computed in float64 on them, exactly upcast). So the build of a float64 input is the
build of the same input rounded to float32 beforehand, byte for byte. Give the build positions
relative to a nearby origin (the pipeline's are relative to the scene's bounding-box centre):
rounding to float32 moves a coordinate by at most 2 micrometres within 64 m of it, 4 within 128 m
(half a unit in the last place), and the stages after the octree (depth maps, proxies, the GPU)
use float32 positions anyway. A given ``bbox`` is rounded to float32 too (the octree's box, in
``octree.json``); rounding is monotonic, so a point inside the given box stays inside the rounded
one, and the exact box of the input rounds to the box of the rounded points.

The selection is a pure function of the *set* of (rounded) input points: chunk order and chunk
sizes do not change the octree (except the order of exact duplicate points, which follows the
input; rounding may make duplicates of points a float32 step apart). Each level file is in Morton
order of its cells (the remainder: of the finest cells, duplicates in input order), so for a given
input the level files are the same bytes whatever the memory limit, the
buckets and the number of workers.

Out-of-core build (memory ``M = memory_limit_mb``, ``W`` workers)
---------------------------------------------------------------
The input parts, cell counts, buckets and spill files are :mod:`dmrt.preprocess.buckets` and
:mod:`dmrt.preprocess.spill` (shared with the normals); this module chooses the levels, the
bucket level and the budget, and selects the levels.

1. (only without ``bbox``) one pass for the bounding box;
2. *count*: points per cell of a counting grid (sparse: sorted int64 Morton keys + counts; coarsened
   one level at a time while the table would exceed ``M/256`` entries, ~3/8 M with merge temporaries);
3. choose the *bucket level* ``c`` = the coarsest level whose cells each hold at most one bucket's
   capacity (0.4 M / W of records plus work arrays), and cut the Morton-sorted level-``c`` cells
   into buckets of consecutive cells, each within capacity;
4. *distribute*: stream the points into per-bucket spill files (``M/4`` bytes of buffers), in input
   order;
5. *candidates*: levels ``l < c`` have cells spanning several buckets. A level-``l`` pick is the best
   point of its cell that levels ``< l`` did not take; at most ``l`` points of the cell were taken, so
   it is among the cell's ``l + 1`` best, hence among the union over buckets of each bucket's ``l + 1``
   best of that cell. Each bucket contributes those candidates (few: they scale with the coarse
   levels' sizes), and levels ``0 .. c-1`` are resolved exactly in memory;
6. *select*: each bucket is loaded alone, the coarse picks are removed, and levels ``c .. levels-2``
   plus the remainder are selected inside it (level ``>= c`` cells never cross a bucket): one
   stable sort by the finest Morton key makes every level's cells contiguous runs, and each level
   is a segmented minimum over them, taken block by block (blocks of whole level-``c`` cells, small
   enough to stay in cache across the levels). A bucket's spill folder is deleted as soon as it is
   done.

A level-``c`` cell that alone exceeds the capacity (extreme point density) is processed by streaming
per-level reductions over its spill file; then memory is proportional to its number of occupied
cells per level rather than to its number of points (plus one byte per point). Its remainder is
spilled once more, in runs of whole finest cells of at most half the capacity, and each run is
sorted alone, so it is written in the same order as a bucket selected in memory.

With a distributed executor (``executor`` of :meth:`Octree.build`, e.g.
:class:`~dmrt.preprocess.parallel.ProcessPool`; ``W = executor.workers`` processes), passes 5 and 6
run as tasks, one per bucket: a task reads its bucket's spill files and returns the candidates (5)
or writes the bucket's levels to ``select/b<bucket>/`` in the temporary folder and deletes the
bucket's spill folder (6); this process resolves the coarse levels and appends the buckets' level
files in bucket order, deleting each as it goes. W workers hold W buckets at once, hence the
capacity of 0.4 M / W each; every worker process brings its own interpreter with numpy (~45 MB
resident) on top.

Passes 1, 2 and 4 read the input. They run as tasks too when the source *splits*: a picklable
callable with a method ``split(parts)`` returning at most ``parts`` consecutive sub-sources that
together yield the same points in the same order (:class:`~dmrt.io.pointcloud.PointRange` of a
binary PLY, :class:`OctreeRange`). The source is split into ``K <= W`` parts, one task each, and
each task holds 1/K of the tables, buffers and slices a serial pass holds: (1) returns the part's
box and point count; (2) returns the part's sparse counts, coarsened against ``M/256/K`` entries,
which this process merges at the coarsest level any part reached and coarsens while over ``M/256``
(see :meth:`_Builder._count`); (4) writes the part's points of bucket ``b`` to
``spill/b<bucket>/p<part>/``. A bucket is then read part after part, which is the input order, so
passes 5 and 6 see exactly what the serial build spilled. A source without ``split`` (a plain
callable, a list), or one that returns a single part, is read in this process. Either way the
level files are the serial build's, byte for byte. Measured (``bench/bench_octree.py``, 4M points,
``M`` = 256 MB, input generation excluded, before the input passes ran in the workers): serially,
select takes ~70% of the build, count and distribute ~15% each, candidates nothing (``c`` = 0
there); so beyond a few workers the passes that read the input dominate unless they split.

Input chunks are processed in slices of about ``M / 8`` (``M / 8K`` per part) of work arrays, but
the caller's chunk itself counts against the budget: keep ``chunk_size * record_bytes`` well below
``M`` (``M / K`` with a split source; ``record_bytes`` = the caller's position bytes, 24 for float64,
plus the attributes' bytes; the build rounds each slice to float32 as it reads it, 12 bytes a
point of the slice, and spills ``record_bytes`` = 12 plus the attributes' bytes). The interpreter
with numpy (~40 MB resident) comes on top. Measured (``bench/bench_octree.py``, 20M points of 39
bytes = 744 MB, ``M`` = 256 MB, before positions were stored as float32): maximum RSS 174,724 kB
(``/usr/bin/time -v``) including that baseline.

An interrupted build (exception, Ctrl-C) removes its temporary folder; a killed one leaves only
``<name>.partial`` without ``octree.json``, which :meth:`Octree.open` refuses.

On disk (written to a temporary sibling folder and renamed when complete)::

    out_dir/octree.json            format, version, config, bbox, counts, fields, buckets, workers, timings
    out_dir/level_XX/<field>.bin   raw little-endian arrays, one file per attribute, Morton-ordered
                                   (positions.bin: (n, 3) float32)

Version 2 stores float32 positions; :meth:`Octree.open` refuses version 1 (float64 positions).
"""

from __future__ import annotations

import dataclasses
import json
import math
import shutil
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Iterator

import numpy as np

from dmrt.errors import InputError
from dmrt.io.atomic import atomic_dir
from dmrt.morton import MAX_BITS_PER_AXIS, morton_encode
from dmrt.preprocess.buckets import (Buckets, chunk_source, coarsen, count_input, distribute, first_chunk, in_sorted,
                                     input_bbox, input_pass, iter_chunks, merge_counts, morton_columns,
                                     normalize_chunk, progress_bar, split_input, unique_counts)
from dmrt.preprocess.spill import Appender, Spill, field_bytes, read_records, take

FORMAT = "dmrt-octree"
VERSION = 2  # 2: positions stored as float32 (1: float64)

POSITIONS_DTYPE = "float32"
"""The dtype of the octree's positions, in every pass and on disk: the input's are rounded to it as
they enter the build (see the module docstring)."""


# ---------------------------------------------------------------------------------------------
# configuration
# ---------------------------------------------------------------------------------------------
@dataclass
class OctreeConfig:
    """How to build the levels of detail."""

    levels: int = 8
    """Number of levels of detail; levels ``0 .. levels-2`` are grid levels, the last one holds the
    remainder (every point no grid level took)."""
    root_cell: float | None = None
    """Cell size of level 0, metres. Default: bounding-box diagonal / 64."""
    memory_limit_mb: float = 2048
    """Bytes of point data (and working arrays) the build may hold at once, in MiB."""

    def __post_init__(self):
        if int(self.levels) < 1:
            raise ValueError(f"OctreeConfig.levels must be >= 1, got {self.levels}")
        self.levels = int(self.levels)
        if self.root_cell is not None and not float(self.root_cell) > 0:
            raise ValueError(f"OctreeConfig.root_cell must be > 0, got {self.root_cell}")
        if not float(self.memory_limit_mb) > 0:
            raise ValueError(f"OctreeConfig.memory_limit_mb must be > 0, got {self.memory_limit_mb}")


# ---------------------------------------------------------------------------------------------
# the grid of all levels
# ---------------------------------------------------------------------------------------------
@dataclass
class _Grid:
    origin: np.ndarray  # (3,) float64
    root_cell: float
    n_grid: int  # number of grid levels (= levels - 1)
    bits0: int  # bits per axis at level 0

    @property
    def finest(self) -> int:
        return self.n_grid - 1

    def cell(self, level: int) -> float:
        return self.root_cell / 2.0 ** level

    def coords(self, pos: np.ndarray) -> np.ndarray:
        """(n, 3) int64 cell coordinates at the finest grid level (coarser: ``>> (finest - l)``)."""
        bits = self.bits0 + self.finest
        q = np.subtract(pos, self.origin)  # float64, in place from here
        q *= 1.0 / self.cell(self.finest)
        np.floor(q, out=q)
        np.clip(q, 0, (1 << bits) - 1, out=q)
        return q.astype(np.int64)

    def keys_and_d2(self, pos: np.ndarray, q: np.ndarray, level: int):
        """Morton keys of the level-``level`` cells and squared distances to their centres."""
        ql = q >> (self.finest - level)
        return morton_encode(ql), self.d2(pos[:, 0], pos[:, 1], pos[:, 2], ql[:, 0], ql[:, 1], ql[:, 2], level)

    def d2(self, x, y, z, qx, qy, qz, level: int) -> np.ndarray:
        """Squared distance of points (coordinate columns) to the centres of their level-``level``
        cells (integer columns). The one formula every path uses, so equal inputs give bit-equal
        distances (and exact ties stay ties)."""
        s = self.cell(level)
        o = self.origin
        dx = x - (o[0] + (qx + 0.5) * s)
        dy = y - (o[1] + (qy + 0.5) * s)
        dz = z - (o[2] + (qz + 0.5) * s)
        return dx * dx + dy * dy + dz * dz

    def coord_columns(self, pos: np.ndarray) -> list:
        """:meth:`coords` of (n, 3) ``pos`` as three contiguous (n,) int32 columns (the same values:
        the same float64 operations per coordinate; < 2**21 fits int32, half the traffic)."""
        hi = (1 << (self.bits0 + self.finest)) - 1
        buf = np.empty(len(pos))
        out = []
        for j in range(3):
            # origin[j:j + 1], an array: a float64 loop whatever numpy's scalar casting rules
            np.subtract(pos[:, j], self.origin[j:j + 1], out=buf)
            buf *= 1.0 / self.cell(self.finest)
            np.floor(buf, out=buf)
            np.clip(buf, 0, hi, out=buf)
            out.append(buf.astype(np.int32))
        return out

    def d2_runs(self, cols, qc, runs: "_Runs", shift: int, level: int) -> np.ndarray:
        """:meth:`d2` of coordinate columns ``cols`` and finest-grid integer columns ``qc`` whose
        level-``level`` cells (``qc >> shift``) are the runs ``runs``, bit for bit: each cell
        centre is computed once per run with :meth:`d2`'s operations and spread over the run, so a
        point costs a spread, a subtraction and a square per axis instead of seven passes."""
        s, o = self.cell(level), self.origin
        d2 = None
        for j in range(3):
            centre = np.take(qc[j], runs.start) >> shift
            centre = centre + 0.5
            centre *= s
            centre += o[j]
            d = runs.spread(centre)
            np.subtract(cols[j], d, out=d)
            if d2 is None:
                d2 = np.multiply(d, d, out=d)
            else:
                d *= d
                d2 += d
        return d2


@dataclass
class _Runs:
    """Runs of equal cells in an array of ``n`` points sorted by cell: ``start`` ((r,) int64,
    ``start[0] == 0``) and, when runs are short, each point's run index ``rid`` ((n,) int64)."""

    start: np.ndarray
    n: int
    rid: np.ndarray | None = None

    @classmethod
    def from_breaks(cls, breaks: np.ndarray) -> "_Runs":
        """Runs of ``n = len(breaks) + 1`` points where ``breaks[i]`` says point ``i + 1`` starts
        a new run ((n - 1,) bool)."""
        n = len(breaks) + 1
        start = np.r_[0, np.flatnonzero(breaks) + 1]
        rid = None
        if len(start) * 8 > n:
            # short runs: np.repeat spends per run (27 against 11 ms for 3M points in runs of
            # two), a gather by run index per point does not (and its index serves every spread)
            rid = np.empty(n, np.int64)
            rid[0] = 0
            np.cumsum(breaks, out=rid[1:])
        return cls(start, n, rid)

    def spread(self, values: np.ndarray) -> np.ndarray:
        """Each point's value of its run, (n,), from ``values`` (r,) per run."""
        if self.rid is not None:
            return np.take(values, self.rid)
        return np.repeat(values, np.diff(np.r_[self.start, self.n]))


def _best_in_runs(keys, d2, cols) -> np.ndarray:
    """Like :func:`_best_per_cell` for ``keys`` already sorted (cells are contiguous runs) and
    positions given as coordinate columns ``(x, y, z)``; among exact ties of distance and position
    the earliest index wins."""
    if len(keys) == 0:
        return np.zeros(0, np.int64)
    return _best_of_runs(_Runs.from_breaks(keys[1:] != keys[:-1]), d2, cols)


def _best_of_runs(runs: _Runs, d2, cols) -> np.ndarray:
    """Index of the best point of each run ``d2[start[i]:start[i + 1]]`` of ``start = runs.start``
    (smallest ``d2``, then lowest x, y, z of the columns ``cols``, then earliest), in run order. A
    point whose ``d2`` is ``inf`` is no candidate (real distances never are) and a run of only such
    points has no best.

    Parameters
    ----------
    runs : :class:`_Runs` of the ``n`` points
    d2 : (n,) float64 squared distances, m**2
    cols : three (n,) float32 (or float64) coordinate columns, m
    """
    start = runs.start
    gmin = np.minimum.reduceat(d2, start)
    is_min = d2 == runs.spread(gmin)
    idx = np.flatnonzero(is_min)  # sorted; every run has at least one minimum
    del is_min
    if len(idx) == len(start):  # one minimum per run, the common case: no run search
        best = idx
    else:  # exact distance ties (regular grids, duplicates): lowest x, y, z
        grp = np.searchsorted(start, idx, side="right") - 1 if runs.rid is None else np.take(runs.rid, idx)
        first = np.r_[True, grp[1:] != grp[:-1]]
        best = idx[first]
        n_min = np.diff(np.r_[np.flatnonzero(first), len(idx)])
        sel = np.repeat(n_min > 1, n_min)
        ti, tg = idx[sel], grp[sel]
        ot = np.lexsort((ti, cols[2][ti], cols[1][ti], cols[0][ti], tg))
        tgs = tg[ot]
        firsts = np.r_[True, tgs[1:] != tgs[:-1]]
        best[tgs[firsts]] = ti[ot[firsts]]
    dead = gmin == np.inf
    return best[~dead] if dead.any() else best


def _best_per_cell(keys, d2, pos) -> np.ndarray:
    """Index of the best point of every cell — smallest distance to the cell centre, ties broken by
    x, then y, then z, then index — in Morton order of the cells.

    One stable sort of the keys (:func:`_stable_order`) and a segmented minimum; only exact
    distance ties (regular grids) take a lexicographic sort, on the tied points alone.

    Parameters
    ----------
    keys : (n,) int64 cell keys
    d2 : (n,) float64 squared distances to the cell centres
    pos : (n, 3) float32 (or float64)
    """
    if len(keys) == 0:
        return np.zeros(0, np.int64)
    o, ks = _stable_order(keys)
    p = np.take(pos, o, axis=0)
    return o[_best_in_runs(ks, d2[o], (p[:, 0], p[:, 1], p[:, 2]))]


def _top_m(keys, d2, pos, m: int) -> np.ndarray:
    """Indices of the ``m`` best points of every cell (order as :func:`_best_per_cell`, repeated)."""
    if m == 1:
        return _best_per_cell(keys, d2, pos)
    out = []
    alive = np.arange(len(keys))
    for _ in range(m):
        if len(alive) == 0:
            break
        b = alive[_best_per_cell(keys[alive], d2[alive], pos[alive])]
        out.append(b)
        mask = np.ones(len(keys), bool)
        mask[np.concatenate(out)] = False
        alive = np.flatnonzero(mask)
    return np.concatenate(out) if out else np.zeros(0, np.int64)


def _stable_order(keys: np.ndarray):
    """The permutation of a stable argsort of ``keys`` and the sorted keys, both (n,) int64.

    Where the keys' range and the index fit 63 bits together, one plain sort of the keys packed
    above their index (equal keys fall to the index: stable), an order of magnitude faster than
    numpy's stable argsort of int64 (measured 23 against 374 ms on 2M random 39-bit keys)."""
    n = len(keys)
    if n == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    lo = int(keys.min())
    ib = max(1, (n - 1).bit_length())
    if (int(keys.max()) - lo).bit_length() + ib > 63:
        o = np.argsort(keys, kind="stable")
        return o, keys[o]
    packed = keys - lo
    packed <<= ib
    packed |= np.arange(n)
    packed.sort()
    srt = packed >> ib
    srt += lo
    packed &= (1 << ib) - 1
    return packed, srt


SELECT_BLOCK = 1 << 16
"""Points of a block of the in-memory select (:meth:`_BucketWork._select_block`): its work arrays
and temporaries (~70 bytes a point, 4.5 MB) stay in a core's cache (or its share of a shared one)
across the block's levels, and its numpy calls (a few hundred) cost little against its points.
Measured (one core, 3M points as dense per cell as the 683M-point scan's buckets, CPU time):
0.23 us a point unblocked, 0.19 / 0.19 / 0.18 in blocks of 2**14 / 2**16 / 2**18."""


def _block_cuts(breaks: np.ndarray, size: int) -> np.ndarray:
    """Cut ``n = len(breaks) + 1`` points into blocks of whole runs (``breaks[i]``: point ``i + 1``
    starts a run), each of about ``size`` points or one longer run: (k + 1,) int64 increasing
    bounds from 0 to ``n``."""
    n = len(breaks) + 1
    start = np.flatnonzero(breaks) + 1
    # the first run start at or after each multiple of size
    at = np.searchsorted(start, np.arange(size, n, size))
    return np.unique(np.r_[0, start[at[at < len(start)]], n])


def _gather(rec: dict, idx: np.ndarray) -> dict:
    """The records ``idx`` (an index array) of every field of ``rec``: ``np.take`` along the first
    axis, several times faster than fancy indexing for per-point rows such as (n, 3) positions."""
    return {k: np.take(v, idx, axis=0) for k, v in rec.items()}


# ---------------------------------------------------------------------------------------------
# the octree
# ---------------------------------------------------------------------------------------------
class Octree:
    """Nested levels of detail on disk (see the module docstring).

    Attributes
    ----------
    path : Path
    config : OctreeConfig
    level_counts : list[int]
        Points per level, coarsest first.
    bbox : ((3,) float64, (3,) float64)
    fields : dict name -> (dtype str, per-point shape tuple); always holds ``'positions'``
        (``('float32', (3,))``).
    meta : dict
        The parsed ``octree.json``.
    """

    def __init__(self, path, meta: dict):
        self.path = Path(path)
        self.meta = meta
        cfg = meta["config"]
        self.config = OctreeConfig(levels=cfg["levels"], root_cell=cfg["root_cell"],
                                   memory_limit_mb=cfg["memory_limit_mb"])
        self.level_counts = [int(c) for c in meta["level_counts"]]
        self.bbox = (np.asarray(meta["bbox"][0], np.float64), np.asarray(meta["bbox"][1], np.float64))
        self.fields = {k: (v["dtype"], tuple(v["shape"])) for k, v in meta["fields"].items()}

    # -- properties ------------------------------------------------------------------------------
    @property
    def levels(self) -> int:
        return len(self.level_counts)

    @property
    def n_points(self) -> int:
        return int(sum(self.level_counts))

    def cell_size(self, level: int) -> float:
        """Cell size (metres) of grid level ``level``."""
        return float(self.meta["root_cell"]) / 2.0 ** level

    def __repr__(self):
        return f"Octree({str(self.path)!r}, levels={self.level_counts})"

    # -- opening -------------------------------------------------------------------------------
    @classmethod
    def open(cls, out_dir) -> "Octree":
        path = Path(out_dir)
        jf = path / "octree.json"
        if not jf.is_file():
            raise InputError(jf, "not an octree: octree.json is missing (unfinished or wrong folder)")
        try:
            meta = json.loads(jf.read_text())
        except json.JSONDecodeError as e:
            raise InputError(jf, f"invalid JSON: {e}") from None
        if meta.get("format") != FORMAT:
            raise InputError(jf, f"field 'format' is {meta.get('format')!r}, expected {FORMAT!r}")
        if meta.get("version") != VERSION:
            hint = " (version 1 stored float64 positions: build the octree again)" if meta.get("version") == 1 else ""
            raise InputError(jf, f"field 'version' is {meta.get('version')!r}, this reader knows {VERSION}{hint}")
        for key in ("config", "level_counts", "bbox", "fields", "root_cell"):
            if key not in meta:
                raise InputError(jf, f"field {key!r} is missing")
        tree = cls(path, meta)
        for lvl, n in enumerate(tree.level_counts):
            for k, (dt, shape) in tree.fields.items():
                f = tree._level_dir(lvl) / f"{k}.bin"
                want = n * np.dtype(dt).itemsize * int(np.prod(shape, dtype=np.int64))
                size = f.stat().st_size if f.exists() else 0
                if size != want:
                    raise InputError(f, f"holds {size} bytes, octree.json field 'level_counts' "
                                        f"implies {want}")
        return tree

    # -- reading -------------------------------------------------------------------------------
    def _level_dir(self, level: int) -> Path:
        return self.path / f"level_{level:02d}"

    def _check_level(self, level):
        if not 0 <= level < self.levels:
            raise IndexError(f"level {level} out of range 0..{self.levels - 1}")

    def read_level(self, level: int) -> dict:
        """All points of one level: ``{'positions': (n, 3) float32, <attribute>: (n, ...)}``."""
        self._check_level(level)
        return read_records(self._level_dir(level), self.fields)

    def iter_level_chunks(self, level: int, chunk_size: int = 1_000_000) -> Iterator[dict]:
        """One level in chunks of at most ``chunk_size`` points (dicts as :meth:`read_level`)."""
        self._check_level(level)
        n = self.level_counts[level]
        for s in range(0, n, int(chunk_size)):
            yield read_records(self._level_dir(level), self.fields, s, min(n, s + int(chunk_size)))

    def iter_levels(self, levels: Iterable[int] | None = None, chunk_size: int = 1_000_000) -> Iterator[dict]:
        """Stream several levels (default: all), coarsest first, in chunks of ``<= chunk_size``."""
        for lvl in (range(self.levels) if levels is None else levels):
            yield from self.iter_level_chunks(lvl, chunk_size)

    def point_range(self, levels: Iterable[int] | None = None, chunk_size: int = 1_000_000) -> "OctreeRange":
        """The points of ``levels`` (default: all; consecutive), coarsest first, as a picklable
        chunk source that splits into ranges for worker processes (:class:`OctreeRange`)."""
        levels = list(range(self.levels) if levels is None else levels)
        if levels and levels != list(range(levels[0], levels[0] + len(levels))):
            raise ValueError(f"levels must be consecutive, got {levels}")
        counts = np.cumsum([0] + self.level_counts)
        start, stop = (int(counts[levels[0]]), int(counts[levels[-1] + 1])) if levels else (0, 0)
        return OctreeRange(str(self.path), self.fields, tuple(self.level_counts), start, stop, int(chunk_size))

    def read_lod(self, k: int) -> dict:
        """``LOD k`` = levels ``0 .. k-1`` concatenated (the paper's proxy cloud P_LD for ``k``), a
        dict as :meth:`read_level` (``'positions'``: (n, 3) float32)."""
        parts = [self.read_level(lvl) for lvl in range(k)]
        if not parts:
            return {f: np.zeros((0, *s), dt) for f, (dt, s) in self.fields.items()}
        return {f: np.concatenate([p[f] for p in parts]) for f in self.fields}

    def lod_counts(self) -> list[int]:
        """``|LOD k|`` for ``k = 1 .. levels``."""
        return [int(c) for c in np.cumsum(self.level_counts)]

    def subsampling_factors(self) -> list[float]:
        """``|P_HD| / |LOD k|`` for ``k = 1 .. levels`` (non-increasing, ends at 1.0)."""
        total = self.n_points
        return [total / c if c else math.inf for c in self.lod_counts()]

    def lod_for_factor(self, factor: float) -> int:
        """The smallest ``k`` whose sub-sampling factor is at most ``factor`` (i.e. the coarsest
        LOD at least as dense as asked)."""
        for k, f in enumerate(self.subsampling_factors(), start=1):
            if f <= factor:
                return k
        return self.levels

    # -- building ------------------------------------------------------------------------------
    @classmethod
    def build(cls, chunks_fn, out_dir, config: OctreeConfig | None = None, bbox=None,
              progress: bool = True, executor=None) -> "Octree":
        """Build the levels of detail out of core and write them to ``out_dir``.

        Parameters
        ----------
        chunks_fn : callable returning an iterator of chunks (or a re-iterable)
            Each chunk is ``(positions (n, 3) float64 or float32, {name: (n, ...) array})``, a
            dict with ``'positions'``, or a ``PointCloud``. Positions are rounded to float32 as
            they are read (the octree stores float32 positions: keep them near the origin). Read
            2 times (3 without ``bbox``), plus the
            first chunk once more for the attribute schema; every pass must yield the same points
            in the same order, and every chunk the first chunk's attributes (dtype and shape).
            Attributes travel with the points. A picklable callable with ``split(parts) -> list``
            of consecutive sub-sources (:class:`~dmrt.io.pointcloud.PointRange`,
            :class:`OctreeRange`) is read in parts by the workers of a distributed ``executor``.
        out_dir : path
            Written atomically: built in ``<out_dir>.partial`` beside it and renamed when
            complete. An existing octree there is replaced; any other non-empty folder is an error.
        config : OctreeConfig
        bbox : ((3,), (3,)) float64, optional
            The cloud's bounding box; computed in an extra pass if omitted. Rounded to float32
            (nearest), as the points are: the octree's box and origin. Points whose rounded
            position lies outside it are clipped into the boundary cells and counted in
            ``octree.json``'s ``points_outside_bbox``; a point inside the given box never is.
        progress : bool
            tqdm progress bars.
        executor : optional, :mod:`dmrt.preprocess.parallel`
            When distributed, the candidates and select passes run as tasks, one per bucket,
            each worker within ``memory_limit_mb / executor.workers``; the workers read and write
            the build's temporary folder beside ``out_dir``, so it must be on a file system they
            see. When ``chunks_fn`` splits into several parts (at most ``executor.workers``), the
            passes that read the input (bbox, count, distribute) run as tasks too, one per part,
            each within its share of the memory; else they run here. An error in a task (e.g. a
            chunk whose attributes differ, named by its part and its index in the part) is raised
            here. The level files equal those of the serial build (None or an
            :class:`~dmrt.preprocess.parallel.InProcess`) byte for byte.
        """
        config = config or OctreeConfig()
        src = chunk_source(chunks_fn)
        out_dir = Path(out_dir)
        if out_dir.exists() and not (out_dir / "octree.json").exists() and any(out_dir.iterdir()):
            raise InputError(out_dir, "exists and is not an octree; refusing to overwrite it")
        out_dir.parent.mkdir(parents=True, exist_ok=True)
        with atomic_dir(out_dir, what="octree") as tmp:
            meta = _Builder(src, tmp, config, bbox, progress, executor).run()
            (tmp / "octree.json").write_text(json.dumps(meta, indent=1))
        return cls.open(out_dir)


@dataclasses.dataclass(frozen=True)
class OctreeRange:
    """Points ``[start, stop)`` of an octree's levels taken in order (coarsest first), as a
    re-readable, picklable chunk source: calling it yields dicts as :meth:`Octree.read_level`
    (``'positions'``: (n, 3) float32), in
    chunks of at most ``chunk_size`` that never span two levels; :meth:`split` cuts it into
    consecutive ranges that worker processes read on their own, :meth:`deal` into interleaved
    shares of its chunks."""

    path: str
    fields: dict
    level_counts: tuple
    start: int
    stop: int
    chunk_size: int = 1_000_000

    def __len__(self) -> int:
        return self.stop - self.start

    def _chunks(self) -> Iterator[tuple[int, int, int, int]]:
        """``(level, level's first point, start, stop)`` of each chunk, in order; ``start`` and
        ``stop`` count over all levels, as :attr:`start` and :attr:`stop` do."""
        first = 0
        for level, n in enumerate(self.level_counts):
            a, b = max(self.start, first), min(self.stop, first + n)
            for s in range(a, b, self.chunk_size):
                yield level, first, s, min(b, s + self.chunk_size)
            first += n

    def __call__(self) -> Iterator[dict]:
        for level, first, a, b in self._chunks():
            yield read_records(Path(self.path) / f"level_{level:02d}", self.fields, a - first, b - first)

    def deal(self, parts: int) -> list[list["OctreeRange"]]:
        """This range's chunks, each as a range of its own, dealt round-robin into at most
        ``parts`` shares (share ``p``: chunks ``p``, ``p + parts``, ...). Unlike :meth:`split`'s
        consecutive ranges, every share takes points from every level and every stretch of a
        level: the octree's order is spatial (a level's chunk is one region, the coarse levels
        hold the sparse regions' points, whose splats are larger), so consecutive halves can
        cost a GPU very different times (on llvmpipe, 6.1 against 2.0 s for the halves of the
        tiny scene's points in its 12 depth maps; 2.7 against 3.0 s dealt in chunks of 1000)."""
        pieces = [dataclasses.replace(self, start=a, stop=b) for _, _, a, b in self._chunks()]
        parts = max(1, min(int(parts), len(pieces)))
        return [pieces[p::parts] for p in range(parts)]

    def split(self, parts: int) -> list["OctreeRange"]:
        """At most ``parts`` consecutive ranges covering this one, in order."""
        parts = max(1, min(int(parts), len(self)))
        cuts = [self.start + len(self) * i // parts for i in range(parts + 1)]
        return [dataclasses.replace(self, start=a, stop=b) for a, b in zip(cuts, cuts[1:]) if b > a]


COUNT_CELLS = 1 << 22  # the counting table's most cells (_Builder._plan_memory)


class _Builder:
    """The build passes of :meth:`Octree.build` (see the module docstring)."""

    def __init__(self, src, tmp: Path, config: OctreeConfig, bbox, progress, executor=None):
        self.src = src
        self.tmp = tmp
        self.config = config
        self.bbox = bbox
        self.progress = progress
        self.budget = int(config.memory_limit_mb * 2 ** 20)
        # the bucket passes run as tasks of a distributed executor, else here (the serial path)
        self.executor = executor if executor is not None and executor.distributed else None
        self.workers = max(1, int(self.executor.workers)) if self.executor is not None else 1
        # the passes that read the input run as tasks, one per part, when the source splits
        # into several (consecutive ranges of the input: PointRange, OctreeRange), else here
        self.parts = split_input(src, self.executor)
        self.buckets = None
        self.timings = {}

    # -- budget split -----------------------------------------------------------------------------
    def _plan_memory(self):
        rb = field_bytes(self.schema)  # bytes a record: 12 of float32 positions + the attributes'
        # the input passes read the K = len(self.parts) parts at once (K <= W), so each part gets
        # 1/K of the budget of the tables, buffers and slices below (serially K = 1: all of it)
        k = len(self.parts)
        # counting table: int64 keys + int64 counts (16 B/cell); merging it with a slice's cells
        # takes ~6 temporaries of that size, so 96 B/cell at the peak: cap it at ~3/8 of the budget
        # (count_cap: the whole table, merged here from the parts'; part_count_cap: one part's).
        # At most COUNT_CELLS cells: the table only chooses the bucket level and cuts the buckets,
        # for which 4M cells (~170 points each at 683M points) are plenty, while merging the parts'
        # tables here costs time linear in their size (a 16 GB budget allowed 65M cells: 6.9 of the
        # octree's 11.7 s on 32M points and 16 cores went into counting). Before a merge the count
        # pass keeps up to max(a slice, the table) of waiting keys (buckets.count_cells): 8 B a point
        # of a slice beside its ~4 * rb + 64 of work arrays, or 8 B a cell beside the table's 96
        # (within the margins of both plans)
        self.count_cap = max(4096, min(self.budget // 256, COUNT_CELLS))
        self.part_count_cap = max(4096, self.count_cap // k)
        # spill buffers: a quarter of the budget
        self.buffer_bytes = max(1 << 16, self.budget // k // 4)
        # one bucket in memory per worker: its records, a copy while writing levels, and ~100
        # bytes/point of work arrays (int64 coordinates 24, keys 8, distances 8, lexsort 16, float
        # temporaries 48: the float64 upcasts of the float32 positions in the distance and cell
        # arithmetic); W workers hold W buckets at once, so each gets 0.4 M / W. Measured
        # (tracemalloc, _select_in_memory of 200k points with an int64 attribute, rb = 20): 117
        # bytes/point beside the loaded records, of the rb + 112 = 132 planned
        self.capacity = max(1024, int(self.budget / self.workers * 0.4 / (2 * rb + 112)))
        # input chunks are sliced so the per-slice work arrays (~ 4 * rb + 64 bytes/point) stay
        # within an eighth of the budget
        self.slice_points = max(1024, int(self.budget / k / 8 / (4 * rb + 64)))

    # -- passes ------------------------------------------------------------------------------------
    def run(self) -> dict:
        t0 = time.perf_counter()
        cfg = self.config
        # schema from the first chunk
        first = first_chunk(self.src)
        if first is None:
            raise ValueError("the point source yielded no chunks")
        pos0, attrs0 = normalize_chunk(first, "chunk 0", dtype=None)
        self.schema = {"positions": (POSITIONS_DTYPE, (3,))}
        self.schema.update({k: (str(v.dtype), tuple(v.shape[1:])) for k, v in attrs0.items()})
        del first, pos0, attrs0
        self._plan_memory()

        self.n_total = None
        if self.bbox is None:
            lo, hi, self.n_total = input_bbox(self.parts, self.executor, POSITIONS_DTYPE, "octree: bbox",
                                              self.progress)
        else:
            # the given box rounded to float32 as the points are: rounding is monotonic, so every
            # point inside the given box stays inside the rounded one (none is counted outside
            # because rounding moved it across a face), and the exact box of the input gives the
            # box the bbox pass would find (min of the rounded points = rounded min), so the same
            # octree as without a bbox
            lo, hi = (np.asarray(b, np.float64).reshape(3).astype(POSITIONS_DTYPE).astype(np.float64)
                      for b in self.bbox)
            if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
                raise ValueError(f"bbox {self.bbox} is not finite (or beyond float32's range)")
            self.bbox = (lo, hi)
        self.timings["bbox_s"] = time.perf_counter() - t0
        extent = np.maximum(hi - lo, 0.0)
        diag = float(np.linalg.norm(extent))
        root = float(cfg.root_cell) if cfg.root_cell else (diag / 64.0 if diag > 0 else 1.0)
        n_grid = cfg.levels - 1
        dims0 = max(1, int(np.ceil(np.max(extent) / root)))
        bits0 = max(1, int(math.ceil(math.log2(dims0))) if dims0 > 1 else 1)
        if n_grid > 0 and bits0 + n_grid - 1 > MAX_BITS_PER_AXIS:
            raise ValueError(f"{cfg.levels} levels with root cell {root:g} m over a {np.max(extent):g} m "
                             f"box need {bits0 + n_grid - 1} bits per axis (max {MAX_BITS_PER_AXIS}): "
                             "use fewer levels or a larger root_cell")
        self.grid = _Grid(lo, root, n_grid, bits0)
        self.spill = self.tmp / "spill"
        self.spill.mkdir()

        if n_grid == 0:
            counts = self._copy_all()
        else:
            t = time.perf_counter()
            self._count()
            self.timings["count_s"] = time.perf_counter() - t
            t = time.perf_counter()
            self._make_buckets()
            self._distribute()
            self.timings["distribute_s"] = time.perf_counter() - t
            t = time.perf_counter()
            self._coarse_levels()
            self.timings["coarse_s"] = time.perf_counter() - t
            t = time.perf_counter()
            counts = self._fine_levels()
            self.timings["select_s"] = time.perf_counter() - t
        shutil.rmtree(self.spill)
        self.timings["total_s"] = time.perf_counter() - t0
        if self.n_total is not None and sum(counts) != self.n_total:
            raise RuntimeError(f"the point source yielded {sum(counts)} points, the bbox pass {self.n_total}: "
                               "chunks_fn must yield the same points on every call")
        outside = getattr(self, "n_outside", 0)
        bucket_counts = [0] if self.buckets is None else self.buckets.counts
        return {
            "format": FORMAT,
            "version": VERSION,
            "config": dataclasses.asdict(cfg),
            "root_cell": root,
            "bbox": [lo.tolist(), hi.tolist()],
            "level_counts": [int(c) for c in counts],
            "n_points": int(sum(counts)),
            "fields": {k: {"dtype": dt, "shape": list(s)} for k, (dt, s) in self.schema.items()},
            "bucket_level": int(getattr(self, "c", 0)),
            "n_buckets": len(bucket_counts),
            "max_bucket_points": int(max(bucket_counts, default=0)),
            "bucket_capacity": int(self.capacity),
            "points_outside_bbox": int(outside),
            "workers": self.workers,
            "input_parts": len(self.parts),
            "timings": self.timings,
        }

    # pass: everything into level 0 when there are no grid levels
    def _copy_all(self):
        app = Appender(self.tmp / "level_00", self.schema)
        with progress_bar(self.n_total, "octree: copy", self.progress) as bar:
            for pos, attrs in iter_chunks(self.src, self.schema, self.slice_points, dtype=POSITIONS_DTYPE):
                app.write({"positions": pos, **attrs})
                bar.update(len(pos))
        app.close()
        return [app.count]

    # pass: sparse counts at the finest affordable level
    def _count(self):
        g = self.grid
        bbox = (g.origin, np.asarray(self.bbox[1], np.float64)) if self.bbox is not None else None
        # The serial pass (one part, cap = count_cap) ends at the finest level whose table of *all*
        # the points fits count_cap (0 if none does), L* say (dmrt.preprocess.buckets: a pure
        # function of the point set). Each part's table is coarsened against count_cap / K here
        # (its share of the memory), then the tables are added and coarsened while over
        # count_cap: each merged table is the table of a subset of the points, so this never
        # coarsens past L*. The result is the serial table when every part stopped at L* or finer,
        # i.e. when no part alone has more than count_cap / K cells at L*. A part that has (not
        # rare: in bench_octree's 4M points, each half alone has over half of the 722k level-4
        # cells, so 2 parts stop at level 3) leaves the table coarser than L*: the serial table
        # coarsened. That changes the bucket level c only where no level up to the table's has
        # every cell within a bucket's capacity (c is then the table's level, and more buckets are
        # over-full); the level files do not depend on the buckets, so they are the same bytes
        # either way. Shifts are doublings coarser than the finest level, no coarser than level 0.
        counts, part_n, n_out = count_input(
            self.parts, self.executor, g, self.count_cap, self.slice_points, part_cap=self.part_count_cap,
            max_shift=g.finest, desc="octree: count", progress=self.progress, total=self.n_total,
            schema=self.schema, dtype=POSITIONS_DTYPE, bbox=bbox)
        n = sum(part_n)
        if self.n_total is not None and n != self.n_total:
            raise RuntimeError(f"chunks_fn yielded {n} points now and {self.n_total} before: "
                               "it must yield the same points on every call")
        self.n_total = n
        # clipped into the boundary cells; harmless but reported. Counted on the rounded points
        # against the rounded box: a point inside the given box never counts, and one outside it
        # by less than float32's resolution there may round onto the box and not count either
        self.n_outside = n_out
        # bucket level: the coarsest level whose every cell fits one bucket
        level, keys, cnts = g.finest - counts.shift, counts.keys, counts.counts
        c, ck, cc = level, keys, cnts
        for lvl in range(0, level + 1):
            k2, c2 = coarsen(keys, cnts, level - lvl)
            if c2.max() <= self.capacity:
                c, ck, cc = lvl, k2, c2
                break
        self.c, self.cell_keys, self.cell_counts = c, ck, cc

    def _make_buckets(self):
        self.buckets = Buckets.cut(self.grid, self.grid.finest - self.c, self.cell_keys, self.cell_counts,
                                   self.capacity)
        del self.cell_keys, self.cell_counts
        self.bucket_offsets = np.r_[0, np.cumsum(self.buckets.counts)]
        spill = Spill(str(self.spill.resolve()), self.schema, len(self.parts))
        self.work = _BucketWork(spill, self.grid, self.c, self.capacity)
        self.work.spill.create(len(self.buckets))

    # pass: points -> per-bucket spill files, one folder per bucket and part
    def _distribute(self):
        got = np.zeros(len(self.buckets), np.int64)
        for _, written in input_pass(distribute, self.parts, self.executor, "octree: distribute", self.progress,
                                     self.n_total, buckets=self.buckets, spill=self.work.spill,
                                     slice_points=self.slice_points, buffer_bytes=self.buffer_bytes,
                                     schema=self.schema, dtype=POSITIONS_DTYPE):
            got += written
        for b in np.flatnonzero(got != self.buckets.counts)[:1]:
            raise RuntimeError(f"bucket {b} received {got[b]} points, counted {self.buckets.counts[b]}: "
                               "chunks_fn must yield the same points on every call")
    # pass: candidates for levels 0..c-1, resolved exactly in memory
    def _coarse_levels(self):
        c, nb = self.c, len(self.buckets)
        self.coarse_picks = [np.zeros(0, np.int64) for _ in range(nb)]  # local indices per bucket
        self.level_apps = [Appender(self.tmp / f"level_{lvl:02d}", self.schema) for lvl in range(self.config.levels)]
        if c == 0:
            return
        cand = [[] for _ in range(c)]  # per level: one dict (uid, key, d2, record fields) per bucket
        items = [(b, int(self.buckets.counts[b]), int(self.bucket_offsets[b])) for b in range(nb)]
        for per_level in self._tasks(_bucket_candidates, items, "octree: coarse levels"):
            for lvl in range(c):
                cand[lvl].append(per_level[lvl])
        picked = np.zeros(0, np.int64)
        for lvl in range(c):
            allc = {k: np.concatenate([p[k] for p in cand[lvl]]) for k in cand[lvl][0]}
            cand[lvl] = None
            free = ~in_sorted(allc["uid"], picked)
            allc = take(allc, free)
            t = _top_m(allc["key"], allc["d2"], allc["positions"], 1)
            best = take(allc, t)
            self.level_apps[lvl].write({k: best[k] for k in self.schema})
            picked = np.sort(np.concatenate([picked, best["uid"]]))  # disjoint: free only
        bid = np.searchsorted(self.bucket_offsets, picked, side="right") - 1
        for b in unique_counts(bid)[0]:
            self.coarse_picks[b] = np.sort(picked[bid == b] - self.bucket_offsets[b])

    # pass: levels c..levels-2 and the remainder, bucket by bucket
    def _fine_levels(self):
        nb = len(self.buckets)
        items = [(b, int(self.buckets.counts[b]), self.coarse_picks[b]) for b in range(nb)]
        self.coarse_picks = None
        if self.executor is None:
            with progress_bar(self.n_total, "octree: select", self.progress) as bar:
                for b, n, coarse_local in items:
                    self.work.select(b, n, coarse_local, self.level_apps)
                    self.work.spill.remove(b)
                    bar.update(n)
        else:
            # each task writes its bucket's levels to out/b<bucket>/level_XX and removes the
            # bucket's spill folder; here they are appended in bucket order (the serial bytes) and
            # removed, while the next buckets are selected
            out = self.tmp / "select"
            out.mkdir()
            results = self.executor.imap(_select_bucket, items, desc="octree: select", progress=self.progress,
                                         work=self.work, out=str(out.resolve()))
            for (b, _, _), counts in zip(items, results):
                folder = out / f"b{b:06d}"
                for lvl, (app, m) in enumerate(zip(self.level_apps, counts)):
                    app.append_files(folder / f"level_{lvl:02d}", m)
                shutil.rmtree(folder, ignore_errors=True)
            shutil.rmtree(out, ignore_errors=True)
        for app in self.level_apps:
            app.close()
        return [app.count for app in self.level_apps]

    def _tasks(self, fn, items, desc):
        """``fn(item, work=self.work)`` per item, results in item order: as tasks of the executor
        when it is distributed, else here (a bar over the points, ``item[1]``)."""
        if self.executor is not None:
            yield from self.executor.imap(fn, items, desc=desc, progress=self.progress, work=self.work)
            return
        with progress_bar(self.n_total, desc, self.progress) as bar:
            for item in items:
                yield fn(item, work=self.work)
                bar.update(item[1])


# ---------------------------------------------------------------------------------------------
# per-bucket work (in this process, or as tasks in worker processes)
# ---------------------------------------------------------------------------------------------
@dataclass
class _BucketWork:
    """The candidates and select work of one bucket at a time. Picklable: tasks in worker
    processes get a copy and read the bucket's spill files (whose root is an absolute path that
    the workers see)."""

    spill: Spill
    grid: _Grid
    c: int  # bucket level
    capacity: int  # points of one bucket in memory

    @property
    def schema(self) -> dict:
        return self.spill.schema

    def chunks(self, b: int, n: int, schema=None):
        """Yield ``(local_start, record)`` for bucket ``b`` (``n`` points) in slices within the
        capacity (all fields, or those of ``schema``)."""
        step = n if n <= self.capacity else max(1024, self.capacity // 2)
        for s in range(0, n, step):
            yield s, self.spill.read(b, s, min(n, s + step), schema)

    def candidates(self, b: int, n: int, offset: int) -> list[dict]:
        """Per level ``l < c``: the ``l + 1`` best points of every level-``l`` cell in bucket ``b``
        (``uid`` = ``offset`` + index in the bucket, ``key``, ``d2`` and the record fields)."""
        g, c = self.grid, self.c
        running = [None] * c
        for s, rec in self.chunks(b, n):
            pos = rec["positions"]
            q = g.coords(pos)
            uid = offset + s + np.arange(len(pos), dtype=np.int64)
            for lvl in range(c):
                keys, d2 = g.keys_and_d2(pos, q, lvl)
                part = {"uid": uid, "key": keys, "d2": d2, **rec}
                if running[lvl] is not None:
                    part = {k: np.concatenate([running[lvl][k], part[k]]) for k in part}
                t = _top_m(part["key"], part["d2"], part["positions"], lvl + 1)
                running[lvl] = take(part, t)
        return running

    def select(self, b: int, n: int, coarse_local, writers):
        """Levels ``c ..`` and the remainder of bucket ``b`` (``n`` points, minus the local indices
        ``coarse_local`` taken by coarse levels), appended to ``writers[level]`` in Morton order."""
        if n <= self.capacity:
            self._select_in_memory(self.spill.read(b), coarse_local, writers)
        else:
            self._select_streaming(b, n, coarse_local, writers)

    def _select_in_memory(self, rec, coarse_local, writers):
        """One stable sort by the finest Morton key, after which the cells of every coarser level
        are contiguous runs too (their keys are prefixes). The work arrays are 1-D columns in that
        order (float32 positions, int32 cell coordinates, the records' indices), selected block
        by block (:meth:`_select_block`). The records themselves stay in input order and each
        level's picks are gathered from them once: every record moves once in all, where
        permuting them up front moved each twice."""
        g, c = self.grid, self.c
        pos = rec["positions"]
        base = None
        if len(coarse_local):
            keep = np.ones(len(pos), bool)
            keep[coarse_local] = False
            base = np.flatnonzero(keep)
            del keep
            pos = np.take(pos, base, axis=0)
        qc = g.coord_columns(pos)
        o, kf = _stable_order(morton_columns(qc))  # stable: exact duplicates keep their input order
        qc = [np.take(a, o) for a in qc]
        pos = np.take(pos, o, axis=0)
        cols = [np.ascontiguousarray(pos[:, j]) for j in range(3)]
        idx = o if base is None else np.take(base, o)  # the work arrays' records
        del pos, base, o
        picks = [[] for _ in writers]  # per level: the picks' records, block after block
        # a level-l run starts where consecutive keys differ at bit 3 * (finest - l) or above
        cuts = _block_cuts(kf[1:] ^ kf[:-1] >= 1 << 3 * (g.finest - c), SELECT_BLOCK)
        for a, e in zip(cuts[:-1], cuts[1:]):
            self._select_block(kf[a:e], [x[a:e] for x in cols], [x[a:e] for x in qc], idx[a:e], picks)
        for w, p in zip(writers, picks):
            if p:
                w.write(_gather(rec, np.concatenate(p)))

    def _select_block(self, kf, cols, qc, idx, picks):
        """Levels ``c ..`` and the remainder of one block of whole level-``c`` cells (work arrays in
        Morton order, ``kf`` their finest keys), their records appended to ``picks``.
        Level-``l >= c`` cells never cross a level-``c`` cell, so blocks are independent, and the
        picks of block after block are in Morton order; a block of ``SELECT_BLOCK`` points keeps
        the work arrays and every level's temporaries in the core's cache."""
        g = self.grid
        dk = kf[1:] ^ kf[:-1]
        # points taken since the work arrays were last compacted: the coarse levels take few
        # points, so compacting after each would copy nearly all the arrays for nothing
        taken = np.zeros(0, np.int64)
        for lvl in range(self.c, g.n_grid):
            if len(idx) == len(taken):
                return
            shift = g.finest - lvl
            runs = _Runs.from_breaks(dk >= 1 << 3 * shift)
            d2 = g.d2_runs(cols, qc, runs, shift, lvl)
            d2[taken] = np.inf
            best = _best_of_runs(runs, d2, cols)
            del d2, runs
            picks[lvl].append(np.take(idx, best))
            taken = np.concatenate([taken, best])
            if len(taken) > len(idx) // 4:
                mask = np.ones(len(idx), bool)
                mask[taken] = False
                idx, kf = idx[mask], kf[mask]
                dk = kf[1:] ^ kf[:-1]
                cols = [a[mask] for a in cols]
                qc = [a[mask] for a in qc]
                taken = taken[:0]
        picks[-1].append(np.delete(idx, taken) if len(taken) else idx)  # the remainder, in Morton order

    def _select_streaming(self, b, n, coarse_local, writers):
        """Levels of an over-full bucket by per-level running reductions over its spill file; the
        output is what :meth:`_select_in_memory` would write (so it does not depend on which
        buckets are over-full, i.e. on the memory limit or the number of workers)."""
        g = self.grid
        assigned = np.full(n, -1, np.int8)  # -1: free, -2: a coarse level's, else the level
        assigned[coarse_local] = -2
        for lvl in range(self.c, g.n_grid):
            running = None
            for s, rec in self.chunks(b, n):
                free = np.flatnonzero(assigned[s:s + len(rec["positions"])] == -1)
                if len(free) == 0:
                    continue
                part = take(rec, free)
                part["key"], part["d2"] = g.keys_and_d2(part["positions"], g.coords(part["positions"]), lvl)
                part["idx"] = free + s
                if running is not None:
                    part = {k: np.concatenate([running[k], part[k]]) for k in part}
                running = take(part, _best_per_cell(part["key"], part["d2"], part["positions"]))
            if running is None:
                return  # no point left
            assigned[running["idx"]] = lvl
            writers[lvl].write(running)  # one point per cell, in Morton order of the cells
        self._remainder_streaming(b, n, assigned, writers[-1])

    def _remainder_streaming(self, b, n, assigned, writer):
        """The free points (``assigned == -1``) of an over-full bucket in the order of a stable sort
        by the finest key: the finest cells are cut into runs of whole cells of at most half the
        capacity (a cell above that alone forms a run), each run spilled to its own files in input
        order, then sorted alone (a one-cell run is in order already and is copied as it is)."""
        g = self.grid
        pos_only = {"positions": self.schema["positions"]}
        keys, cnts = np.zeros(0, np.int64), np.zeros(0, np.int64)
        for s, rec in self.chunks(b, n, pos_only):
            p = rec["positions"][assigned[s:s + len(rec["positions"])] == -1]
            keys, cnts = merge_counts(keys, cnts, *unique_counts(morton_encode(g.coords(p))))
        if len(keys) == 0:
            return
        run_cap = max(1024, self.capacity // 2)
        first, sizes = [], []
        for i, m in enumerate(cnts.tolist()):
            if not first or sizes[-1] + m > run_cap:
                first.append(i)
                sizes.append(0)
            sizes[-1] += m
        one_cell = np.diff(np.r_[first, len(keys)]) == 1
        run_keys = keys[first]
        del keys, cnts
        folder = self.spill.folder(b) / "remainder"
        runs = [Appender(folder / f"r{r:06d}", self.schema) for r in range(len(first))]
        for s, rec in self.chunks(b, n):
            sub = take(rec, np.flatnonzero(assigned[s:s + len(rec["positions"])] == -1))
            if len(sub["positions"]) == 0:
                continue  # a slice the levels took whole: no run to cut
            run = np.searchsorted(run_keys, morton_encode(g.coords(sub["positions"])), side="right") - 1
            o = np.argsort(run, kind="stable")
            run = run[o]
            sub = take(sub, o)
            cuts = np.flatnonzero(np.r_[True, run[1:] != run[:-1], True])
            for a, e in zip(cuts[:-1], cuts[1:]):
                runs[run[a]].write({k: v[a:e] for k, v in sub.items()})
                runs[run[a]].close()  # never hold many handles
        for r, app in enumerate(runs):
            if one_cell[r]:
                writer.append_files(app.dir, app.count)
            else:
                rec = read_records(app.dir, self.schema)
                kf = morton_encode(g.coords(rec["positions"]))
                writer.write(_gather(rec, _stable_order(kf)[0]))
                del rec, kf
            shutil.rmtree(app.dir, ignore_errors=True)


def _bucket_candidates(item, work: _BucketWork) -> list[dict]:
    """Task: :meth:`_BucketWork.candidates` of ``item = (bucket, points, uid offset)``."""
    b, n, offset = item
    return work.candidates(b, n, offset)


def _select_bucket(item, work: _BucketWork, out: str) -> list[int]:
    """Task: :meth:`_BucketWork.select` of ``item = (bucket, points, coarse picks)`` into
    ``out/b<bucket>/level_XX/``; removes the bucket's spill folder. Returns the points per level."""
    b, n, coarse_local = item
    folder = Path(out) / f"b{b:06d}"
    folder.mkdir(exist_ok=True)  # not its parents: a build that failed meanwhile removed them
    writers = [Appender(folder / f"level_{lvl:02d}", work.schema) for lvl in range(work.grid.n_grid + 1)]
    try:
        work.select(b, n, coarse_local, writers)
    finally:
        for w in writers:
            w.close()
    work.spill.remove(b)
    return [w.count for w in writers]
