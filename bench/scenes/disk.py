"""The disk a synthetic scene takes end to end, its files and then ``dmrt preprocess`` on them, by
arithmetic from the formats the code writes (``docs/scene3.md`` gives the sums for ``paper-scene3``).

Preprocessing writes into the bundle's temporary folder and keeps its work files until the bundle
is complete (:func:`dmrt.preprocess.pipeline.preprocess`), but for the scan grid's, deleted once the
octree carries them:

* ``scan``: the scan grid's radii (and normals where the cloud has none) in input order, float32
  ``.npy`` (``--radii scan``, or ``auto`` with the ``scans.json`` every synthetic scene has), until
  the octree is built;
* ``octree``: every point once in its level files, a record of float32 positions (12 bytes), the
  normals the cloud or the scan carries (float32, 12), colours (3) and the scan's radii (4). While
  it is built the records move from spill files into level files, a bucket at a time; a bucket
  being selected (one per worker) or appended is held twice, ``(W + 1)`` buckets of the capacity
  of :class:`dmrt.preprocess.octree._Builder` (``0.4 M / W`` bytes of records and work arrays);
* ``attrs``: the kNN path's radii (and normals) in octree order, float32; it first spills every
  point's position, index and a flag (21 bytes) once, plus the halo copies (``KNN_HALO``). The
  scan path writes none: the later phases read the radii and normals from the octree;
* the bundle: depth maps (EXR, at most raw float32), low-resolution photos, ``proxy.npz``; the
  photos are hard links to the scene's (the work folder keeps both on one file system).

Each size is an upper bound or exact (the point files); :func:`check_free` refuses a run whose
peak the file system cannot hold before any of it is written.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass
from pathlib import Path

from dmrt.errors import InputError

GB = 1e9
PLY_HEADER = 512  # bytes: PointWriter's header is ~250
NPY_HEADER = 128  # bytes: numpy's format 1.0 header
# mesh.ply (~42 kB a room of the tiny scene), sparse/ (~250 bytes a photo), scans.json, synthetic.json
OTHER_FILES = (1 << 20, 128 << 10, 1 << 10)  # bytes: base, a room, a photo
# the kNN spill's halo copies, a share of the points: Scene 2's spill (1.25 cm halos around buckets
# of metres) measured 14.0 GB at 21 bytes a point of 683M (reports/scene2-h200/samples.tsv), under 5 %
KNN_HALO = 0.10
KNN_SPILL = 21  # bytes a point: float32 position, int64 index, uint8 flag (dmrt.preprocess.normals)
OCTREE_WORK = 112  # bytes a bucket point of work arrays beside two copies of its record (octree.py)
# proxies of a fixed level of detail: the suite's largest proxy set is the paper preset's LOD 5, 3.0M
MAX_PROXIES = 4_000_000
PROXY_BYTES = 36  # a proxy in proxy.npz: positions 12, normals 12, radii 4, hd_radii 4, labels 4


@dataclass
class DiskEstimate:
    """Bytes a scene and its preprocessing put on disk.

    Attributes
    ----------
    points : int
        Points of the scan.
    files : dict
        Bytes of each set of files when complete (``points.ply``, ``images/``, ...).
    moments : dict
        Bytes on disk at each moment of the run where they peak, everything of the run then
        present (the scene included), in run order.
    """

    points: int
    files: dict
    moments: dict

    @property
    def peak(self) -> tuple[str, int]:
        """The moment with the most bytes on disk, and those bytes."""
        return max(self.moments.items(), key=lambda kv: kv[1])

    @property
    def scene(self) -> int:
        """Bytes of the scene's files."""
        return self.moments["scene generated"]

    def lines(self) -> list[str]:
        """The estimate as a table for a terminal."""
        out = [f"{self.points:,} points"]
        out += [f"  {name:<44} {b / GB:8.2f} GB" for name, b in self.files.items()]
        out += [f"  on disk when {name:<31} {b / GB:8.2f} GB" for name, b in self.moments.items()]
        name, b = self.peak
        return out + [f"peak: {b / GB:.2f} GB ({b / 2 ** 30:.2f} GiB), when {name}"]

    def to_json(self) -> dict:
        return {"points": self.points, "files": self.files, "moments": self.moments,
                "peak": {"moment": self.peak[0], "bytes": self.peak[1]}}


