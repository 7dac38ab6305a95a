"""Preprocessing end to end on the tiny scene, against Embree and against simpler labelings."""

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest
from scipy import ndimage
from scipy.spatial import cKDTree

from dmrt.bundle import read_bundle
from dmrt.cli import main
from dmrt.errors import InputError
from dmrt.labeling import LabelingConfig, energy, icm, knn_edges, winner_take_all
from dmrt.preprocess import PreprocessConfig, find_candidates
from dmrt.scene import load_scene
from reference.raycast import MeshRaycaster


def test_bundle_contents(tiny_bundle, tiny_scene):
    b = read_bundle(tiny_bundle)
    scene = load_scene(tiny_scene)
    assert len(b.cameras) == len(scene.cameras)
    np.testing.assert_array_equal(b.origin, scene.origin)
    c = b.meta["counts"]
    assert c["points"] == scene.n_points and c["proxies"] == len(b.proxy["positions"])
    # |P_HD| / |P_LD| reported per level count, decreasing to 1 (all levels = P_HD)
    f = c["subsampling_factors"]
    assert all(a >= b_ for a, b_ in zip(f, f[1:])) and f[-1] == 1.0
    target = PreprocessConfig().proxy_factor  # the level count whose factor is nearest the target
    k = c["proxy_levels"]
    assert all(abs(np.log(f[k - 1] / target)) <= abs(np.log(x / target)) for x in f)
    assert b.depth_map(0).shape == (171, 256)
    assert b.image(0, low=True).shape == (171, 256, 3)
    assert len(b.meta["labeling"]["energy_per_sweep"]) >= 2
    assert "preprocess" in b.meta["parameters"] and b.meta["timings"]["total_s"] > 0


def test_depth_maps_match_embree(tiny_bundle, tiny_scene):
    """Each depth map vs the Embree depth of the mesh from the same camera."""
    b = read_bundle(tiny_bundle)
    scene = load_scene(tiny_scene)
    rc = MeshRaycaster.from_file(scene.mesh_path, origin=scene.origin)
    meta = json.loads((tiny_scene / "synthetic.json").read_text())
    stations = np.array(meta["stations"])
    hd = scene.read_points().positions
    tree = cKDTree(hd - scene.origin)
    for j in range(0, len(b.cameras), 2):
        cam = b.cameras[j]
        dm = b.depth_map(j)
        truth, face, normal = rc.cast_camera(cam.scaled(dm.shape[1], dm.shape[0]))
        # Silhouettes: within 2 px of a depth jump > 5 cm the two surfaces legitimately mix.
        jump = np.maximum(ndimage.maximum_filter(truth, 5) - truth, truth - ndimage.minimum_filter(truth, 5)) > 0.05
        dirs, c = cam.scaled(dm.shape[1], dm.shape[0]).pixel_rays()
        pts = c + dirs * truth.reshape(-1, 1)
        # Only surface the scanner saw can be in a depth map: a pixel counts where some station
        # has a clear line of sight to its surface point (lifted 1 cm off the surface).
        lifted = pts + 0.01 * normal.reshape(-1, 3)
        scanned = np.zeros(len(pts), bool)
        for s in stations:
            scanned |= rc.visible(lifted, s)
        valid = (truth > 0) & ~jump & scanned.reshape(truth.shape)
        coverage = np.mean(dm[valid] > 0)
        assert coverage >= 0.98, (j, coverage)
        both = valid & (dm > 0)
        spacing = tree.query(pts[both.ravel()] - scene.origin, k=2)[0][:, 1]  # local point spacing
        dz = np.abs(dm[both] - truth[both])
        assert np.median(dz / spacing) < 0.5, (j, np.median(dz), np.median(spacing))


def test_proxy_level_choice():
    from dmrt.preprocess import choose_proxy_levels

    lods = [1_000, 4_000, 16_000, 64_000]
    assert choose_proxy_levels(lods, 64_000, PreprocessConfig(proxy_factor=40)) == 1  # 64x nearer 40x than 16x
    assert choose_proxy_levels(lods, 64_000, PreprocessConfig(proxy_factor=20)) == 2
    assert choose_proxy_levels(lods, 64_000, PreprocessConfig(proxy_count=5_000)) == 2
    assert choose_proxy_levels(lods, 64_000, PreprocessConfig(proxy_levels=3)) == 3
    assert choose_proxy_levels(lods, 64_000, PreprocessConfig(proxy_levels=9)) == 4


