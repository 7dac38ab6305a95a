"""Splat radii and normals from the scan's grid of beams, where each point's station and grid cell
are known (:mod:`dmrt.io.stations`): no nearest-neighbour search.

A terrestrial scanner samples each station's surroundings on an angular grid, so the gap between a
point and its neighbours on the surface is its range times the angular step, stretched where the
surface tilts away from the beam, and the surface's tangents are the differences to the neighbours
of its grid row and column (:func:`scan_phase` chooses this path: ``--radii auto|scan|knn``).

* **Radii** follow the kNN radii's convention (:func:`dmrt.preprocess.normals.radius_factor`): the
  disc that covers a cell of the sampling grid, half the cell's diagonal, times ``scale``
  (``--radius-scale``)::

      radius = scale * range * max(|v_r + v_c|, |v_r - v_c|) / 2,   v = a (e - d (n . e) / (n . d))

  with ``a_r``, ``a_c`` the angles between neighbouring beams along the grid's rows and columns
  (radians), ``e`` the unit direction of that axis on the sphere of beams, and ``v`` that step
  moved along the beam ``d`` onto the surface of normal ``n``: the cell's sides on the surface,
  stretched where the surface tilts away from the beam, sheared where it tilts diagonally to the
  grid. On a square grid of step ``h`` facing the beam this is ``scale * range * h / sqrt(2)``:
  what the kNN radius gives on a square grid of spacing ``range * h`` (its 8th neighbour is the
  diagonal one, ``sqrt(2) range h``, times ``radius_factor(8) = 1/2``). Each side's stretch is
  capped at 4, where the kNN radius saturates too (a row of the grid alone then holds the 8
  neighbours).
  A spherical grid (``scans.json``) gives the angles and axes exactly: ``a_r`` = the elevation
  step, ``a_c`` = the azimuth step at the point's elevation (``2 asin(cos(el) sin(step / 2))``;
  beams crowd toward the zenith). An E57 grid states no angles: they are measured between the
  point's beam and the nearest beam within ``REACH`` cells along each axis (its direction, whatever
  range it hit), the other axis's where one axis has none, the median of the block's points of its
  station where neither has (``isolated_points``).
* **Normals**: ``T_c x T_r``, oriented toward the station, of the tangents along the grid's columns
  and rows fitted by least squares over the point's 5 x 5 grid window (:func:`_grid_normals`:
  averaged central differences where the window is full, one-sided at an edge). A neighbour counts
  when its range differs by at most ``TAU`` grid spacings per cell from the point's, so a
  silhouette's point takes the side of its own surface. Where the neighbours on the surface do not
  span both axes (a one-point-wide pole, a point among beams that returned nothing), the normal is
  the least-squares plane of the point's ``k`` nearest points (3D) among the window's cells (a kNN
  restricted to the grid window), counted as ``fallback_normals``; with fewer than 3 it faces the
  station. Where the input has normals, they are kept and only give the stretch.

Out of core: the input is streamed once in its chunks; each chunk is processed with a halo of the
points up to ``REACH`` scan lines before and after it in file order (``Station.line``: scanners
write line after line), and the results go to ``(n,)`` / ``(n, 3)`` float32 arrays in input order
on disk. Chunks are prepared and processed on threads (numpy releases the GIL); the results do not
depend on the chunks or the threads. Neighbours farther in file order than the halo (a file not
written line by line) are not seen: their points fall back as above. :meth:`ScanResult.attach`
hands the results to the octree build as attributes of the points, so they arrive in octree order
with the points: the later phases read them from the octree, and the pipeline deletes ``folder``
once the octree is built (:func:`dmrt.preprocess.pipeline.preprocess`).

Measured against the kNN path (:func:`dmrt.preprocess.normals.process_chunked`, k = 16 and 8) on
the same points, both at ``--radius-scale`` 1.5 (``python -m bench.bench_scangrid --preset P``;
true normals: the mesh faces the beams hit; synthetic scans with 2 mm range noise)::

    scene  points  stations  radius / kNN radius     normal vs truth, degrees (median, p90)
                             median (5 - 95 %)       scan grid        kNN
    tiny   0.20M   2         1.01 (0.91 - 1.88)      0.8, 9.2         1.2, 9.6
    small  2.00M   6         1.01 (0.90 - 1.86)      1.3, 7.4         1.9, 8.5

The radii agree at the median. The scan's are larger within ~15 degrees of a scanner's zenith,
where the beams' rings crowd (kNN's radius spans the crowded ring, leaving the rings apart; tiny:
scan / kNN median 1.85 there, ``bench_scangrid``'s ``by_elevation``), and where stations overlap
(the kNN sees their union, denser than the one station's grid, which covers the surface alone).
On 2 shared cores the pass took 1.6 - 1.9 CPU microseconds a point against the kNN's 8.2 - 10.3
(``README.md``, "Radii and normals from the scan's grid").
"""

from __future__ import annotations

import math
import sys
import time
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from pathlib import Path

import numpy as np

from dmrt.errors import ConfigError, InputError
from dmrt.io.pointcloud import extent
from dmrt.io.stations import MAX_INDEX, ScanStructure
from dmrt.preprocess.buckets import progress_bar
from dmrt.preprocess.parallel import default_workers

__all__ = ["ScanResult", "scan_attributes", "scan_phase", "REACH", "TAU", "STRETCH_MAX"]

