"""Radii and normals from the scan's grid (dmrt.preprocess.scangrid): range x angular step on the
synthetic scanner's grid, normals against the mesh's true ones, structured E57 scans (synthetic and
the real pumpA file), and the pipeline's choice of method with the bundles it makes."""

import json
import math
import re
import os
import shutil

import numpy as np
import pytest

from dmrt.errors import ConfigError, InputError
from dmrt.io import e57, pointcloud, stations
from dmrt.io.bundle import read_bundle
from dmrt.io.scene import load_scene
from dmrt.preprocess.config import PreprocessConfig
from dmrt.preprocess.pipeline import preprocess
from dmrt.preprocess.scangrid import STRETCH_MAX, scan_attributes, scan_phase
from helpers import assert_bundles_equal
from test_bad_input import assert_bad_input
from reference.raycast import MeshRaycaster
from test_e57 import REAL, PUMP, needs_real, quaternion, rotation, write_raw_scans

SCALE = 1.5  # the pipeline's --radius-scale


def _run(scene, out, chunk=1_000_000, threads=None, normals=None):
    r = scan_attributes(scene.point_range(chunk), scene.scan_structure, scene.n_points, out, scale=SCALE,
                        normals=normals, threads=threads)
    nrm = np.load(out / "normals.npy") if r.normals else None
    return r, nrm, np.load(out / "radii.npy")


@pytest.fixture(scope="module")
def tiny(tiny_scene, tmp_path_factory):
    """The tiny scene's scan results, the points' stations, beams and the true normals (the mesh
    face each beam hit, Embree)."""
    scene = load_scene(tiny_scene, check_images=False)
    result, nrm, rad = _run(scene, tmp_path_factory.mktemp("scan"))
    st = scene.scan_structure
    station = np.repeat(np.arange(len(st.stations)), [s.points[1] - s.points[0] for s in st.stations])
    beam = scene.read_points().positions - st.positions[station]
    rc = MeshRaycaster.from_file(scene.mesh_path, origin=scene.origin)
    truth = np.zeros_like(beam)
    for k, s in enumerate(st.positions):
        sel = station == k
        _, face = rc.intersect(s, beam[sel] * 1.05)  # just past the noisy point: its face
        assert (face >= 0).all()
        truth[sel] = rc.face_normals[face]
    return dict(scene=scene, result=result, normals=nrm, radii=rad, station=station, beam=beam, truth=truth)


def test_synthetic_scene_records_its_grid(tiny_scene):
    """scans.json: one station per scanner position, runs covering the cloud, and every point's
    direction on a beam of its station's grid."""
    meta = json.loads((tiny_scene / "synthetic.json").read_text())
    st = load_scene(tiny_scene, check_images=False).scan_structure
    assert st.source == "scans.json"
    np.testing.assert_allclose(st.positions, meta["stations"], rtol=0, atol=1e-9)
    g = st.stations[0].grid
    assert g.wraps and g.azimuth_step == g.elevation_step and g.columns * g.rows > 90_000