def _candidates(b, scene):
    cams = [c.relative_to(b.origin) for c in b.cameras]
    return find_candidates(b.proxy["positions"], b.proxy["normals"], b.proxy["hd_radii"], cams,
                           b.depth_map, scene.read_image, PreprocessConfig(), progress=False), cams


def test_labels_are_candidates_and_graph_cut_beats_wta_and_icm(tiny_bundle, tiny_scene):
    b = read_bundle(tiny_bundle)
    scene = load_scene(tiny_scene)
    cands, cams = _candidates(b, scene)
    labels = b.proxy["labels"]
    has = cands.counts() > 0
    assert has.mean() > 0.6  # most proxies are seen by some photo
    np.testing.assert_array_equal(labels >= 0, has)  # -1 exactly where no photo sees the point
    _, found = cands.lookup(np.flatnonzero(has), labels[has])
    assert found.all()  # every label is one of its point's candidates: 100 %
    # Energies on the same graph and costs as label_points used.
    from dmrt.labeling import candidate_data_costs
    cfg = LabelingConfig()
    centers = np.array([c.center for c in cams])
    focal = np.array([np.sqrt(c.fx * c.fy) for c in cams])
    costs = candidate_data_costs(b.proxy["positions"], b.proxy["normals"], centers, focal, cands, cfg)
    edges = knn_edges(b.proxy["positions"], cfg.k_neighbors)
    e_cut = energy(labels, costs, edges, cands, cfg)[0]
    wta = winner_take_all(costs, cands)
    e_wta = energy(wta, costs, edges, cands, cfg)[0]
    e_icm = energy(icm(wta, costs, edges, cands, cfg), costs, edges, cands, cfg)[0]
    assert e_cut < e_icm <= e_wta, (e_cut, e_icm, e_wta)
    sweeps = b.meta["labeling"]["energy_per_sweep"]
    assert all(a >= b_ - 1e-9 for a, b_ in zip(sweeps, sweeps[1:]))


def test_existing_bundle_refused_without_force(tiny_bundle, tiny_scene, capsys):
    assert main(["preprocess", str(tiny_scene), "--out", str(tiny_bundle), "--quiet"]) == 2
    assert "--force" in capsys.readouterr().err


def test_broken_bundles_name_file_and_field(tiny_bundle, tmp_path):
    import shutil

    bad = tmp_path / "b"
    shutil.copytree(tiny_bundle, bad)
    meta = json.loads((bad / "bundle.json").read_text())
    (bad / "bundle.json").write_text(json.dumps({**meta, "version": 99}))
    with pytest.raises(InputError, match="bundle.json.*version"):
        read_bundle(bad)
    (bad / "bundle.json").write_text(json.dumps(meta))
    (bad / meta["depthmaps"][3]).unlink()
    with pytest.raises(InputError, match="photo_0003.exr.*missing"):
        read_bundle(bad)
    with pytest.raises(InputError, match="bundle.json missing"):
        read_bundle(tmp_path)
    shutil.copytree(tiny_bundle, tmp_path / "c")
    (tmp_path / "c" / "proxy.npz").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(InputError, match="proxy.npz"):
        read_bundle(tmp_path / "c").proxy


def test_interrupted_preprocess_leaves_no_bundle(tiny_scene, tmp_path):
    out = tmp_path / "b"
    proc = subprocess.Popen([sys.executable, "-m", "dmrt.cli", "preprocess", str(tiny_scene), "--out", str(out),
                             "--quiet", "--depthmap-width", "256"])
    deadline = time.time() + 120
    while not list((tmp_path / "b.partial" / "depthmaps").glob("*.exr")):  # mid depth maps
        assert time.time() < deadline and proc.poll() is None
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(60) != 0
    assert list(tmp_path.iterdir()) == []