REACH = 3  # grid cells searched along an axis for a beam (E57), and scan lines in a chunk's halo
# A grid neighbour is on the point's surface when their ranges differ by at most TAU spacings: a
# plane tilted by theta from the beam changes range by tan(theta) spacings a step, so 8 keeps
# surfaces up to 83 degrees from the beam and 2 mm noise at 2.4 mm spacings (paper-full at 3 m),
# and cuts a pole 20 cm in front of a wall from it wherever the spacing is below 2.5 cm.
TAU = 8.0
HALF = 2  # the normals' grid window: (2 HALF + 1)^2 cells
STRETCH_MAX = 4.0  # cap of the incidence stretch (module docstring)
# bytes a point of a chunk in flight: its prepared arrays (89), the window's copy of them, the
# station image, sums and solution of its block (about 60 a cell), normals and radii
_BYTES_IN_FLIGHT = 320
_DENSE_SLACK = 1 << 16  # cells a station's image may hold beyond 4 per point of the block
_LINE = 1 << 14  # beams of a scan line where the input does not say (E57 without indexBounds)
_BITS = 24  # bits of a row or column in a packed key (station << 48 | row << 24 | column)
_MASK = (1 << _BITS) - 1


@dataclass
class ScanResult:
    """Normals and radii from the scan grid, in input order (:func:`scan_attributes`).

    Attributes
    ----------
    folder : Path
        Holds ``radii.npy`` ((n,) float32, metres) and, when computed, ``normals.npy`` ((n, 3)
        float32 unit, toward the station).
    n_points : int
    normals : bool
        Whether normals were computed (False: the input's were kept).
    counts : dict
        ``fallback_normals`` (kNN in the grid window), ``isolated_points`` (no beam along either
        axis: spacing from the station's median), ``off_grid_points`` (a direction more than a
        quarter step from every beam of its grid: a cloud that does not match its scans.json).
    stations : int
    source : str
        Where the structure came from: ``scans.json`` or ``e57``.
    seconds : float
    bounds : ((3,), (3,)) float64 or None
        The points' bounding box, world metres (lowest and highest corner): the pass read every
        point, so the pipeline needs no pass of its own to find it (:func:`dmrt.io.scene.load_scene`).
    """

    folder: Path
    n_points: int
    normals: bool
    counts: dict = field(default_factory=dict)
    stations: int = 0
    source: str = ""
    seconds: float = 0.0
    bounds: tuple[np.ndarray, np.ndarray] | None = None

    def names(self) -> list[str]:
        """The attributes computed, as the octree carries them."""
        return ["normals", "radii"] if self.normals else ["radii"]

    def attach(self, source) -> "ScanAttrs":
        """``source`` (chunks ``(positions, attrs)`` in input order) with ``radii`` and, when
        computed, ``normals`` added to each chunk's attributes: the octree build's input."""
        return ScanAttrs(source, str(self.folder), tuple(self.names()))

    def meta(self) -> dict:
        """What ``bundle.json`` records under ``normals_radii``."""
        return {"method": "scan", "radii": "scan", "normals": "scan" if self.normals else "input",
                "structure": self.source, "stations": self.stations, **self.counts,
                "scan_s": round(self.seconds, 3)}


class ScanAttrs:
    """A chunk source (``(positions, attrs)`` chunks, as the octree reads) with the scan results of
    ``folder`` added to each chunk's attributes; picklable, and split as its source splits (parts
    of a :class:`~dmrt.io.pointcloud.PointRange`, which know their first record)."""

    def __init__(self, source, folder: str, names: tuple, start: int = 0):
        self.source, self.folder, self.names, self.start = source, folder, names, start

    def __call__(self):
        arrays = {n: np.load(Path(self.folder) / f"{n}.npy", mmap_mode="r") for n in self.names}
        g = self.start
        for pos, attrs in self.source():
            m = len(pos)
            yield pos, {**attrs, **{n: np.array(a[g:g + m]) for n, a in arrays.items()}}
            g += m

    def split(self, parts: int) -> list["ScanAttrs"]:
        return [ScanAttrs(p, self.folder, self.names, p.source.start) for p in self.source.split(parts)]


def scan_phase(scene, work, config, progress: bool = False, executor=None) -> ScanResult | None:
    """The pipeline's choice (``config.radii``): the scan-grid results of ``scene`` in
    ``work/scan``, or None for the kNN path (``knn``, or ``auto`` on a scene without structure).

    Raises
    ------
    ConfigError
        ``--radii scan`` for a scene without scan structure.
    """
    if config.radii == "knn" or (config.radii == "auto" and scene.scan_structure is None):
        return None
    if scene.scan_structure is None:
        raise ConfigError("radii", f"scan: the scene {scene.root} has no scan structure (no scans.json beside "
                                   f"points.ply, no structured E57 scans with rowIndex/columnIndex)")
    source = replace(scene.point_range(config.chunk_points), colors=False)  # the pass has no use for them
    result = scan_attributes(source, scene.scan_structure, scene.n_points, Path(work) / "scan",
                             scale=config.radius_scale, k_normals=config.normals_k, progress=progress,
                             executor=executor, memory_limit_mb=config.memory_limit_mb)
    off = result.counts["off_grid_points"] / max(result.n_points, 1)
    if off > 0.01:  # a cloud that does not match its scans.json: its cells are guesses
        print(f"dmrt: warning: {scene.root / 'scans.json'}: {off:.1%} of the points lie off their station's grid "
              f"of beams (another cloud, or other stations?); --radii knn does not use it", file=sys.stderr)
    return result


