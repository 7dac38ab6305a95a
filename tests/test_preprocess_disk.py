"""Preprocessing's disk (issue #40, item 4; docs/scene3.md): on the scan path the scan grid's work
folder is deleted once the octree carries its radii and normals, and the later phases read the radii
from the octree (no copy in ``work/attrs``); bundle.json records the bytes each phase left on disk."""

import numpy as np
from scipy.spatial import cKDTree

from dmrt.io.bundle import read_bundle
from dmrt.io.scene import load_scene
from dmrt.preprocess import pipeline
from dmrt.preprocess.config import PreprocessConfig
from dmrt.preprocess.scangrid import scan_attributes

SCAN_RECORD = 12 + 12 + 3 + 4  # bytes an octree point: float32 positions, scan normals, colours, radii
OCTREE_JSON = 64 << 10  # bytes: octree.json is ~2 kB


def test_scan_work_folder_is_gone_after_the_octree(tiny_scene, tmp_path, monkeypatch):
    # memory limits that take the out-of-core paths: octree buckets, depth maps streamed in parts
    config = PreprocessConfig(radii="scan", depthmap_width=64, memory_limit_mb=2, resident_mb=1)
    seen = {}

    def watch(name, phase):  # the real phase, after a look at the work folder it starts from
        def run(*args, **kwargs):
            work, = tmp_path.glob("*/work")  # in the bundle's temporary folder
            seen[name] = sorted(p.relative_to(work).as_posix() for p in work.iterdir())
            return phase(*args, **kwargs)
        monkeypatch.setattr(pipeline, phase.__name__, run)

    watch("normals", pipeline.normals_radii_phase)
    watch("depth", pipeline.render_depth_phase)
    bundle = read_bundle(pipeline.preprocess(tiny_scene, tmp_path / "out", config, progress=False))
    assert seen == {"normals": ["octree"], "depth": ["octree"]}  # no scan/, no attrs/
    assert not (tmp_path / "out" / "work").exists()

    # the bundle is complete: every map and photo, proxies with the radii the scan gave their points
    scene = load_scene(tiny_scene)
    n = scene.n_points
    meta = bundle.meta
    assert meta["counts"]["points"] == n and meta["normals_radii"]["method"] == "scan"
    assert meta["octree"]["n_buckets"] > 1 and meta["depthmap_splats"]["modes"] == ["streamed"]
    for j in range(len(scene.cameras)):
        assert (bundle.depth_map(j) > 0).mean() > 0.5
        assert bundle.image(j).shape[2] == bundle.image(j, low=True).shape[2] == 3
    scan = scan_attributes(scene.point_range(), scene.scan_structure, n, tmp_path / "scan", scale=config.radius_scale)
    radii = np.load(tmp_path / "scan" / "radii.npy")
    # the octree stores positions relative to the origin rounded to float32: the same rounding finds them
    local = (scene.read_points().positions - scene.origin).astype(np.float32)
    dist, idx = cKDTree(local).query(bundle.proxy["positions"])
    assert scan.normals and dist.max() == 0
    np.testing.assert_array_equal(bundle.proxy["hd_radii"], radii[idx])

    # bytes on disk after each phase: the scan's radii and normals (16 bytes a point) until the
    # octree is built, then the octree's points alone, and nothing added by phase 2
    disk = meta["disk_bytes_after"]
    assert disk["scan_grid_s"] >= 16 * n
    assert SCAN_RECORD * n <= disk["octree_s"] == disk["normals_radii_s"] < SCAN_RECORD * n + OCTREE_JSON
    assert disk["depthmaps_s"] > disk["normals_radii_s"]  # the maps, in the bundle's folder


def test_knn_path_records_its_attrs(tiny_bundle):
    """The kNN path (the default) still writes its radii and normals in octree order, 16 bytes a
    point, and bundle.json says so."""
    meta = read_bundle(tiny_bundle).meta
    disk, n = meta["disk_bytes_after"], meta["counts"]["points"]
    assert meta["normals_radii"]["method"] == "knn" and "scan_grid_s" not in disk
    assert meta["normals_radii"]["kernel"].startswith("pykdtree")  # the kNN kernel recorded
    assert disk["normals_radii_s"] - disk["octree_s"] == 16 * n + 2 * 128  # two .npy headers of 128 bytes