def test_radii_are_range_times_step(tiny):
    """Radius = scale x range x half the grid cell's longer diagonal on the surface: with the
    grid's step ``h`` both ways at the horizon and a surface facing the beam, scale x range x h / sqrt(2)."""
    g = tiny["scene"].scan_structure.stations[0].grid
    h = g.elevation_step
    beam, nrm, rad = tiny["beam"], tiny["normals"].astype(np.float64), tiny["radii"]
    rng = np.linalg.norm(beam, axis=1)
    u = beam / rng[:, None]
    # the definition, written out independently: the steps to the next beam along elevation (h)
    # and azimuth (the chord of h at the point's elevation), moved along the beam onto the surface
    # (at most 4 times longer), span the cell; its longer diagonal, halved, times the range
    e_c = np.cross([0.0, 0.0, 1.0], u)
    e_c /= np.linalg.norm(e_c, axis=1, keepdims=True)
    e_r = np.cross(u, e_c)
    a_c = 2 * np.arcsin(np.sqrt(1 - u[:, 2] ** 2) * np.sin(h / 2))
    sides = []
    for a_k, e in ((h, e_r), (a_c, e_c)):
        limit = math.sqrt(STRETCH_MAX ** 2 - 1)
        t = np.clip(np.sum(nrm * e, axis=1) / np.sum(nrm * u, axis=1), -limit, limit)
        sides.append(np.reshape(a_k, (-1, 1)) * (e - u * t[:, None]))
    diagonal = np.maximum(*(np.linalg.norm(sides[0] + sign * sides[1], axis=1) for sign in (1, -1)))
    want = SCALE * rng * diagonal / 2
    # float32 results (7 digits) of float64 arithmetic in another order
    np.testing.assert_allclose(rad, want, rtol=2e-5)
    # the plain case: near the horizon, on surfaces facing the beam (the true normal and the
    # estimated one within 3 degrees of it and of each other: not at an edge)
    cos3 = math.cos(math.radians(3))
    facing = (np.abs(u[:, 2]) < 0.05) & (np.abs(np.sum(tiny["truth"] * u, axis=1)) > cos3) \
        & (np.abs(np.sum(tiny["truth"] * nrm, axis=1)) > cos3)
    assert facing.sum() > 200
    ratio = rad[facing] / (SCALE * rng[facing] * h / math.sqrt(2))
    # |elevation| < 0.05 shortens the azimuth spacing by < 0.07 %; an estimated normal 6 degrees
    # off the beam stretches the spacing by at most 1 / cos(6 deg) = 1.0055
    assert np.all((ratio > 0.999) & (ratio < 1.0055)), (ratio.min(), ratio.max())


def test_normals_from_the_grid_match_the_mesh(tiny):
    """Against the true face normals of the mesh: as close as the kNN plane fit (measured 0.8 and
    9 degrees at the median and 90th percentile here, kNN 1.2 and 9.6), all facing their station."""
    nrm, truth, beam = tiny["normals"], tiny["truth"], tiny["beam"]
    angle = np.degrees(np.arccos(np.clip(np.abs(np.sum(nrm * truth, axis=1)), 0, 1)))
    # the median is the planes' noise (2 mm over 4 cm spacings); the 90th percentile takes in the
    # edges and corners, where a window of 5 x 5 beams spans two faces
    assert np.median(angle) < 2.0 and np.percentile(angle, 90) < 12.0, np.percentile(angle, [50, 90])
    assert np.all(np.sum(nrm * beam, axis=1) < 0)  # toward the station
    counts = tiny["result"].counts
    assert counts["off_grid_points"] == 0 and counts["fallback_normals"] < 0.01 * len(nrm)


def test_results_do_not_depend_on_chunks_threads_or_processes(tiny, tmp_path):
    """Chunks of 6,553 points (a 6 MiB budget on one thread; lines of 475 beams: halos of 3 lines
    cross chunks and stations), and 3 record ranges in 3 worker processes, give the same numbers
    as one chunk on all cores, bit for bit."""
    from dmrt.preprocess.parallel import open_executor

    scene = tiny["scene"]
    scan_attributes(scene.point_range(), scene.scan_structure, scene.n_points, tmp_path / "a", scale=SCALE,
                    threads=1, memory_limit_mb=6)
    assert np.array_equal(np.load(tmp_path / "a" / "normals.npy"), tiny["normals"])
    assert np.array_equal(np.load(tmp_path / "a" / "radii.npy"), tiny["radii"])
    with open_executor(None, workers=3) as ex:
        r = scan_attributes(scene.point_range(30_000), scene.scan_structure, scene.n_points, tmp_path / "b",
                            scale=SCALE, executor=ex)
    assert np.array_equal(np.load(tmp_path / "b" / "normals.npy"), tiny["normals"])
    assert np.array_equal(np.load(tmp_path / "b" / "radii.npy"), tiny["radii"])
    assert r.counts == tiny["result"].counts


def test_lookups_give_what_the_images_give(tiny, tmp_path, monkeypatch):
    """A file not in scan-line order is summed by lookups instead of images: the same numbers."""
    from dmrt.preprocess import scangrid

    monkeypatch.setattr(scangrid, "_DENSE_SLACK", -1 << 40)
    _, nrm, rad = _run(tiny["scene"], tmp_path, chunk=50_000)
    assert np.array_equal(nrm, tiny["normals"]) and np.array_equal(rad, tiny["radii"])