# ---------------------------------------------------------------------------------------------
# the pass over the input
# ---------------------------------------------------------------------------------------------
def scan_attributes(source, structure: ScanStructure, n_points: int, out_dir, *, scale: float = 1.0,
                    k_normals: int = 16, normals: bool | None = None, threads: int | None = None,
                    progress: bool = False, executor=None, memory_limit_mb: float | None = None) -> ScanResult:
    """Radii and normals of every point from its scan grid (module docstring), in input order.

    Parameters
    ----------
    source : callable returning an iterator of :class:`~dmrt.io.pointcloud.PointCloud` chunks
        The whole cloud in file order (``Scene.point_range``): world positions, and for an E57
        structure ``scan_index`` and ``grid``.
    structure : ScanStructure
    n_points : int
        Points the source yields.
    out_dir : path
        Receives ``radii.npy`` and ``normals.npy``.
    scale : float
        The radius scale (``--radius-scale``).
    k_normals : int
        Neighbours of the fallback plane fit.
    normals : bool, optional
        Compute normals; default: where the input has none.
    threads : int, optional
        Chunks processed at once in this process; default one per core.
    executor : optional, :mod:`dmrt.preprocess.parallel`
        When distributed and the source splits into record ranges (a binary PLY's
        :class:`~dmrt.io.pointcloud.PointRange`): one task per range, each reading its range with
        the halos around it and writing its rows of the results, one thread each. The results are
        those of one process, bit for bit (they do not depend on the chunks).
    memory_limit_mb : float, optional
        Bounds the chunks of a :class:`~dmrt.io.pointcloud.PointRange` source (``chunk_size``) so
        that the chunks and windows in flight (``_BYTES_IN_FLIGHT`` a point each) fit: this much
        in this process, or this much shared by the executor's workers.

    Returns
    -------
    ScanResult
    """
    t0 = time.perf_counter()
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    first = _first_chunk(source)
    if normals is None:
        normals = first is None or first.normals is None
    if not normals and (first is None or first.normals is None):
        raise ValueError("normals=False needs normals in the input")
    for name, shape in (("radii", (n_points,)), ("normals", (n_points, 3)))[:1 + bool(normals)]:
        np.lib.format.open_memmap(out_dir / f"{name}.npy", "w+", np.float32, shape)  # the tasks write their rows
    task = dict(structure=structure, out_dir=str(out_dir), halo=REACH * (structure.line() or _LINE) + REACH + 1,
                scale=scale, k_normals=k_normals, normals=normals)
    parts = None
    if executor is not None and executor.distributed and getattr(source, "seekable", False):
        parts = source.split(executor.workers)
    threads = 1 if parts is not None and len(parts) > 1 else threads or default_workers()
    if memory_limit_mb is not None and hasattr(source, "chunk_size"):
        tasks = len(parts) if parts is not None and len(parts) > 1 else 1
        # windows in flight a task: threads + 1 pending, one being prepared
        fit = int(memory_limit_mb * 2 ** 20 / tasks / (threads + 2) / _BYTES_IN_FLIGHT)
        if fit < source.chunk_size:
            source = replace(source, chunk_size=max(fit, 1))
    if parts is None or len(parts) < 2:
        done = [_scan_range((source, 0, n_points, True), threads=threads, progress=progress, **task)]
    else:
        items = [(source, p.start, p.stop, False) for p in parts]
        done = executor.map(_scan_range, items, desc="scan grid", progress=progress, threads=threads, **task)
    n_seen = sum(n for n, _, _ in done)
    if n_seen != n_points:
        raise RuntimeError(f"the source yielded {n_seen} points, expected {n_points}")
    counts = {k: sum(c.get(k, 0) for _, c, _ in done) for k in ("fallback_normals", "isolated_points",
                                                                  "off_grid_points")}
    bounds = (np.min([lo for _, _, (lo, _) in done], axis=0), np.max([hi for _, _, (_, hi) in done], axis=0))
    return ScanResult(out_dir, n_points, bool(normals), counts, len(structure.stations), structure.source,
                      time.perf_counter() - t0, bounds)


def _first_chunk(source):
    """The source's first non-empty chunk (None if it has none)."""
    it = iter(source())
    try:
        return next((pc for pc in it if len(pc.positions)), None)
    finally:
        if hasattr(it, "close"):
            it.close()


def _part_chunks(source, a: int, b: int, whole: bool, halo: int):
    """The chunks of records ``a - halo .. b + halo - 1`` of ``source``, each marked whether it
    lies in ``a .. b - 1`` (the part's own), and the index of the first: ``(first, iterator)``.
    A ``whole`` source is read as it is; a part of a seekable
    :class:`~dmrt.io.pointcloud.PointRange` (records counted from the file's first) as three
    ranges: the halo before, its own records, the halo after."""
    if whole:
        return 0, ((pc, True) for pc in source())
    lo, hi = max(source.start, a - halo), min(source.stop, b + halo)

    def chunks():
        for x, y, own in ((lo, a, False), (a, b, True), (b, hi, False)):
            if y > x:
                yield from ((pc, own) for pc in replace(source, start=x, stop=y)())

    return lo, chunks()


