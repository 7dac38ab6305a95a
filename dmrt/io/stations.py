"""The scan structure of a cloud: which scanner station took each point, and on which angular grid.

A terrestrial laser scanner fires beams on a grid of directions from each station, so every point
has a station, a row and a column. Preprocessing takes splat radii and normals from that grid where
it is known (:mod:`dmrt.preprocess.scangrid`) instead of searching nearest neighbours. Two inputs
carry it:

* ``scans.json`` beside ``points.ply`` (written by the synthetic scanner, :mod:`bench.scenes.synthetic`):
  per station its position, its consecutive run of the cloud's points (file order) and its
  spherical grid. A point's row and column follow from its direction, so the cloud itself holds no
  extra byte::

      {"format": "dmrt-scans", "version": 1,
       "stations": [{"position": [x, y, z],              world metres
                     "rotation": [[...], [...], [...]],  scanner -> world (optional; identity)
                     "points": [first, stop],            records first .. stop-1 of the cloud
                     "grid": {"azimuth_start": a0, "azimuth_step": da, "columns": nc,
                              "elevation_start": e0, "elevation_step": de, "rows": nr}}, ...]}

  Column ``c`` looks at azimuth ``a0 + c da`` (from the scanner's +x toward +y), row ``r`` at
  elevation ``e0 + r de`` (up from its xy plane), radians. A grid whose columns span the full
  circle wraps (column ``nc - 1`` neighbours column 0).
* E57 scans with ``rowIndex`` and ``columnIndex`` in their point prototype (structured scans):
  per point its scan (:attr:`~dmrt.io.pointcloud.PointCloud.scan_index`) and grid cell
  (:attr:`~dmrt.io.pointcloud.PointCloud.grid`); the scan's pose gives the station. The angular
  steps are not in the file: they are measured between neighbouring beams.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from dmrt.errors import InputError

FORMAT, VERSION = "dmrt-scans", 1
MAX_INDEX = 1 << 24  # rows and columns fit 24 bits each: (station, row, column) packs into an int64


@dataclass(frozen=True)
class SphericalGrid:
    """A station's beam directions: ``columns`` azimuths x ``rows`` elevations, radians."""

    azimuth_start: float
    azimuth_step: float
    columns: int
    elevation_start: float
    elevation_step: float
    rows: int

    @property
    def wraps(self) -> bool:
        """The columns go round the full circle: the last neighbours the first."""
        return self.columns * self.azimuth_step >= 2 * math.pi - 0.5 * self.azimuth_step

    def cells(self, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The grid cells of unit beam directions in the scanner's frame.

        Parameters
        ----------
        directions : (n, 3) float64 unit vectors, scanner frame

        Returns
        -------
        row, column : (n,) int64, the nearest cell (row clipped to the grid).
        off : (n,) bool, the direction lies more than a quarter step from that cell's centre
        (not a beam of this grid).
        """
        az = np.arctan2(directions[:, 1], directions[:, 0])
        el = np.arcsin(np.clip(directions[:, 2], -1.0, 1.0))
        fc = (az - self.azimuth_start) / self.azimuth_step
        if self.wraps:  # azimuth is periodic: measure from the start, in [0, 2 pi)
            fc = np.mod(az - self.azimuth_start, 2 * math.pi) / self.azimuth_step
        fr = (el - self.elevation_start) / self.elevation_step
        col, row = np.rint(fc), np.rint(fr)
        off = (np.abs(fc - col) > 0.25) | (np.abs(fr - row) > 0.25) | (row < 0) | (row >= self.rows)
        col = col.astype(np.int64)
        if self.wraps:
            col %= self.columns
        else:
            off |= (col < 0) | (col >= self.columns)
        return np.clip(row, 0, self.rows - 1).astype(np.int64), np.clip(col, 0, self.columns - 1), off


@dataclass(frozen=True)
class Station:
    """One scanner station.

    Attributes
    ----------
    position : (3,) float64, world metres.
    rotation : (3, 3) float64, scanner frame -> world.
    points : (first, stop) or None
        Its points are the cloud's records ``first .. stop - 1`` (``scans.json``); None: given
        per point by ``PointCloud.scan_index`` (E57).
    grid : SphericalGrid or None
        Its beam directions (``scans.json``); None: cells given per point by ``PointCloud.grid``.
    line : int or None
        The most beams of one scan line (a row or a column, whichever the file runs along):
        how far in file order a point's grid neighbours can lie. None: unknown.
    """

    position: np.ndarray
    rotation: np.ndarray
    points: tuple[int, int] | None = None
    grid: SphericalGrid | None = None
    line: int | None = None


@dataclass
class ScanStructure:
    """The stations of a cloud and where its per-point structure comes from.

    Attributes
    ----------
    stations : list of Station
    source : {"scans.json", "e57"}
        ``scans.json``: stations by point runs, cells from the directions; ``e57``: stations and
        cells per point (``PointCloud.scan_index`` and ``PointCloud.grid``).
    """

    stations: list[Station] = field(default_factory=list)
    source: str = "scans.json"

    @property
    def positions(self) -> np.ndarray:
        """(s, 3) float64 station positions, world metres."""
        return np.array([s.position for s in self.stations], np.float64).reshape(-1, 3)

    def line(self) -> int | None:
        """The longest scan line of any station (None if one is unknown)."""
        lines = [s.line for s in self.stations]
        return None if any(v is None for v in lines) else max(lines)


def _grid_json(g: SphericalGrid) -> dict:
    return {"azimuth_start": g.azimuth_start, "azimuth_step": g.azimuth_step, "columns": g.columns,
            "elevation_start": g.elevation_start, "elevation_step": g.elevation_step, "rows": g.rows}


def write_scans_json(path, stations: list[Station]) -> None:
    """Write ``stations`` (each with ``points`` and ``grid``) as ``scans.json`` (module docstring)."""
    doc = {"format": FORMAT, "version": VERSION, "stations": [
        {"position": [float(v) for v in s.position], "rotation": np.asarray(s.rotation, float).tolist(),
         "points": [int(s.points[0]), int(s.points[1])], "grid": _grid_json(s.grid)} for s in stations]}
    Path(path).write_text(json.dumps(doc, indent=1))


def read_scans_json(path, n_points: int) -> ScanStructure:
    """The stations of ``scans.json``, checked against a cloud of ``n_points`` points.

    Raises
    ------
    InputError
        Naming the file and the field: not JSON, another format or version, a station without a
        finite position, a rotation that is not 3 x 3 orthonormal, point runs that do not cover
        the cloud's records in order, a grid with non-positive or non-finite steps or sizes.
    """
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except (OSError, ValueError) as e:
        raise InputError(path, f"not readable JSON: {e}") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise InputError(path, f"field 'format' must be {FORMAT!r}")
    if doc.get("version") != VERSION:
        raise InputError(path, f"field 'version' is {doc.get('version')!r}, this reader knows {VERSION}")
    entries = doc.get("stations")
    if not isinstance(entries, list) or not entries:
        raise InputError(path, "field 'stations' must be a non-empty list")
    stations, expect = [], 0
    for i, e in enumerate(entries):
        where = f"stations[{i}]"
        try:
            pos = np.asarray(e["position"], np.float64).reshape(3)
            rot = np.asarray(e.get("rotation", np.eye(3)), np.float64).reshape(3, 3)
            first, stop = (int(v) for v in e["points"])
            g = e["grid"]
            grid = SphericalGrid(float(g["azimuth_start"]), float(g["azimuth_step"]), int(g["columns"]),
                                 float(g["elevation_start"]), float(g["elevation_step"]), int(g["rows"]))
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(path, f"{where}: missing or malformed field ({exc})") from None
        if not (np.isfinite(pos).all() and np.isfinite(rot).all()):
            raise InputError(path, f"{where}: non-finite position or rotation")
        if not np.allclose(rot @ rot.T, np.eye(3), atol=1e-6):
            raise InputError(path, f"{where}.rotation is not a rotation (not orthonormal)")
        if first != expect or stop < first:
            raise InputError(path, f"{where}.points is [{first}, {stop}]: the runs must follow each other "
                                   f"from record 0 (expected it to start at {expect})")
        steps = (grid.azimuth_step, grid.elevation_step)
        if not all(math.isfinite(v) and v > 0 for v in steps) or not (0 < grid.rows < MAX_INDEX) \
                or not (0 < grid.columns < MAX_INDEX) or not all(map(math.isfinite, (grid.azimuth_start,
                                                                                   grid.elevation_start))):
            raise InputError(path, f"{where}.grid: steps must be finite and > 0, rows and columns in "
                                   f"1..{MAX_INDEX - 1}")
        stations.append(Station(pos, rot, (first, stop), grid, grid.columns))
        expect = stop
    if expect != n_points:
        raise InputError(path, f"the stations' point runs end at record {expect}, the cloud has {n_points} points")
    return ScanStructure(stations, "scans.json")


def e57_structure(scans) -> ScanStructure | None:
    """The structure of E57 scans (:class:`~dmrt.io.e57.E57Scan`), or None unless every scan is
    structured (has ``rowIndex`` and ``columnIndex``)."""
    if not scans or not all(s.structured for s in scans):
        return None
    stations = [Station(np.asarray(s.translation, np.float64), np.asarray(s.rotation, np.float64),
                        line=None if s.grid_size is None else max(s.grid_size) + 1) for s in scans]
    return ScanStructure(stations, "e57")