def test_input_normals_are_kept(tiny, tmp_path):
    """A cloud with normals: radii only, the input's normals giving the stretch (here the scan's
    own normals, written with the points: the same radii)."""
    from dmrt.io.pointcloud import PointCloud, write_points

    scene = tiny["scene"]
    pc = scene.read_points()
    root = tmp_path / "scene"
    root.mkdir()
    write_points(root / "points.ply", PointCloud(pc.positions, tiny["normals"], pc.colors))
    with pytest.raises(ValueError, match="needs normals in the input"):
        _run(scene, tmp_path / "none", normals=False)
    ply = pointcloud.point_range(root / "points.ply")
    r = scan_attributes(ply, scene.scan_structure, scene.n_points, tmp_path / "out", scale=SCALE)
    assert not r.normals and not (tmp_path / "out" / "normals.npy").exists() and r.meta()["normals"] == "input"
    # float32 normals normalised again: radii within float32 rounding
    np.testing.assert_allclose(np.load(tmp_path / "out" / "radii.npy"), tiny["radii"], rtol=1e-5)


def _structured_e57(path, noise=0.0, seed=0):
    """A posed scanner in a box room (x -3..4, y -2.5..3, z -1.5..1.5 m in its frame) on a grid of
    0.015 rad azimuths x 0.004 rad elevations, written column after column with rowIndex and
    columnIndex, a patch of beams flagged without return. Returns the truth per valid point."""
    da, de = 0.015, 0.004
    cols, rows = int(2 * np.pi / da) + 1, 350
    az = np.arange(cols) * da
    el = -1.0 + np.arange(rows) * de
    C, R = np.meshgrid(np.arange(cols), np.arange(rows), indexing="ij")  # column-major file order
    A, E = az[C].ravel(), el[R].ravel()
    d = np.stack([np.cos(E) * np.cos(A), np.cos(E) * np.sin(A), np.sin(E)], 1)
    lo, hi = np.array([-3.0, -2.5, -1.5]), np.array([4.0, 3.0, 1.5])
    with np.errstate(divide="ignore"):
        t_axes = np.where(d > 0, hi / d, np.where(d < 0, lo / d, np.inf))  # to each axis' wall ahead
    axis = np.argmin(t_axes, axis=1)
    t = t_axes[np.arange(len(d)), axis]
    local_n = np.zeros_like(d)
    local_n[np.arange(len(d)), axis] = -np.sign(d[np.arange(len(d)), axis])
    t = t + np.random.default_rng(seed).normal(0, noise, len(t))
    local = d * t[:, None]
    invalid = ((C.ravel() > 100) & (C.ravel() < 130) & (R.ravel() > 200) & (R.ravel() < 260)).astype(np.int64)
    q, pos = quaternion((0.2, 0.3, 1.0), 35.0), np.array([100.0, -50.0, 12.0])
    write_raw_scans(path, [({"cartesianX": local[:, 0], "cartesianY": local[:, 1], "cartesianZ": local[:, 2],
                             "rowIndex": R.ravel(), "columnIndex": C.ravel(), "cartesianInvalidState": invalid},
                            (q, pos), None)])
    rot = rotation((0.2, 0.3, 1.0), 35.0)
    keep = invalid == 0
    return dict(normals=local_n[keep] @ rot.T, range=t[keep], elevation=E[keep], da=da, de=de,
                station=pos, beams=(d @ rot.T)[keep])