def _scan_range(item, structure, out_dir: str, halo: int, scale, k_normals, normals: bool, threads: int,
                progress: bool = False):
    """The results of points ``a .. b - 1`` of ``item = (source, a, b, whole)`` (see
    :func:`_part_chunks`), written to their rows of ``out_dir/radii.npy`` (and ``normals.npy``):
    each own chunk with its window of ``halo`` points around it, on ``threads`` threads. Returns
    (points done, counts, (lo, hi): the bounding box of those points, (3,) float64 metres each)."""
    source, a, b, whole = item
    st = _Stations(structure, getattr(source, "path", None))
    out_r = np.load(Path(out_dir) / "radii.npy", mmap_mode="r+")
    out_n = np.load(Path(out_dir) / "normals.npy", mmap_mode="r+") if normals else None
    counts = dict.fromkeys(("fallback_normals", "isolated_points", "off_grid_points"), 0)
    pending: list = []
    done = 0
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)

    def drain(limit):
        nonlocal done
        while len(pending) > limit:
            g, fut = pending.pop(0)
            nrm, rad, c = fut.result()
            out_r[g:g + len(rad)] = rad
            if out_n is not None:
                out_n[g:g + len(rad)] = nrm
            for k, v in c.items():
                counts[k] += v
            done += len(rad)

    read, it = _part_chunks(source, a, b, whole, halo)
    chunks, cores = [], []  # chunks: (first, stop, prepared future); cores: own chunks not yet processed
    with ThreadPoolExecutor(threads) as pool, progress_bar(b - a, "scan grid", progress) as bar:
        while True:
            pc, own = next(it, (None, False))
            if pc is not None and len(pc.positions):
                m = len(pc.positions)
                if read + m > len(out_r):
                    raise RuntimeError(f"the source yields more than its {len(out_r)} points")
                if not normals and pc.normals is None:
                    raise ValueError("normals=False needs normals in the input")
                chunks.append((read, read + m, pool.submit(st.prepare, pc, read)))
                if own:
                    cores.append((read, read + m))
                    c_lo, c_hi = extent(pc.positions)
                    lo, hi = np.minimum(lo, c_lo), np.maximum(hi, c_hi)
                read += m
            # a chunk is processed once the halo after it is read; its window takes the prepared
            # chunks it overlaps (a task waits only on tasks queued before it: no deadlock)
            while cores and (pc is None or read >= cores[0][1] + halo):
                c0, c1 = cores.pop(0)
                parts = [(x0, x1, f) for x0, x1, f in chunks if x1 > c0 - halo and x0 < c1 + halo]
                pending.append((c0, pool.submit(_window_block, parts, c0, c1, halo, st, scale, k_normals,
                                                normals)))
                if cores:
                    chunks = [c for c in chunks if c[1] > cores[0][0] - halo]
                drain(threads)  # bounded: at most threads + 1 windows in memory
                bar.update(c1 - c0)
            if pc is None:
                break
        drain(0)
    for arr in (out_r, out_n):
        if arr is not None:
            arr.flush()
    return done, counts, (lo, hi)


class _Stations:
    """Per-station arrays of a structure, indexed by station: positions (s, 3), rotations (s, 3,
    3), first records (s,) and whether grids are known / wrap."""

    def __init__(self, structure: ScanStructure, path=None):
        self.structure, self.path = structure, path
        s = structure.stations
        self.positions = structure.positions
        self.up = np.array([np.asarray(x.rotation)[:, 2] for x in s]).reshape(-1, 3)  # the scanner's z, world
        self.upright = bool(np.all(self.up == [0.0, 0.0, 1.0]))
        self.grids = [x.grid for x in s]
        self.known = structure.source == "scans.json"
        self.firsts = np.array([x.points[0] if x.points else 0 for x in s], np.int64)
        self.wrap = np.array([x.grid.columns if x.grid is not None and x.grid.wraps else 0 for x in s], np.int64)

    def prepare(self, pc, g: int) -> dict:
        """Per-point arrays of chunk ``pc`` (its first point is the ``g``-th of the cloud):
        ``pos`` (m, 3) float64, ``u`` (m, 3) unit beams, ``rng`` (m,), ``key`` (m,) int64 packed
        (station, row, column), ``off`` (m,) bool, ``normals`` (m, 3) or None."""
        m = len(pc.positions)
        if self.known:  # the stations whose runs the chunk overlaps, each for its share
            k0, k1 = (int(np.searchsorted(self.firsts, x, side="right")) - 1 for x in (g, g + m - 1))
            cuts = np.concatenate([[0], np.clip(self.firsts[k0 + 1:k1 + 1] - g, 0, m), [m]])
            s = np.repeat(np.arange(k0, k1 + 1), np.diff(cuts))
        else:
            s = np.asarray(pc.scan_index, np.int64)
        pos = np.asarray(pc.positions, np.float64)
        if self.known:  # each station's run less its position (the same differences as a gather's)
            d = np.empty_like(pos)
            for k, a, b in zip(range(k0, k1 + 1), cuts[:-1], cuts[1:]):
                np.subtract(pos[a:b], self.positions[k], out=d[a:b])
        else:
            d = pos - self.positions[s]
        rng = np.sqrt(np.einsum("ij,ij->i", d, d))
        u = d / np.where(rng > 0, rng, 1.0)[:, None]
        off = rng == 0
        if self.known:
            row, col = np.zeros(m, np.int64), np.zeros(m, np.int64)
            for k, a, b in zip(range(k0, k1 + 1), cuts[:-1], cuts[1:]):
                st = self.structure.stations[k]
                row[a:b], col[a:b], o = st.grid.cells(u[a:b] @ np.asarray(st.rotation))
                off[a:b] |= o
        else:
            row, col = (np.asarray(pc.grid[:, i], np.int64) for i in (0, 1))
            bad = (row < 0) | (row >= MAX_INDEX) | (col < 0) | (col >= MAX_INDEX)
            if bad.any():
                raise InputError(self.path, f"rowIndex/columnIndex of point {g + int(np.argmax(bad))} outside "
                                            f"0..{MAX_INDEX - 1}")
        key = (s << (2 * _BITS)) | (row << _BITS) | col
        nrm = None if pc.normals is None else np.asarray(pc.normals, np.float64)
        return {"pos": pos, "u": u, "rng": rng, "key": key, "off": off, "normals": nrm}


def _window_block(parts, c0: int, c1: int, halo: int, st: _Stations, scale, k_normals, normals):
    """:func:`_block` of the cloud's points ``c0 .. c1 - 1``, its window being those ``halo``
    before and after them in the prepared chunks ``parts`` (``(first, stop, future)``)."""
    if st.known and not normals:  # spacings from the grid itself and no fit: no neighbour is looked at
        halo = 0
    w0, w1 = max(c0 - halo, parts[0][0]), min(c1 + halo, parts[-1][1])
    arrays = []
    for a0, a1, fut in (p for p in parts if p[1] > w0 and p[0] < w1):  # one part, usually: views, no copy
        arr, lo, hi = fut.result(), max(a0, w0) - a0, min(a1, w1) - a0
        arrays.append({k: None if v is None else v[lo:hi] for k, v in arr.items()})
    win = arrays[0] if len(arrays) == 1 else {
        k: None if arrays[0][k] is None else np.concatenate([a[k] for a in arrays]) for k in arrays[0]}
    return _block(win, c0 - w0, c1 - w0, st, scale, k_normals, normals)


