"""Out-of-core buckets: the input read in parts, sparse point counts per grid cell, and the points
cut into spatial buckets, each written to its own spill files, with or without a halo.

Both out-of-core builders use it: the octree (:mod:`dmrt.preprocess.octree`; buckets of whole
cells of one level, no halos) and the normals and radii (:mod:`dmrt.preprocess.normals`; buckets
with halos, so every point's neighbourhood is complete in its bucket).

Input
-----
A *chunk source* is a callable returning a fresh iterator of chunks: ``(positions (n, 3),
{name: (n, ...) array})``, a dict with ``'positions'``, or a ``PointCloud`` (:func:`iter_chunks`
normalizes them). The passes that read the input run over its *parts* (:func:`split_input`,
:func:`input_pass`): the whole source in this process, or, with a distributed executor and a
source that *splits* (a picklable callable whose ``split(parts)`` returns at most ``parts``
consecutive sub-sources that together yield the same points in the same order, e.g.
:class:`~dmrt.io.pointcloud.PointRange`, :class:`~dmrt.preprocess.octree.OctreeRange`), one task
per part in worker processes. Results come back in part order, so what the parts write and is
read back part after part is in input order: the serial pass's bytes.

Counts
------
A *grid* is any object whose ``coords(pos)`` gives (n, 3) int64 cell coordinates on a fine grid
(:class:`FineGrid`, the octree's grid of levels); one that also has ``coord_columns(pos)`` (the
same coordinates as three (n,) int32 columns, as the octree's has) is read through those, which
is faster. Coarser cells are those coordinates shifted right (``shift`` doublings), never a second
``floor()``, so every pass puts a point in exactly the same cell. :class:`CellCounts` is a sparse
table of points per cell (sorted int64 Morton keys and counts), coarsened one doubling at a time
while it holds more than ``cap`` cells. It coarsens past
a shift ``s`` only when the table of the points added so far, hence that of all points, exceeds the
cap at ``s``, and it ends with the table of all points within the cap: so it ends at the finest
shift whose table of all points fits, a pure function of the point set, whatever the order and
the parts in which the points come (each part given the whole cap) and the order in which the
parts' tables are added.

Buckets
-------
:meth:`Buckets.cut` cuts the Morton-sorted occupied cells of one grid level into runs of
consecutive cells within a capacity: bucket ``b`` holds the cells whose keys lie in ``[starts[b],
starts[b + 1])``. :func:`distribute` streams one part's points into their buckets' spill files
(:class:`~dmrt.preprocess.spill.Spill`), in input order. With a ``margin`` (halos, on a grid whose
cells are wider than ``2 * margin``) each point also goes to every other bucket that has an
occupied cell overlapped by the point's margin box ``[p - margin, p + margin]``, so a bucket with
its halo holds every point within ``margin`` (per axis) of its own cells.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from typing import Callable, Iterable, Iterator, NamedTuple

import numpy as np

from dmrt.io.pointcloud import extent
from dmrt.morton import morton_encode
from dmrt.preprocess.spill import Spill

try:  # progress bars are optional
    from tqdm.auto import tqdm as _tqdm
except ImportError:  # pragma: no cover
    _tqdm = None

__all__ = ["progress_bar", "chunk_source", "normalize_chunk", "iter_chunks", "first_chunk", "positions_dtype",
           "InputPart", "split_input", "input_pass", "bbox_part", "input_bbox", "compute_bbox",
           "morton_columns", "cell_columns", "cell_keys", "unique_counts", "in_sorted", "merge_counts", "coarsen",
           "CellCounts", "count_cells", "count_input",
           "FineGrid", "Buckets", "halo_schema", "distribute"]


def progress_bar(total, desc: str, enabled: bool, unit: str = "pt"):
    """A tqdm bar over points, or another ``unit`` (a do-nothing one when disabled or without tqdm);
    a context manager."""
    if not enabled or _tqdm is None:
        return _NullBar()
    return _tqdm(total=total, desc=desc, unit=unit, unit_scale=unit == "pt", leave=False)


class _NullBar:
    def update(self, n=1):
        pass

    def close(self):
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False


# ---------------------------------------------------------------------------------------------
# reading the input
# ---------------------------------------------------------------------------------------------
def normalize_chunk(item, where="chunk", dtype=np.float64) -> tuple[np.ndarray, dict]:
    """Accept ``(positions, attrs)``, a dict with ``'positions'``, or an object with ``.positions``
    (e.g. ``dmrt.io.pointcloud.PointCloud``; attributes that are ``None`` are skipped).

    Returns ``(positions (n, 3), {name: (n, ...) array})``; positions contiguous of ``dtype``, or
    as given (only reshaped) for ``dtype=None``."""
    if isinstance(item, (tuple, list)) and len(item) == 2:
        pos, attrs = item
        attrs = dict(attrs or {})
    elif isinstance(item, dict):
        attrs = dict(item)
        pos = attrs.pop("positions")
    elif hasattr(item, "positions"):
        pos = item.positions
        if dataclasses.is_dataclass(item):
            names = [f.name for f in dataclasses.fields(item) if f.name != "positions"]
        else:
            names = [n for n in ("normals", "colors", "radii") if hasattr(item, n)]
        attrs = {n: getattr(item, n) for n in names}
    else:
        raise TypeError(f"{where}: expected (positions, attributes), a dict or a PointCloud, "
                        f"got {type(item).__name__}")
    pos = np.asarray(pos).reshape(-1, 3)
    if dtype is not None:
        pos = np.ascontiguousarray(pos, dtype=dtype)
    out = {}
    for name, a in attrs.items():
        if a is None or not isinstance(a, np.ndarray) and not isinstance(a, (list, tuple)):
            continue
        a = np.ascontiguousarray(np.asarray(a))
        if a.ndim == 0 or a.shape[0] != len(pos):
            raise ValueError(f"{where}: attribute {name!r} has {a.shape[0] if a.ndim else 0} rows "
                             f"for {len(pos)} positions")
        out[name] = a
    return pos, out


def chunk_source(chunks_fn) -> Callable[[], Iterator]:
    """``chunks_fn`` as a callable returning a fresh iterator of chunks (a re-iterable such as a
    list is wrapped; a one-shot iterator is refused: the passes read the input several times)."""
    if callable(chunks_fn):
        return chunks_fn
    if isinstance(chunks_fn, Iterator):
        raise TypeError("the out-of-core passes read their input several times: pass a callable that "
                        "returns a fresh iterator of chunks (or a re-iterable such as a list)")
    if isinstance(chunks_fn, Iterable):
        return lambda: iter(chunks_fn)
    raise TypeError(f"chunks_fn must be callable, got {type(chunks_fn).__name__}")


def first_chunk(src):
    """The first chunk of the source (None without any); the rest is not read."""
    it = iter(src())
    first = next(it, None)
    if hasattr(it, "close"):
        it.close()
    return first


def positions_dtype(src) -> str:
    """``"float32"`` when the source's first chunk holds float32 positions (an octree's), which a
    spill then keeps exactly in 12 bytes a point instead of 24; else ``"float64"``."""
    first = first_chunk(src)
    if isinstance(first, (tuple, list)):
        pos = first[0]
    else:
        pos = first["positions"] if isinstance(first, dict) else getattr(first, "positions", None)
    return "float32" if np.asarray(pos).dtype == np.float32 else "float64"


def iter_chunks(src, schema=None, max_points=None, where="", dtype=np.float64):
    """Yield ``(positions (n, 3) dtype, attrs)`` from the source, checking the attribute schema
    (``{name: (dtype str, per-point shape)}``, as the first chunk's), and split into slices of at
    most ``max_points`` so working arrays stay bounded. ``where`` prefixes the chunk in error
    messages (e.g. ``"input part 2 of 4, "``: chunks are counted from the part's start). The
    positions are converted to ``dtype`` slice by slice (the octree's passes: rounded to float32),
    so a conversion copy never holds more than one slice."""
    want = None if schema is None else {k: (str(dt), list(s)) for k, (dt, s) in schema.items() if k != "positions"}
    for i, item in enumerate(src()):
        pos, attrs = normalize_chunk(item, where=f"{where}chunk {i}", dtype=None)
        if want is not None:
            got = {k: (str(v.dtype), list(v.shape[1:])) for k, v in attrs.items()}
            if got != want:
                raise ValueError(f"{where}chunk {i}: attributes {got} differ from the first chunk's {want}")
        n = len(pos)
        if n == 0:
            continue
        step = n if not max_points else max(1, int(max_points))
        for s in range(0, n, step):
            yield np.ascontiguousarray(pos[s:s + step], dtype=dtype), {k: v[s:s + step] for k, v in attrs.items()}


class InputPart(NamedTuple):
    """Part ``index`` of ``parts`` consecutive parts of the input, with its chunk source."""

    index: int
    parts: int
    source: Callable

    @property
    def where(self) -> str:
        """The prefix of this part's errors (empty for a whole input)."""
        return f"input part {self.index + 1} of {self.parts}, " if self.parts > 1 else ""


def split_input(src, executor=None) -> list[InputPart]:
    """The parts the input passes run on: one per sub-source of ``src.split(executor.workers)``
    when the executor is distributed and the source splits into several, else the whole source."""
    sources = [src]
    if executor is not None and executor.distributed and callable(getattr(src, "split", None)):
        sources = list(src.split(max(1, int(executor.workers))))
        if len(sources) <= 1:
            sources = [src]
    return [InputPart(i, len(sources), s) for i, s in enumerate(sources)]


def input_pass(fn, parts: list[InputPart], executor, desc: str, progress: bool = False, total=None,
               **shared) -> Iterator:
    """``fn(part, **shared)`` per part, results in part order: as tasks of ``executor`` when there
    are several parts, else here on the whole source (with a bar over ``total`` points, passed to
    ``fn`` as ``bar``). ``fn`` and ``shared`` must be picklable for worker processes."""
    if len(parts) > 1:
        yield from executor.imap(fn, parts, desc=desc, progress=progress, **shared)
        return
    with progress_bar(total, desc, progress) as bar:
        yield fn(parts[0], bar=bar, **shared)


def bbox_part(part: InputPart, dtype=np.float64, bar=None) -> tuple[np.ndarray, np.ndarray, int]:
    """Bounding box of one part's positions converted to ``dtype``: ``(min (3,) float64, max (3,)
    float64, points)``; ``inf`` and ``-inf`` without points (the neutral elements of combining
    parts), NaN where a coordinate is (``inf`` too where rounding overflows float32's range)."""
    lo, hi, n = np.full(3, np.inf), np.full(3, -np.inf), 0
    for pos, _ in iter_chunks(part.source, where=part.where, dtype=dtype):
        lo = np.minimum(lo, pos.min(axis=0))
        hi = np.maximum(hi, pos.max(axis=0))
        n += len(pos)
        if bar is not None:
            bar.update(len(pos))
    return lo, hi, n


def input_bbox(parts: list[InputPart], executor=None, dtype=np.float64, desc: str = "bbox",
               progress: bool = False) -> tuple[np.ndarray, np.ndarray, int]:
    """One pass over the parts: ``(min (3,) float64, max (3,) float64, number of points)`` of the
    positions converted to ``dtype``; a ValueError without points or with non-finite ones."""
    lo, hi, n = np.full(3, np.inf), np.full(3, -np.inf), 0
    for lo_p, hi_p, n_p in input_pass(bbox_part, parts, executor, desc, progress, dtype=dtype):
        lo, hi, n = np.minimum(lo, lo_p), np.maximum(hi, hi_p), n + n_p
    if n == 0:
        raise ValueError("the point source yielded no points")
    if not (np.all(np.isfinite(lo)) and np.all(np.isfinite(hi))):
        raise ValueError("the point source contains non-finite coordinates")
    return lo, hi, n


def compute_bbox(chunks_fn, progress=False) -> tuple[np.ndarray, np.ndarray, int]:
    """One streaming pass: ``(min (3,) float64, max (3,) float64, number of points)`` of the
    positions as given (taken as float64)."""
    return input_bbox(split_input(chunk_source(chunks_fn)), progress=progress)


# ---------------------------------------------------------------------------------------------
# counts
# ---------------------------------------------------------------------------------------------
_SPREAD_BITS = 11
_SPREAD = morton_encode(np.c_[np.arange(1 << _SPREAD_BITS), np.zeros((1 << _SPREAD_BITS, 2), np.int64)])
"""Bit ``i`` of the index moved to bit ``3 i``: :func:`morton_encode` of 11 bits by a table lookup
(16 KB, cache-resident)."""


def morton_columns(qc) -> np.ndarray:
    """:func:`~dmrt.morton.morton_encode` of the cell coordinate columns ``qc`` (three (n,) int32 or
    int64, each in ``[0, 2**21)``): (n,) int64 keys, the same values, by two lookups in a table per
    axis instead of fifteen whole-array bit operations (measured 91 against 145 ms for 3M keys)."""
    key = None
    for j, q in enumerate(qc):
        lo = np.take(_SPREAD, q & ((1 << _SPREAD_BITS) - 1))
        hi = np.take(_SPREAD, q >> _SPREAD_BITS)
        hi <<= 3 * _SPREAD_BITS + j
        if j:
            lo <<= j
            key |= lo
        else:
            key = lo
        key |= hi
    return key


def cell_columns(grid, pos: np.ndarray, shift: int = 0) -> list:
    """The coordinates of the cells ``shift`` doublings coarser than ``grid``'s of the points
    ``pos`` (n, 3) as three (n,) integer columns: ``grid.coord_columns`` where the grid has it
    (int32), else the columns of ``grid.coords`` (int64)."""
    columns = getattr(grid, "coord_columns", None)
    if columns is None:
        q = grid.coords(pos) >> shift
        return [q[:, 0], q[:, 1], q[:, 2]]
    return [q >> shift for q in columns(pos)]


def cell_keys(grid, pos: np.ndarray, shift: int = 0) -> np.ndarray:
    """(n,) int64 Morton keys of the cells of :func:`cell_columns`."""
    return morton_columns(cell_columns(grid, pos, shift))


def unique_counts(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Sorted unique values and their counts, (m,) and (m,) int64 (sort-based: NumPy 2.4's
    hash-based ``np.unique`` is an order of magnitude slower on large int64 arrays)."""
    s = np.sort(a)
    if len(s) == 0:
        return s, np.zeros(0, np.int64)
    start = np.flatnonzero(np.r_[True, s[1:] != s[:-1]])
    return s[start], np.diff(np.r_[start, len(s)])


def in_sorted(a: np.ndarray, sorted_b: np.ndarray) -> np.ndarray:
    """Boolean mask: which elements of ``a`` occur in the sorted array ``sorted_b``."""
    if len(sorted_b) == 0:
        return np.zeros(len(a), bool)
    i = np.searchsorted(sorted_b, a)
    return sorted_b[np.minimum(i, len(sorted_b) - 1)] == a


def merge_counts(k1, c1, k2=None, c2=None) -> tuple[np.ndarray, np.ndarray]:
    """Merge sorted (key, count) tables (keys may repeat): sorted unique keys and summed counts.
    Two tables: the second's keys are looked up in the first (binary search of sorted keys), their
    counts added and the new keys inserted, which is linear in the first table (a sort of both
    took ~10x longer for a large table and a slice's keys)."""
    k1, c1 = _reduce_runs(k1, c1)
    if k2 is None:
        return k1, c1
    return _merge_unique(k1, c1, *_reduce_runs(k2, c2))


def _merge_unique(k1, c1, k2, c2) -> tuple[np.ndarray, np.ndarray]:
    """:func:`merge_counts` of two tables of unique sorted keys. The merged table is filled once
    through one mask of the new keys' places (two ``np.insert`` calls built that mask twice and
    copied the first table's counts a third time)."""
    i = np.searchsorted(k1, k2)
    hit = i < len(k1)
    hit[hit] = k1[i[hit]] == k2[hit]
    new = ~hit
    i_new = i[new]
    at = i_new + np.arange(len(i_new))  # a new key's place: its insertion point after those before it
    keep = np.ones(len(k1) + len(at), bool)
    keep[at] = False
    k = np.empty(len(keep), k1.dtype)
    k[keep] = k1
    k[at] = k2[new]
    c = np.empty(len(keep), c1.dtype)
    c[keep] = c1
    c[at] = c2[new]
    i_hit = i[hit]  # the second's keys are unique: no place repeats
    c[i_hit + np.searchsorted(i_new, i_hit, side="right")] += c2[hit]
    return k, c


def _reduce_runs(k, c):
    """A sorted (key, count) table with each run of equal keys summed into one entry."""
    if len(k) < 2:
        return k, c
    head = np.empty(len(k), bool)  # one comparison pass both tests and finds the runs
    head[0] = True
    np.not_equal(k[1:], k[:-1], out=head[1:])
    if head.all():
        return k, c
    start = np.flatnonzero(head)
    return k[start], np.add.reduceat(c, start)


def _shifted(keys: np.ndarray, doublings: int) -> np.ndarray:
    """Morton ``keys`` of cells ``doublings`` times coarser (still sorted, now with repeats)."""
    return keys >> (3 * doublings) if doublings else keys


def coarsen(keys: np.ndarray, counts: np.ndarray, doublings: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """A (key, count) table of cells ``doublings`` times coarser."""
    return merge_counts(_shifted(keys, doublings), counts)


@dataclass
class CellCounts:
    """Points per occupied cell of a grid ``shift`` doublings coarser than the fine grid, coarsened
    while over ``cap`` cells and below ``max_shift`` (see the module docstring).

    Attributes
    ----------
    keys : (m,) int64 sorted Morton keys of the occupied cells.  counts : (m,) int64.
    shift : int.
    """

    cap: int
    max_shift: int | None = None
    keys: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    counts: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    shift: int = 0

    def add(self, keys: np.ndarray, counts: np.ndarray, shift: int):
        """Add a table at ``shift``: both brought to the coarser shift, merged, then coarsened
        while over the cap."""
        s = max(self.shift, shift)
        # the table's keys are unique unless shifted: no pass over it to reduce runs
        k1, c1 = (self.keys, self.counts) if s == self.shift else coarsen(self.keys, self.counts, s - self.shift)
        k, c = _merge_unique(k1, c1, *merge_counts(_shifted(keys, s - shift), counts))
        top = self.max_shift if self.max_shift is not None else np.inf
        if len(k) > self.cap and s < top:
            # the cells d doublings coarser, counted on the adjacent keys' XOR (two sorted keys
            # differ there iff it has a bit at 3 * d or above), then one coarsening: a merged
            # table coarsened one doubling at a time took most of the count pass
            x = k[1:] ^ k[:-1]
            d = 1
            while 1 + np.count_nonzero(x >> (3 * d)) > self.cap and s + d < top:
                d += 1
            s += d
            k, c = coarsen(k, c, d)
        self.keys, self.counts, self.shift = k, c, s


def count_cells(part: InputPart, grid, cap: int, slice_points: int, *, schema=None, dtype=np.float64,
                max_shift=None, bbox=None, bar=None) -> tuple[CellCounts, int, int]:
    """One part's :class:`CellCounts` on ``grid`` within ``cap`` cells.

    Parameters
    ----------
    schema, dtype : as :func:`iter_chunks` (the attributes checked; the positions' type).
    bbox : ((3,), (3,)) float64, optional; points outside it are counted (``outside``).

    Returns
    -------
    counts : CellCounts.  points : int.  outside : int (0 without ``bbox``).
    """
    counts = CellCounts(cap, max_shift)
    n = n_out = 0
    # The slices' keys wait (8 bytes a point, at most a slice's or the table's worth) and are
    # counted and merged into the table together: merging costs time linear in the table, and a
    # table larger than a slice took most of this pass merged slice by slice. The table ends the
    # same whatever the batches (CellCounts: a function of the point set).
    waiting, n_waiting = [], 0
    for pos, _ in iter_chunks(part.source, schema, slice_points, part.where, dtype):
        # the columns' extremes (non-finite if any coordinate is: min and max keep NaN and inf)
        # spare the per-row test of the points in the box, which costs 5x more
        lo, hi = extent(pos)
        if not (np.isfinite(lo).all() and np.isfinite(hi).all()):
            beyond = " (or beyond float32's range)" if np.dtype(dtype) == np.float32 else ""
            raise ValueError(f"the point source contains non-finite coordinates{beyond}")
        if bbox is not None and not ((lo >= bbox[0]).all() and (hi <= bbox[1]).all()):
            n_out += int(np.count_nonzero(np.any((pos < bbox[0]) | (pos > bbox[1]), axis=1)))
        waiting.append(cell_keys(grid, pos, counts.shift))
        n_waiting += len(pos)
        if n_waiting >= max(slice_points, len(counts.keys)):
            counts.add(*unique_counts(np.concatenate(waiting)), counts.shift)
            waiting, n_waiting = [], 0
        n += len(pos)
        if bar is not None:
            bar.update(len(pos))
    if waiting:
        counts.add(*unique_counts(np.concatenate(waiting)), counts.shift)
    return counts, n, n_out


def count_input(parts: list[InputPart], executor, grid, cap: int, slice_points: int, *, part_cap=None,
                max_shift=None, desc: str = "count", progress: bool = False, total=None,
                **kw) -> tuple[CellCounts, list[int], int]:
    """:func:`count_cells` over the parts (each within ``part_cap``, default ``cap``), their tables
    added within ``cap``. Returns ``(counts, points of each part, points outside)``; ``kw``:
    ``schema``, ``dtype``, ``bbox`` as :func:`count_cells`."""
    out = CellCounts(cap, max_shift)
    part_n, n_out = [], 0
    for counts, n_p, out_p in input_pass(count_cells, parts, executor, desc, progress, total, grid=grid,
                                         cap=part_cap or cap, slice_points=slice_points, max_shift=max_shift,
                                         **kw):
        out.add(counts.keys, counts.counts, counts.shift)
        part_n.append(n_p)
        n_out += out_p
    return out, part_n, n_out


# ---------------------------------------------------------------------------------------------
# buckets
# ---------------------------------------------------------------------------------------------
@dataclass
class FineGrid:
    """``2**21`` cells of side ``cell`` per axis from ``lo`` (points beyond are clipped into the
    boundary cells)."""

    lo: np.ndarray  # (3,) float64
    cell: float

    def coords(self, p: np.ndarray) -> np.ndarray:
        """(m, 3) int64 cell coordinates of the points ``p`` (m, 3)."""
        q = np.floor((p - self.lo) / self.cell)
        np.clip(q, 0, (1 << 21) - 1, out=q)
        return q.astype(np.int64)


# the 8 corners of a margin box, as (low 0 / high 1) per axis
_CORNERS = np.array([[dx, dy, dz] for dx in (0, 1) for dy in (0, 1) for dz in (0, 1)], np.int64)


@dataclass
class Buckets:
    """Spatial buckets: runs of consecutive Morton cells of the grid ``shift`` doublings coarser
    than ``grid``'s coordinates (bucket ``b``: the cells of keys ``[starts[b], starts[b + 1])``).

    Attributes
    ----------
    grid : an object whose ``coords(pos)`` gives (n, 3) int64 fine-grid coordinates.
    shift : int.
    starts : (nb,) int64 sorted first key of each bucket.
    counts : (nb,) int64 points of each bucket's own cells.
    cells : (m,) int64 sorted keys of the occupied cells (for halos: only they draw copies), or None.
    """

    grid: object
    shift: int
    starts: np.ndarray
    counts: np.ndarray
    cells: np.ndarray | None = None

    @classmethod
    def cut(cls, grid, shift: int, keys: np.ndarray, counts: np.ndarray, capacity: int,
            halos: bool = False) -> "Buckets":
        """Cut the occupied cells (``keys`` sorted, ``counts`` points each) into runs of consecutive
        cells holding at most ``capacity`` points (a cell above it alone forms a bucket); with
        ``halos``, keep the cells for :meth:`with_halos`."""
        starts, sizes, acc = [], [], 0
        for key, cnt in zip(keys.tolist(), counts.tolist()):
            if not starts or acc + cnt > capacity:
                starts.append(key)
                sizes.append(0)
                acc = 0
            acc += cnt
            sizes[-1] += cnt
        return cls(grid, shift, np.asarray(starts, np.int64), np.asarray(sizes, np.int64), keys if halos else None)

    def __len__(self) -> int:
        return len(self.starts)

    def of_keys(self, keys: np.ndarray) -> np.ndarray:
        """(n,) int64 bucket of each cell key."""
        return np.searchsorted(self.starts, keys, side="right") - 1

    def of(self, pos: np.ndarray) -> np.ndarray:
        """(n,) int64 bucket of each point (n, 3)."""
        if len(pos) == 0:
            return np.zeros(0, np.int64)
        qc = cell_columns(self.grid, pos, self.shift)
        # Scans come in scan order, so runs of consecutive points share a bucket-grid cell: a
        # comparison of consecutive coordinates finds the runs, and only each run's cell is
        # Morton-encoded and looked up (the same buckets; on every point when the runs are short)
        head = np.empty(len(pos), bool)
        head[0] = True
        np.not_equal(qc[0][1:], qc[0][:-1], out=head[1:])
        for a in qc[1:]:
            head[1:] |= a[1:] != a[:-1]
        heads = np.flatnonzero(head)
        if len(heads) > len(pos) // 4:
            return self.of_keys(morton_columns(qc))
        return np.repeat(self.of_keys(morton_columns([a[heads] for a in qc])), np.diff(np.r_[heads, len(pos)]))

    def with_halos(self, pos: np.ndarray, margin: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Every (bucket, point) pair of the points' own buckets and halos: each point's own bucket,
        and every bucket with an occupied cell that the point's margin box ``[p - margin, p +
        margin]`` overlaps. The grid's cells must be wider than ``2 * margin``, so the box spans at
        most 2 cells per axis: its cells are the 8 combinations of its low and high corner cells.

        Returns
        -------
        bucket : (c,) int64, sorted.  index : (c,) int64 the point's row, sorted within a bucket.
        core : (c,) bool, whether it is the point's own bucket.
        """
        m = len(pos)
        own = self.of(pos)
        qlo = self.grid.coords(pos - margin) >> self.shift
        qhi = self.grid.coords(pos + margin) >> self.shift
        # (only occupied cells: a bucket's key range also spans empty cells, which must not draw
        # halos)
        bb, pi = [own], [np.arange(m)]  # the core copy, always
        for corner in _CORNERS:
            kk = morton_encode(np.where(corner, qhi, qlo))
            occ = np.flatnonzero(in_sorted(kk, self.cells))
            bb.append(self.of_keys(kk[occ]))
            pi.append(occ)
        bb, pi = np.concatenate(bb), np.concatenate(pi)
        pair, _ = unique_counts(bb * m + pi)  # one copy per (bucket, point), sorted by bucket, then point
        bb, ii = pair // m, pair % m
        return bb, ii, bb == own[ii]


def halo_schema(positions: str) -> dict:
    """Records of buckets with halos: a point's position (``positions`` dtype), its index in the
    input, and whether it is the bucket's own (1) or a halo copy (0)."""
    return {"positions": (positions, (3,)), "gidx": ("int64", ()), "core": ("uint8", ())}


def distribute(part: InputPart, buckets: Buckets, spill: Spill, slice_points: int, buffer_bytes: int, *,
               schema=None, dtype=np.float64, margin: float | None = None, firsts=None,
               bar=None) -> tuple[int, np.ndarray]:
    """Stream one part's points into its spill files of every bucket (``spill.part_folder(bucket,
    part.index)``), in input order, holding at most about ``buffer_bytes`` of records in buffers.

    Without ``margin``: each point with its attributes (``schema``, as :func:`iter_chunks`) to its
    own bucket. With ``margin``: records of :func:`halo_schema`, each point to its own bucket and
    its halos (:meth:`Buckets.with_halos`), ``gidx`` counted from ``firsts[part.index]`` (the
    global index of the part's first point).

    Returns
    -------
    points : int, read.  written : (nb,) int64, records written to each bucket.
    """
    writer = spill.writer(part.index, len(buckets), buffer_bytes)
    g = first = 0 if firsts is None else int(firsts[part.index])
    for pos, attrs in iter_chunks(part.source, schema, slice_points, part.where, dtype):
        if margin is None:
            writer.add(buckets.of(pos), {"positions": pos, **attrs})
        else:
            bucket, idx, core = buckets.with_halos(pos, margin)
            writer.add(bucket, {"positions": pos[idx], "gidx": g + idx, "core": core})
        g += len(pos)
        if bar is not None:
            bar.update(len(pos))
    return g - first, writer.close()