def scene_files(config) -> dict:
    """Bytes of each set of files :func:`bench.scenes.synthetic.generate_scene` writes for
    ``config`` (a :class:`~bench.scenes.synthetic.SynthConfig`): ``points.ply`` exactly (header
    bound aside), the PNG photos at most raw RGB plus 1 %, the rest (:data:`OTHER_FILES`) bounded."""
    from bench.scenes.synthetic import scan_points
    from dmrt.io.pointcloud import PointWriter

    record = PointWriter("points.ply", config.write_normals, True, config.float_positions,
                         config.normals_type).dtype.itemsize
    w, h = config.photo_size
    base, room, photo = OTHER_FILES
    return {"points.ply": PLY_HEADER + scan_points(config) * record,
            # PNG stores raw rows behind a filter byte, in deflate blocks of <= 64 kB with 5 bytes each
            "images/": config.photos * (int(w * h * 3 * 1.01) + h + 1024),
            "other scene files": base + room * config.rooms[0] * config.rooms[1] + photo * config.photos}


def octree_record(normals: bool, radii: bool) -> int:
    """Bytes of an octree record: float32 positions, float32 normals, uchar colours, float32 radii."""
    return 12 + 12 * normals + 3 + 4 * radii


def estimate(config, preprocess=None, workers: int | None = None) -> DiskEstimate:
    """The disk the scene of ``config`` (a :class:`~bench.scenes.synthetic.SynthConfig`) and
    ``dmrt preprocess`` on it with ``preprocess`` (a
    :class:`~dmrt.preprocess.config.PreprocessConfig`, default: the defaults) on ``workers``
    processes (default: one per core, as ``dmrt preprocess``) take (module docstring). ``files``:
    ``points.ply``, ``images/``, ``other scene files``, then the work folder's ``scan/``,
    ``octree/``, ``octree: buckets held twice``, ``attrs/``, ``kNN spill``, and the ``bundle``."""
    from bench.scenes.synthetic import scan_points
    from dmrt.preprocess.config import PreprocessConfig
    from dmrt.preprocess.parallel import default_workers

    pre = preprocess or PreprocessConfig()
    workers = max(1, workers or default_workers())
    n = scan_points(config)
    scan = pre.radii != "knn"  # every synthetic scene has its scans.json
    normals = "input" if config.write_normals else "scan" if scan else "knn"
    record = octree_record(normals != "knn", scan)
    capacity = max(1024, int(pre.memory_limit_mb * 2 ** 20 / workers * 0.4 / (2 * record + OCTREE_WORK)))
    w, h = config.photo_size
    depth_h, low_h = (max(1, round(width * h / w)) for width in (pre.depthmap_width, pre.lowres_width))
    proxies = pre.proxy_count or (min(n, MAX_PROXIES) if pre.proxy_levels else int(n / pre.proxy_factor))
    files = {
        **scene_files(config),
        "scan/": scan * (NPY_HEADER + 4 * n + (normals == "scan") * (NPY_HEADER + 12 * n)),
        "octree/": n * record + (1 << 20),  # + octree.json
        "octree: buckets held twice": min(n, (workers + 1) * capacity) * record,
        "attrs/": (not scan) * (NPY_HEADER + 4 * n + (normals == "knn") * (NPY_HEADER + 12 * n)),
        "kNN spill": (not scan) * int(n * KNN_SPILL * (1 + KNN_HALO)),
        "bundle": config.photos * (pre.depthmap_width * depth_h * 4 + pre.lowres_width * low_h * 3 + 2048)
                  + proxies * PROXY_BYTES,
    }
    files = {k: int(b) for k, b in files.items() if b}
    scene = files["points.ply"] + files["images/"] + files["other scene files"]
    octree = scene + files["octree/"]
    # scan/ is read by the octree build, and deleted when it ends
    moments = {"scene generated": scene,
               "octree built": octree + files.get("scan/", 0) + files["octree: buckets held twice"]}
    if not scan:
        moments["kNN spill written"] = octree + files["kNN spill"] + files["attrs/"]
    moments["bundle written"] = octree + files.get("attrs/", 0) + files["bundle"]
    return DiskEstimate(n, files, moments)


def free_bytes(folder) -> int:
    """Free bytes of the file system that holds ``folder`` (or its nearest existing parent)."""
    path = Path(folder).resolve()
    while not path.exists():
        path = path.parent
    return shutil.disk_usage(path).free


def check_free(needed: int, folder, what: str) -> None:
    """Raise :class:`InputError` naming ``folder`` when its file system has fewer than ``needed``
    bytes free for ``what``."""
    free = free_bytes(folder)
    if free < needed:
        raise InputError(folder, f"too little free disk for {what}: {needed / GB:.1f} GB needed at the peak, "
                                 f"{free / GB:.1f} GB free (bench/scenes/disk.py; python -m bench.workspace "
                                 f"PRESET WORK --dry-run prints the estimate)")