def test_structured_e57_radii_and_normals(tmp_path):
    """rowIndex/columnIndex and the pose make the structure: radii from the measured steps (no
    step is in the file), exact normals on the noise-free planes, fallbacks only at the corners."""
    path = tmp_path / "room.e57"
    truth = _structured_e57(path)
    st = stations.e57_structure(e57.read_scans(path))
    assert st is not None and st.source == "e57"
    np.testing.assert_array_equal(st.positions, [truth["station"]])
    n = sum(len(c) for c in pointcloud.iter_point_chunks(path))
    r = scan_attributes(pointcloud.point_range(path, 50_000), st, n, tmp_path / "out", scale=SCALE)
    nrm, rad = np.load(tmp_path / "out" / "normals.npy"), np.load(tmp_path / "out" / "radii.npy")
    angle = np.degrees(np.arccos(np.clip(np.sum(nrm * truth["normals"], axis=1), -1, 1)))
    # noise-free planes: exact to the float32 sums (measured 0.02 degrees) but within 2 beams of an
    # edge of the box, where the window spans two
    assert np.percentile(angle, 90) < 0.1 and np.mean(angle < 1.0) > 0.95, np.percentile(angle, [50, 90, 99])
    u, nt = truth["beams"], truth["normals"]
    facing = np.abs(np.sum(nt * u, axis=1)) > 0.999
    a_c = 2 * np.arcsin(np.cos(truth["elevation"]) * np.sin(truth["da"] / 2))
    want = SCALE * truth["range"] * np.hypot(truth["de"], a_c) / 2
    # angles measured between neighbouring beams' directions (float64 positions): exact but for
    # the stretch of the few degrees a facing surface may tilt (< 0.1 % at cos > 0.999)
    np.testing.assert_allclose(rad[facing], want[facing], rtol=2e-3)
    assert r.counts["isolated_points"] == 0 and r.counts["fallback_normals"] < 0.01 * n


@needs_real
def test_real_structured_e57(tmp_path):
    """pumpA is a structured scan (1074 x 345 cells, 155,201 points): scan radii near the kNN
    radii (measured median ratio 1.02), normals toward the scanner at the origin."""
    from dmrt.preprocess.normals import splat_radii

    path = REAL / PUMP
    st = stations.e57_structure(e57.read_scans(path))
    assert st is not None and st.line() == 1074
    n = 155_201
    r = scan_attributes(pointcloud.point_range(path, 40_000), st, n, tmp_path, scale=SCALE)
    nrm, rad = np.load(tmp_path / "normals.npy"), np.load(tmp_path / "radii.npy")
    pos = pointcloud.read_points(path).positions
    ratio = rad / splat_radii(pos, 8, SCALE)
    assert 0.8 < np.median(ratio) < 1.25, np.percentile(ratio, [5, 50, 95])
    assert np.all(np.sum(nrm * pos, axis=1) < 0)  # toward the scanner at the origin
    assert r.counts["fallback_normals"] < 0.01 * n


