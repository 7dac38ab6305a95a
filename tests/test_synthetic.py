"""The synthetic laser-scan scene: deterministic, complete, registered, and read by the user path."""

import json
import signal
import subprocess
import sys
import time

import numpy as np
import pytest

from bench.scenes.synthetic import PRESETS, SynthConfig, build_geometry, generate_scene
from dmrt.app.cli import main
from dmrt.io.scene import load_scene
from reference.raycast import MeshRaycaster
from reference.render import sample_bilinear


def test_geometry_is_deterministic_in_the_seed():
    a, b = build_geometry(PRESETS["tiny"]), build_geometry(PRESETS["tiny"])
    np.testing.assert_array_equal(a.vertices, b.vertices)
    np.testing.assert_array_equal(a.face_material, b.face_material)
    c = build_geometry(SynthConfig(seed=7))
    assert len(c.vertices) != len(a.vertices) or not np.array_equal(c.vertices, a.vertices)


def test_tiny_scene_loads_through_the_user_readers(tiny_scene):
    scene = load_scene(tiny_scene)
    cfg = PRESETS["tiny"]
    assert len(scene.cameras) == cfg.photos
    assert 0.8 * cfg.points < scene.n_points < 1.2 * cfg.points
    assert all((c.width, c.height) == cfg.photo_size for c in scene.cameras)
    assert scene.read_image(0).shape == (171, 256, 3)
    # The scene sits at UTM-like coordinates; its origin keeps the float32 offsets small.
    assert np.all(np.abs(scene.origin - np.array(cfg.offset)) < 50)
    pts = scene.read_points()
    assert np.abs(pts.positions - scene.origin).max() < 50
    assert pts.colors is not None and pts.normals is None  # like a raw scan: normals estimated later
    assert scene.mesh_path is not None


def test_scan_points_lie_on_the_mesh(tiny_scene):
    """Every P_HD point is a mesh hit plus range noise along the beam (sigma 2 mm)."""
    scene = load_scene(tiny_scene)
    meta = json.loads((tiny_scene / "synthetic.json").read_text())
    pts = scene.read_points().positions[::50]
    rc = MeshRaycaster.from_file(scene.mesh_path, origin=scene.origin)
    stations = np.array(meta["stations"])
    # Re-cast each point's beam from the nearest station that sees it: the distance to the true
    # surface along the beam is the range noise, |noise| < 5 sigma = 1 cm for all but outliers.
    err = np.full(len(pts), np.inf)
    for s in stations:
        d = pts - s
        t, face = rc.intersect(s, d)  # d unnormalised: the surface is at t = 1 +- noise / |d|
        ok = face >= 0
        err[ok] = np.minimum(err[ok], np.abs(t[ok] - 1) * np.linalg.norm(d[ok], axis=1))
    assert np.mean(err < 0.01) > 0.999


def test_scan_colors_match_photo_pixels(tiny_scene):
    """Camera convention, end to end: P_HD points projected into a photo land on pixels whose colour
    matches the texture the point was sampled from, and the match is best with no pixel shift."""
    scene = load_scene(tiny_scene)
    meta = json.loads((tiny_scene / "synthetic.json").read_text())
    pc = scene.read_points()
    rc = MeshRaycaster.from_file(scene.mesh_path, origin=scene.origin)
    for j in range(0, len(scene.cameras), 3):
        cam, img, gain = scene.cameras[j], scene.read_image(j), np.array(meta["photo_gains"][j])
        uv, z = cam.project(pc.positions)
        inside = np.flatnonzero((z > 0) & (uv[:, 0] >= 1) & (uv[:, 0] < cam.width - 1)
                                & (uv[:, 1] >= 1) & (uv[:, 1] < cam.height - 1))
        depth, _, _ = rc.cast_camera(cam)
        d = depth[uv[inside, 1].astype(int), uv[inside, 0].astype(int)]
        vis = inside[np.abs(d - z[inside]) < 0.02]  # not occluded in this photo
        assert len(vis) > 500
        err = {}
        for shift in [(0, 0), (1, 0), (-1, 0), (0, 1), (0, -1), (0.5, 0.5), (-0.5, -0.5)]:
            c = sample_bilinear(img, uv[vis] + shift) / gain
            err[shift] = np.median(np.abs(c - pc.colors[vis].astype(np.float32)))
        # A photo pixel averages ~5x5 texels of the wall textures (2x2 supersampling), a scan
        # point samples one: a median difference of a few levels is texture detail, not misregistration.
        assert err[(0, 0)] < 8.0
        assert err[(0, 0)] == min(err.values()), err  # any convention slip of half a pixel shows here


def test_output_does_not_depend_on_the_worker_count(tmp_path):
    cfg = SynthConfig(points=30_000, photos=4, photo_size=(64, 43))
    one = generate_scene(cfg, tmp_path / "one", progress=False, workers=1)
    two = generate_scene(cfg, tmp_path / "two", progress=False, workers=2)
    for rel in ["points.ply", "mesh.ply", "sparse/images.txt", "images/photo_0003.png"]:
        assert (one / rel).read_bytes() == (two / rel).read_bytes(), rel


def test_lighting_variation_is_recorded_and_switchable(tmp_path):
    cfg = SynthConfig(points=20_000, photos=4, photo_size=(64, 43), lighting_variation=False)
    out = generate_scene(cfg, tmp_path / "s", progress=False)
    gains = json.loads((out / "synthetic.json").read_text())["photo_gains"]
    assert np.allclose(gains, 1.0)


def test_existing_output_is_refused(tmp_path, capsys):
    out = tmp_path / "s"
    out.mkdir()
    assert main(["scene", "synth", "--out", str(out), "--quiet"]) == 2
    assert "already exists" in capsys.readouterr().err
    with pytest.raises(ValueError, match="--room-size"):
        SynthConfig(room_size=(0.6, 0.7))


@pytest.mark.e2e
def test_interrupted_generation_leaves_nothing(tmp_path):
    """Ctrl-C in the middle of a scan: neither the scene nor its .partial folder remains."""
    out = tmp_path / "small"
    proc = subprocess.Popen([sys.executable, "-m", "dmrt.app.cli", "scene", "synth", "--preset", "small",
                             "--out", str(out), "--quiet", "--workers", "1"])
    deadline = time.time() + 120
    while not list((tmp_path / "small.partial").glob("points.ply*")):  # the scan has begun
        assert time.time() < deadline and proc.poll() is None
        time.sleep(0.05)
    proc.send_signal(signal.SIGINT)
    assert proc.wait(60) != 0
    assert list(tmp_path.iterdir()) == []


def test_float_positions_need_an_offset_near_the_origin():
    from dmrt.errors import ConfigError

    with pytest.raises(ConfigError, match="float-positions.*offset within 1 km"):
        SynthConfig(float_positions=True)  # the default offset is UTM-sized
    assert SynthConfig(float_positions=True, offset=(10.0, 0.0, 0.0)).float_positions
