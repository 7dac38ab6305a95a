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

from dmrt.io.bundle import read_bundle
from dmrt.app.cli import main
from dmrt.errors import InputError
from dmrt.preprocess.labeling import LabelingConfig, energy, icm, knn_edges, winner_take_all
from dmrt.preprocess.candidates import find_candidates
from dmrt.preprocess.pipeline import PreprocessConfig
from dmrt.io.scene import load_scene
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
    # every phase's peak anonymous memory (Linux RssAnon) and peak resident set, MiB; the anonymous
    # part is at most the resident set (it excludes the memory-mapped arrays' file pages)
    anon, rss = b.meta["peak_anon_mb_per_phase"], b.meta["peak_rss_mb_after"]
    assert set(anon) == set(rss) and {"octree_s", "depthmaps_s", "labeling_s"} <= set(anon)
    assert all(0 < anon[k] <= rss[k] for k in anon)


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
    from dmrt.preprocess.proxies import choose_proxy_levels

    lods = [1_000, 4_000, 16_000, 64_000]
    assert choose_proxy_levels(lods, 64_000, PreprocessConfig(proxy_factor=40)) == 1  # 64x nearer 40x than 16x
    assert choose_proxy_levels(lods, 64_000, PreprocessConfig(proxy_factor=20)) == 2
    assert choose_proxy_levels(lods, 64_000, PreprocessConfig(proxy_count=5_000)) == 2
    assert choose_proxy_levels(lods, 64_000, PreprocessConfig(proxy_levels=3)) == 3
    assert choose_proxy_levels(lods, 64_000, PreprocessConfig(proxy_levels=9)) == 4


def _candidates(b, scene):
    cams = [c.relative_to(b.origin) for c in b.cameras]
    return find_candidates(b.proxy["positions"], b.proxy["normals"], b.proxy["hd_radii"], cams,
                           b.depth_map, scene.read_image, PreprocessConfig(), progress=False,
                           radii=b.proxy["radii"]), cams


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
    from dmrt.preprocess.labeling import candidate_data_costs
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


def test_frustum_culling_keeps_the_candidates(tiny_bundle, tiny_scene):
    """Projecting only the proxies of the buckets a photo's frustum meets (cull_points) finds the
    candidates of projecting all of them, colours included."""
    import dataclasses

    b = read_bundle(tiny_bundle)
    scene = load_scene(tiny_scene)
    cams = [c.relative_to(b.origin) for c in b.cameras]
    found = {cull: find_candidates(b.proxy["positions"], b.proxy["normals"], b.proxy["hd_radii"], cams, b.depth_map,
                                   scene.read_image, dataclasses.replace(PreprocessConfig(), cull_points=cull),
                                   progress=False, radii=b.proxy["radii"])
             for cull in (0, 64)}
    assert found[0].nnz > 0
    from dmrt.preprocess.frustum import Buckets

    buckets = Buckets.of(b.proxy["positions"], None, 64)
    kept = [buckets.visible(c.scaled(*b.depth_map(j).shape[::-1])).mean() for j, c in enumerate(cams)]
    assert min(kept) < 0.7  # each photo sees about its room: the culling leaves buckets out
    for name in ("indptr", "photos", "colors"):
        np.testing.assert_array_equal(getattr(found[64], name), getattr(found[0], name))


def test_rim_test_restricts_candidates(tiny_bundle, tiny_scene):
    """``candidate_rim_fraction``: a candidate must also see the disc's rim. Against the centre-only
    test: a subset of its pairs; every point keeps at least one candidate; the dropped pairs are
    those where a rim point falls on another surface of that photo's depth map (checked here
    directly for the dropped pairs: >= one of the six rim points off the map's surface)."""
    import dataclasses

    b = read_bundle(tiny_bundle)
    scene = load_scene(tiny_scene)
    rim, cams = _candidates(b, scene)
    centre = find_candidates(b.proxy["positions"], b.proxy["normals"], b.proxy["hd_radii"], cams, b.depth_map,
                             scene.read_image, dataclasses.replace(PreprocessConfig(), candidate_rim_fraction=0),
                             progress=False, radii=b.proxy["radii"])
    pts_c = np.repeat(np.arange(centre.n_points), centre.counts())
    pts_r = np.repeat(np.arange(rim.n_points), rim.counts())
    _, found = centre.lookup(pts_r, rim.photos)
    assert found.all()
    np.testing.assert_array_equal(rim.counts() > 0, centre.counts() > 0)
    _, kept = rim.lookup(pts_c, centre.photos)
    assert 0.01 < 1 - kept.mean() < 0.5  # some pairs go, most stay
    cfg = PreprocessConfig()
    p = b.proxy["positions"].astype(np.float64)
    n = b.proxy["normals"].astype(np.float64)
    for j in np.unique(centre.photos[~kept])[:3]:
        drop = pts_c[~kept & (centre.photos == j)]
        drop = drop[rim.counts()[drop] > 0]  # points that kept some candidate
        if len(drop) == 0:
            continue
        D = b.depth_map(j)
        cam = cams[j].scaled(D.shape[1], D.shape[0])
        u = np.cross(n[drop], [1.0, 0, 0])
        u[np.abs(n[drop, 0]) >= 0.9] = np.cross(n[drop][np.abs(n[drop, 0]) >= 0.9], [0, 1.0, 0])
        u /= np.linalg.norm(u, axis=1, keepdims=True)
        v = np.cross(n[drop], u)
        r = 0.8 * b.proxy["radii"][drop, None]
        missed = np.zeros(len(drop), bool)
        for a in np.linspace(0, 2 * np.pi, 6, endpoint=False):
            q = p[drop] + r * (np.cos(a) * u + np.sin(a) * v)
            uv, z = cam.project(q)
            ok = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] < D.shape[1]) & (uv[:, 1] >= 0) & (uv[:, 1] < D.shape[0])
            uvi = np.where(ok[:, None], uv, 0).astype(np.int64)
            d = np.where(ok, D[uvi[:, 1], uvi[:, 0]], 0)
            tol = cfg.occlusion_tolerance * b.proxy["hd_radii"][drop] + cfg.occlusion_texels * z / cam.fx
            missed |= ~(ok & (d > 0) & (np.abs(d - z) <= tol))
        assert missed.all()


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


@pytest.mark.gpu  # the preprocess command splats the depth maps
@pytest.mark.e2e
def test_interrupted_preprocess_leaves_no_bundle(tiny_scene, tmp_path):
    out = tmp_path / "b"
    proc = subprocess.Popen([sys.executable, "-m", "dmrt.app.cli", "preprocess", str(tiny_scene), "--out", str(out),
                             "--quiet", "--depthmap-width", "256"])
    deadline = time.time() + 120
    while not list((tmp_path / "b.partial" / "depthmaps").glob("*.exr")):  # mid depth maps
        assert time.time() < deadline and proc.poll() is None
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(60) != 0
    assert list(tmp_path.iterdir()) == []