def test_bad_scans_json(tiny_scene, tmp_path):
    doc = json.loads((tiny_scene / "scans.json").read_text())
    doc["stations"][1]["points"][0] += 1
    (tmp_path / "scans.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match=r"scans.json: stations\[1\].points .* must follow each other"):
        stations.read_scans_json(tmp_path / "scans.json", 200_450)
    doc["stations"][1]["points"][0] -= 1
    (tmp_path / "scans.json").write_text(json.dumps(doc))
    with pytest.raises(InputError, match="the cloud has 7 points"):
        stations.read_scans_json(tmp_path / "scans.json", 7)


@pytest.fixture(scope="module")
def plain_tiny(tiny_scene, tmp_path_factory):
    """The tiny scene without its scans.json: a cloud with no structure."""
    root = tmp_path_factory.mktemp("plain") / "tiny"
    shutil.copytree(tiny_scene, root, ignore=shutil.ignore_patterns("scans.json", "points.ply", "images"))
    for name in ("points.ply", "images"):
        (root / name).symlink_to(tiny_scene / name)
    return root


def test_method_choice(tiny_scene, plain_tiny, tmp_path, capfd):
    assert scan_phase(load_scene(plain_tiny), tmp_path, PreprocessConfig(radii="auto")) is None  # auto: kNN
    assert scan_phase(load_scene(tiny_scene), tmp_path, PreprocessConfig(radii="knn")) is None
    with pytest.raises(ConfigError, match="--radii: scan: the scene .* has no scan structure"):
        scan_phase(load_scene(plain_tiny), tmp_path, PreprocessConfig(radii="scan"))
    # a scans.json that does not match the cloud (stations 30 cm off): said on one line
    doc = json.loads((tiny_scene / "scans.json").read_text())
    for st in doc["stations"]:
        st["position"][0] += 0.3
    (plain_tiny / "scans.json").write_text(json.dumps(doc))
    try:
        r = scan_phase(load_scene(plain_tiny), tmp_path / "off", PreprocessConfig(radii="auto"))
    finally:
        (plain_tiny / "scans.json").unlink()
    assert r.counts["off_grid_points"] > 0.5 * r.n_points
    err = capfd.readouterr().err.splitlines()
    assert len(err) == 1 and "scans.json: " in err[0] and "lie off their station's grid" in err[0], err


@pytest.mark.e2e
def test_bundles_record_the_method_and_are_unchanged_without_structure(tiny_scene, plain_tiny, tmp_path):
    """A scene without structure takes the kNN path with --radii auto: its bundle equals the one made
    with --radii knn of the scene with its scans.json, bit for bit. With its scans.json, auto takes
    the scan path and says so."""
    cfg = dict(depthmap_width=256)
    plain = read_bundle(preprocess(plain_tiny, tmp_path / "plain", PreprocessConfig(radii="auto", **cfg),
                                   progress=False))
    knn = read_bundle(preprocess(tiny_scene, tmp_path / "knn", PreprocessConfig(radii="knn", **cfg), progress=False))
    plain.meta["parameters"]["preprocess"]["radii"] = "knn"  # the one difference: auto asked for it
    assert_bundles_equal(plain, knn)
    assert plain.meta["normals_radii"]["method"] == "knn" and plain.meta["counts"]["normals_estimated"]
    scan = read_bundle(preprocess(tiny_scene, tmp_path / "scan", PreprocessConfig(radii="auto", **cfg),
                                  progress=False)).meta
    assert scan["normals_radii"]["method"] == "scan" and scan["normals_radii"]["normals"] == "scan"
    assert scan["normals_radii"]["fallback_normals"] < 0.01 * scan["counts"]["points"]
    assert scan["counts"]["normals_estimated"] and "scan_grid_s" in scan["timings"]
    # the time outside the phases is recorded too; the parts do not overlap, so they lie within
    # total_s (each, and total_s, rounded to the millisecond: 13 roundings, 6.5 ms at most)
    t = scan["timings"]
    parts = [v for k, v in t.items() if k.endswith("_s") and k != "total_s"]
    assert {"load_scene_s", "bookkeeping_s", "finish_s"} <= set(t) and sum(parts) <= t["total_s"] + 0.007


def test_the_pass_finds_the_bounds(tiny):
    """The scan-grid pass reads every point, so its bounding box is the loader's, exactly (the
    pipeline then skips the loader's own pass: load_scene(bounds=False))."""
    lo, hi = tiny["result"].bounds
    assert lo.tobytes() == tiny["scene"].bounds[0].tobytes() and hi.tobytes() == tiny["scene"].bounds[1].tobytes()


@pytest.mark.parametrize("case", ["nan", "truncated"])
def test_bad_cloud_on_the_scan_path(case, tiny_scene, tmp_path, capfd):
    """Where the scan-grid pass is the first to read the points (in worker processes, the NaN in a
    chunk after the first), a NaN still ends ``dmrt preprocess`` with its one line naming the
    point; a truncated body is refused by the loader from the file's size. No bundle is left."""
    scene = tmp_path / "scene"
    shutil.copytree(tiny_scene, scene)
    ply = scene / "points.ply"
    h = pointcloud._read_ply_header(ply)
    if case == "nan":
        rec = np.memmap(ply, h.dtype, "r+", offset=h.body_offset + h.skip, shape=(h.n,))
        rec["z"][123_456] = np.nan  # in the second of two workers' ranges
        rec.flush()
        del rec
        pattern = "NaN.*index 123456"
    else:
        os.truncate(ply, ply.stat().st_size - 100)
        pattern = "truncated"
    out = tmp_path / "out"
    out.mkdir()
    line = assert_bad_input(["preprocess", scene, "--out", out / "b", "--quiet", "--radii", "scan",
                             "--workers", 2, "--chunk-points", 50_000], capfd, [ply], out)
    assert re.search(pattern, line), line