# ---------------------------------------------------------------------------------------------
# one block: the points window[a:b], their neighbours in the window
# ---------------------------------------------------------------------------------------------
def _angle(u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(m,) angles between unit vectors, radians (atan2 of sine and cosine: exact for small ones)."""
    return np.arctan2(_norm(_cross(u, v)), np.einsum("ij,ij->i", u, v))


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross products of (m, 3) arrays (np.cross is several times slower on them)."""
    out = np.empty(np.broadcast_shapes(a.shape, b.shape), np.result_type(a, b))
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


def _norm(v: np.ndarray) -> np.ndarray:
    """(m,) lengths of the rows of an (m, 3) array: ``np.linalg.norm(v, axis=1)`` bit for bit (the
    same squares summed in the same order), three times faster than its reduction over 3 elements."""
    return np.sqrt(v[:, 0] * v[:, 0] + v[:, 1] * v[:, 1] + v[:, 2] * v[:, 2])


def _unit(v: np.ndarray) -> np.ndarray:
    n = _norm(v)[:, None]
    return v / np.where(n > 0, n, 1.0)


class _Lookup:
    """Grid cells of a window -> window indices (-1 where no point is).

    A window holds a few scan lines of one or two stations, so each station's cells in it span a
    small box of rows x columns: a dense table of that box answers a lookup with one gather. A
    window whose cells do not fit such boxes (a file not written line by line) is looked up by
    binary search in its sorted keys instead.
    """

    def __init__(self, key: np.ndarray, wrap_of_station: np.ndarray):
        self.key, self.wrap, self.built = key, wrap_of_station, False

    def _build(self):
        key, self.built = self.key, True
        s, row, col = key >> (2 * _BITS), (key >> _BITS) & _MASK, key & _MASK
        ids = np.unique(s)
        n_st = int(ids[-1]) + 1
        self.r0, self.c0 = np.zeros(n_st, np.int64), np.zeros(n_st, np.int64)
        self.h, self.w, self.base = (np.zeros(n_st, np.int64) for _ in range(3))
        size = 0
        for k in ids.tolist():
            sel = s == k
            r0, r1 = int(row[sel].min()), int(row[sel].max())
            c0, c1 = int(col[sel].min()), int(col[sel].max())
            self.r0[k], self.c0[k], self.h[k], self.w[k], self.base[k] = r0, c0, r1 - r0 + 1, c1 - c0 + 1, size
            size += (r1 - r0 + 1) * (c1 - c0 + 1)
        self.table = None
        if size <= 8 * len(key) + _DENSE_SLACK:
            self.table = np.full(size, -1, np.int64)
            self.table[self.base[s] + (row - self.r0[s]) * self.w[s] + col - self.c0[s]] = np.arange(len(key))
        else:
            self.order = np.argsort(key, kind="stable")
            self.sorted = key[self.order]

    def find(self, key: np.ndarray, dr: int, dc: int) -> np.ndarray:
        """Indices of the points in the cells ``dr`` rows and ``dc`` columns from the cells ``key``."""
        if not self.built:
            self._build()
        s, row, col = key >> (2 * _BITS), ((key >> _BITS) & _MASK) + dr, (key & _MASK) + dc
        if self.wrap.any():
            w = self.wrap[s]
            col = np.where(w > 0, np.mod(col, np.maximum(w, 1)), col)
        if self.table is not None:
            r, c = row - self.r0[s], col - self.c0[s]
            ok = (r >= 0) & (r < self.h[s]) & (c >= 0) & (c < self.w[s])
            return np.where(ok, self.table[np.where(ok, self.base[s] + r * self.w[s] + c, 0)], -1)
        ok = (row >= 0) & (row < MAX_INDEX) & (col >= 0) & (col < MAX_INDEX)
        q = (s << (2 * _BITS)) | (np.clip(row, 0, _MASK) << _BITS) | np.clip(col, 0, _MASK)
        i = np.minimum(np.searchsorted(self.sorted, q), len(self.sorted) - 1)
        return np.where(ok & (self.sorted[i] == q), self.order[i], -1)


def _block(win: dict, a: int, b: int, st: _Stations, scale: float, k_normals: int, normals: bool):
    """Normals ((m, 3) float32 or None), radii ((m,) float32) and counts of ``win[a:b]``."""
    look = _Lookup(win["key"], st.wrap)  # its table is built on first use
    key, pos, u, rng = win["key"][a:b], win["pos"][a:b], win["u"][a:b], win["rng"][a:b]
    s = key >> (2 * _BITS)
    counts = {"off_grid_points": int(np.count_nonzero(win["off"][a:b]))}
    if st.known:
        spacing, tilts = _grid_spacing(u, s, st)
    else:
        spacing, axis = zip(*(_measured_spacing(look, key, u, win["u"], step) for step in ((1, 0), (0, 1))))
        spacing, tilts, counts["isolated_points"] = _fill_spacing(list(spacing), axis, u, s)

    n_out = None
    if normals:
        n, counts["fallback_normals"] = _grid_normals(win, look, a, b, spacing, st, k_normals)
        n[np.einsum("ij,ij->i", n, u) > 0] *= -1  # toward the station
        n_out = n.astype(np.float32)
    else:
        n = _unit(win["normals"][a:b])
    nu = np.einsum("ij,ij->i", n, u)
    radii = (scale * 0.5 * rng * _cell_diagonal(spacing, nu, *tilts(n, nu)))
    return n_out, radii.astype(np.float32), counts


def _cell_diagonal(spacing, nu, ne_r, ne_c) -> np.ndarray:
    """(m,) the longer diagonal of the grid's cell on the surface, per unit of range.

    The steps ``a_k e_k`` between neighbouring beams (``e_r``, ``e_c``, ``u``: an orthonormal
    frame) moved along the beam ``u`` onto the plane of normal ``n`` are ``v_k = a_k (e_k - u
    t_k)``, ``t_k = (n . e_k) / (n . u)``, each stretched at most ``STRETCH_MAX`` times; the
    longer diagonal of the cell they span is ``|v_r +- v_c|`` with ``|v_k|^2 = a_k^2 (1 + t_k^2)``
    and ``v_r . v_c = a_r a_c t_r t_c``.

    Parameters
    ----------
    spacing : (a_r, a_c), each (m,) radians.  nu, ne_r, ne_c : (m,) ``n . u``, ``n . e_r``, ``n . e_c``.
    """
    limit = math.sqrt(STRETCH_MAX ** 2 - 1)  # |e_k - u t| = sqrt(1 + t^2) <= STRETCH_MAX
    t = []
    for ne in (ne_r, ne_c):
        with np.errstate(divide="ignore", invalid="ignore"):
            tk = ne / nu
        bad = ~np.isfinite(tk)
        np.minimum(np.maximum(tk, -limit, out=tk), limit, out=tk)
        tk[bad] = limit
        t.append(tk)
    (a_r, a_c), (t_r, t_c) = spacing, t
    # a_r^2 (1 + t_r^2) + a_c^2 (1 + t_c^2) + 2 a_r a_c |t_r t_c|, each product and sum as written,
    # in place: the same numbers without a dozen temporaries of m each
    out, tmp, sq = a_r * a_r, a_c * a_c, t_r * t_r
    sq += 1
    out *= sq
    np.multiply(t_c, t_c, out=sq)
    sq += 1
    tmp *= sq
    out += tmp
    np.multiply(a_r, 2, out=tmp)
    tmp *= a_c
    np.multiply(t_r, t_c, out=sq)
    tmp *= np.abs(sq, out=sq)
    out += tmp
    return np.sqrt(out, out=out)


def _grid_normals(win: dict, look: _Lookup, a: int, b: int, spacing, st: _Stations, k_normals: int):
    """Unit normals (sign arbitrary) of ``win[a:b]`` from their grid window, and how many fell back.

    The points of the ``(2 HALF + 1)^2`` cells around a point that lie on its surface (range within
    ``TAU`` grid spacings per cell of distance) are fitted by least squares as ``p(i, j) = c + i T_r
    + j T_c`` over their row and column offsets ``i``, ``j``; the normal is ``T_c x T_r``. With all
    cells present, ``T_r`` and ``T_c`` are averaged central differences along the rows and columns
    (a Savitzky-Golay derivative), which cuts the range noise; at an edge the fit takes the side
    that is there. Where the cells on the surface do not span both axes, the normal is the plane
    of the ``k_normals`` nearest points among the window's cells (:func:`_knn_planes`).

    The sums run over each station's cells as a dense image (the block's box of rows x columns
    plus a margin of ``HALF``), shifted once per offset: no per-point lookups. A box much larger
    than its points (a file not in scan-line order) is summed by lookups instead. Both give the
    same numbers: float32 positions relative to the station, summed in the same order.
    """
    key = win["key"][a:b]
    s, row, col = key >> (2 * _BITS), (key >> _BITS) & _MASK, key & _MASK
    n = np.zeros((b - a, 3))
    a_r2, a_c2 = (x.astype(np.float32) ** 2 for x in spacing)
    ws = win["key"] >> (2 * _BITS)
    fallback = 0
    for k in np.unique(s).tolist():
        sel = np.flatnonzero(s == k)

        def rel(i, k=k):  # window points i relative to the station, as the images hold them
            return (win["pos"][i] - st.positions[k]).astype(np.float32), win["rng"][i].astype(np.float32)

        r0, r1 = int(row[sel].min()), int(row[sel].max())
        c0, c1, wrap = int(col[sel].min()), int(col[sel].max()), int(st.wrap[k])
        if wrap:
            c0, c1 = 0, wrap - 1  # the whole circle, its ends padded from each other
        h, w = r1 - r0 + 1 + 2 * HALF, c1 - c0 + 1 + 2 * HALF
        if h * w > 4 * len(sel) + _DENSE_SLACK:
            def at(i, j, which, keys=key[sel], rel=rel):  # the cells (i, j) from points sel[which]
                f = look.find(keys[which], i, j)
                p, r = rel(np.maximum(f, 0))
                return p, np.where(f >= 0, r, np.float32(np.nan))

            nk, good = _solve(_moments(*rel(a + sel), a_r2[sel], a_c2[sel], at))
        else:
            # station k's points in the box (float32 keeps micrometres within 100 m of the station)
            wi = np.flatnonzero(ws == k)
            wr, wc = (win["key"][wi] >> _BITS) & _MASK, win["key"][wi] & _MASK
            margin = 0 if wrap else HALF
            inside = (wr >= r0 - HALF) & (wr <= r1 + HALF) & (wc >= c0 - margin) & (wc <= c1 + margin)
            wi, wr, wc = wi[inside], wr[inside] - r0 + HALF, wc[inside] - c0 + HALF
            pos = np.zeros((h, w, 3), np.float32)  # 0 where no point: its range (NaN) keeps it out
            rng = np.full((h, w), np.nan, np.float32)
            pos[wr, wc], rng[wr, wc] = rel(wi)
            if wrap:
                for img in (pos, rng):
                    img[:, :HALF], img[:, w - HALF:] = img[:, w - 2 * HALF:w - HALF], img[:, HALF:2 * HALF]
            pr, pc = row[sel] - r0, col[sel] - c0
            ar2 = np.zeros((h - 2 * HALF, w - 2 * HALF), np.float32)  # the centres' squared spacings
            ac2 = np.zeros_like(ar2)
            ar2[pr, pc], ac2[pr, pc] = a_r2[sel], a_c2[sel]

            def shifted(i, j, img, rows=slice(None), h=h, w=w):
                return img[HALF + i:h - HALF + i, HALF + j:w - HALF + j][rows]

            def at(i, j, which, pr=pr, pc=pc, pos=pos, rng=rng):
                return pos[pr[which] + HALF + i, pc[which] + HALF + j], rng[pr[which] + HALF + i, pc[which] + HALF + j]

            m = _moments(shifted(0, 0, pos), shifted(0, 0, rng), ar2, ac2,
                         lambda i, j, rows: (shifted(i, j, pos, rows), shifted(i, j, rng, rows)))
            cells = m[0].size  # solved on the whole box (as many cells as points, about), then picked
            nk, good = _solve(tuple(x.reshape(cells, *x.shape[2:]) for x in m))
            flat = pr * (w - 2 * HALF) + pc
            nk, good = nk[flat], good[flat]
        bad = np.flatnonzero(~good)
        if len(bad):
            nk[bad] = _knn_planes(at, bad, k_normals, -win["u"][a + sel[bad]])
        n[sel] = nk
        fallback += len(bad)
    return n, fallback


def _knn_planes(at, which: np.ndarray, k: int, facing: np.ndarray) -> np.ndarray:
    """Least-squares plane normals (sign arbitrary) of points ``which`` from their ``k`` nearest
    (3D) among the ``(2 HALF + 1)^2`` cells around each (``at(i, j, which)``: their positions and
    ranges, NaN where no point), the point included; ``facing`` ((f, 3): toward the station)
    where fewer than 3 are there."""
    cells = [at(i, j, which) for i in range(-HALF, HALF + 1) for j in range(-HALF, HALF + 1)]
    p = np.stack([c[0] for c in cells], axis=1).astype(np.float64)  # (f, c, 3)
    p -= at(0, 0, which)[0][:, None, :]
    d2 = np.where(np.isfinite(np.stack([c[1] for c in cells], axis=1)), np.einsum("fci,fci->fc", p, p), np.inf)
    k = min(int(k), d2.shape[1])
    near = np.argpartition(d2, k - 1, axis=1)[:, :k]
    w = np.isfinite(np.take_along_axis(d2, near, 1)).astype(np.float64)  # (f, k) present
    q = np.take_along_axis(p, near[:, :, None], 1)
    cnt = w.sum(axis=1)
    mean = (q * w[:, :, None]).sum(axis=1) / np.maximum(cnt, 1)[:, None]
    q = (q - mean[:, None, :]) * w[:, :, None]
    _, vec = np.linalg.eigh(np.einsum("fki,fkj->fij", q, q))
    n = vec[:, :, 0]
    few = cnt < 3
    n[few] = facing[few]
    return n


_OFFSETS = [(i, j) for i in range(-HALF, HALF + 1) for j in range(-HALF, HALF + 1) if i or j]
# per offset (columns) its weight in each sum of _moments: 1, i, j, i^2, j^2, i j
_COEF = np.array([[1, i, j, i * i, j * j, i * j] for i, j in _OFFSETS], np.float32).T
_TILE = 1 << 15  # cells per tile of _moments: its per-offset arrays stay in the cache


def _moments(pos, rng, a_r2, a_c2, neighbour):
    """The least-squares sums of :func:`_grid_normals` over the centre (offset 0, difference 0)
    and its neighbours at every offset that lie on its surface, for arrays of any shape ``S``
    (per point, or per cell of an image).

    Parameters
    ----------
    pos : S + (3,) float32 centres.  rng : S float32 their ranges.  a_r2, a_c2 : S float32 squared
    grid spacings (radians^2).
    neighbour : callable ``(i, j, rows) -> (positions S' + (3,), ranges S')``
        The neighbours at offset ``(i, j)`` of the centres ``[rows]`` (a slice of the first axis);
        range NaN where no point is, position finite.

    Returns
    -------
    s0, si, sj, sii, sjj, sij : S float32.  q0, qi, qj : S + (3,) float32.
    """
    s_out = np.empty((6,) + rng.shape, np.float32)
    q_out = np.empty((3,) + pos.shape, np.float32)
    per_row = max(1, int(np.prod(rng.shape[1:])))
    step = max(1, _TILE // per_row)
    for t0 in range(0, rng.shape[0], step):
        rows = slice(t0, min(rng.shape[0], t0 + step))
        c_pos, c_rng = pos[rows], rng[rows]
        wgt = np.empty((len(_OFFSETS),) + c_rng.shape, np.float32)  # 1 where on the centre's surface
        q = np.empty((len(_OFFSETS),) + c_pos.shape, np.float32)    # differences to those
        limit = {}  # per (|i|, |j|): the largest range difference on the surface
        for o, (i, j) in enumerate(_OFFSETS):
            p, r = neighbour(i, j, rows)
            if (abs(i), abs(j)) not in limit:
                limit[abs(i), abs(j)] = TAU * c_rng * np.sqrt(i * i * a_r2[rows] + j * j * a_c2[rows])
            with np.errstate(invalid="ignore"):
                wgt[o] = np.abs(r - c_rng) <= limit[abs(i), abs(j)]  # False where NaN
            np.subtract(p, c_pos, out=q[o])
            q[o] *= wgt[o][..., None]
        # weighted sums over the offsets (einsum's own loop: BLAS would start threads of its own
        # inside each of the pass's threads, and sum in an order that depends on the tile)
        k = len(_OFFSETS)
        s_out[:, rows] = np.einsum("ok,kn->on", _COEF, wgt.reshape(k, -1)).reshape((6,) + c_rng.shape)
        q_out[:, rows] = np.einsum("ok,kn->on", _COEF[:3], q.reshape(k, -1)).reshape((3,) + c_pos.shape)
    s_out[0] += 1.0  # the centre itself
    return (*s_out, *q_out)


def _solve(m) -> tuple[np.ndarray, np.ndarray]:
    """Unit normals ``T_c x T_r`` (float64) of the fits with sums ``m`` (:func:`_moments`), and
    where they are defined."""
    s0, si, sj, sii, sjj, sij, q0, qi, qj = m
    cii, cjj, cij = sii - si * si / s0, sjj - sj * sj / s0, sij - si * sj / s0
    ci = qi - (si / s0)[:, None] * q0
    cj = qj - (sj / s0)[:, None] * q0
    det = cii * cjj - cij * cij
    good = det > 1e-6 * np.maximum(cii * cjj, 1e-300)
    det = np.where(good, det, 1.0)[:, None]
    t_r = (cjj[:, None] * ci - cij[:, None] * cj) / det
    t_c = (cii[:, None] * cj - cij[:, None] * ci) / det
    n = _cross(t_c, t_r)
    length = _norm(n)
    good &= length > 0
    return n / np.where(good, length, 1.0)[:, None], good


def _measured_spacing(look: _Lookup, key, u, u_win, step):
    """The angle to the nearest beam along one axis (``step``: one row or one column) within
    REACH cells, per cell, and the axis's unit direction on the sphere of beams (toward growing
    index); NaN where no beam is."""
    beam, delta = np.full(len(key), -1), np.zeros(len(key))
    for dist in range(1, REACH + 1):
        for sign in (1, -1):
            j = look.find(key, sign * dist * step[0], sign * dist * step[1])
            new = (beam < 0) & (j >= 0)
            beam[new], delta[new] = j[new], sign * dist
    has = beam >= 0
    ub = u_win[np.maximum(beam, 0)]
    a_k = np.where(has, _angle(u, ub) / np.maximum(np.abs(delta), 1.0), np.nan)
    e_k = _unit(ub - u * np.einsum("ij,ij->i", u, ub)[:, None]) * np.sign(delta)[:, None]
    return a_k, np.where(has[:, None], e_k, np.nan)


def _grid_spacing(u, s, st: _Stations):
    """Exact beam spacings of spherical grids: rows along elevation (the step), columns along
    azimuth (the step's chord at the point's elevation); and ``tilts(n, n . u) -> (n . e_r, n . e_c)``
    for the unit directions of elevation and azimuth at each beam.

    With ``w`` the scanner's up axis and ``sin(el) = u . w``: ``e_c = (w x u) / cos(el)``, ``e_r =
    u x e_c = (w - u sin(el)) / cos(el)`` (undefined at the zenith, where any direction is)."""
    # w = z: u . w and n . w are the z components. einsum's sums with the zero terms give the same
    # but for a zero's sign, which nothing below sees (it is squared, or divided and then squared)
    up = None if st.upright else st.up[s]
    sin_el = u[:, 2] if st.upright else np.einsum("ij,ij->i", u, up)
    cos_el = np.maximum(np.sqrt(np.clip(1.0 - sin_el ** 2, 0.0, 1.0)), 1e-12)
    de = np.array([g.elevation_step for g in st.grids])[s]
    sin_half = np.sin(np.array([g.azimuth_step for g in st.grids]) / 2)  # per station, then per point

    def tilts(n, nu):
        if st.upright:  # w = z: w . (u x n) is the cross product's z
            nw, wun = n[:, 2], u[:, 0] * n[:, 1] - u[:, 1] * n[:, 0]
        else:
            nw, wun = np.einsum("ij,ij->i", n, up), np.einsum("ij,ij->i", up, _cross(u, n))
        return (nw - nu * sin_el) / cos_el, wun / cos_el

    return [de, 2.0 * np.arcsin(np.clip(cos_el * sin_half[s], 0.0, 1.0))], tilts


def _fill_spacing(spacing, axis, u, s):
    """Measured spacings with the gaps filled: an axis without a beam takes the other's angle,
    a point without either its station's median over the block; and ``tilts(n, n . u) -> (n . e_r,
    n . e_c)`` for the frame ``e_c`` (measured along the columns; ``e_r x u`` where only the rows
    have a beam, any direction across the beam where neither has) and ``e_r = u x e_c``. Returns
    (spacings, tilts, points without either)."""
    a_r, a_c = spacing
    only_c, only_r = np.isnan(a_r) & ~np.isnan(a_c), np.isnan(a_c) & ~np.isnan(a_r)
    a_r, a_c = np.where(only_c, a_c, a_r), np.where(only_r, a_r, a_c)
    lone = np.isnan(a_r)
    for k in np.unique(s[lone]):
        vals = np.concatenate([a_r[(s == k) & ~lone], a_c[(s == k) & ~lone]])
        a_r[lone & (s == k)] = a_c[lone & (s == k)] = float(np.median(vals)) if len(vals) else 0.0
    e_r, e_c = axis
    e_c = np.where(only_r[:, None], _cross(np.nan_to_num(e_r), u), np.nan_to_num(e_c))
    across = _unit(_cross(u, np.where(np.abs(u[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])))
    e_c = np.where((np.abs(e_c).sum(axis=1) == 0)[:, None], across, e_c)
    e_c = _unit(e_c - u * np.einsum("ij,ij->i", u, e_c)[:, None])  # across the beam

    def tilts(n, nu):
        return np.einsum("ij,ij->i", n, _cross(u, e_c)), np.einsum("ij,ij->i", n, e_c)

    return [a_r, a_c], tilts, int(np.count_nonzero(lone))
