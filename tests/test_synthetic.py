"""The synthetic laser-scan scene: deterministic, complete, registered, and read by the user path."""

import json
import signal
import subprocess
import sys
import time

from dataclasses import replace

import numpy as np
import pytest

from bench.scenes.synthetic import (PRESETS, Studio, SynthConfig, albedo, build_geometry, generate_scene,
                                    make_materials, shade)
from dmrt.app.cli import main
from dmrt.camera import Camera
from dmrt.errors import InputError
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


# ----------------------------------------------------------------------------------------------
# The options that make the photo choice matter: a glossy highlight, a photographed surface offset
# ----------------------------------------------------------------------------------------------
def _matte_photo(cfg: SynthConfig, camera, gain) -> np.ndarray:
    """The generator's photo as it was before the glossy and offset options (commit a954fc4):
    the scanned mesh, albedo x shade, box-filtered, times the gain. ``camera`` scene-local."""
    geom, materials = build_geometry(cfg), make_materials()
    rc = MeshRaycaster(geom.vertices, geom.faces, origin=np.zeros(3))
    s = cfg.supersample
    dirs, center = camera.scaled(camera.width * s, camera.height * s).pixel_rays()
    t, face = rc.intersect(center, dirs)
    rgb = np.zeros((len(t), 3), np.float32)
    hit = face >= 0
    n = rc.face_normals[face[hit]]
    n[np.einsum("ij,ij->i", n, dirs[hit]) > 0] *= -1
    p = center + dirs[hit] * t[hit, None]
    rgb[hit] = albedo(materials, geom.face_material[face[hit]], p, n) * shade(n)[:, None]
    img = rgb.reshape(camera.height, s, camera.width, s, 3).mean(axis=(1, 3)) * gain
    return np.clip(np.rint(img * 255), 0, 255).astype(np.uint8)


def _studio_reproduces_the_photos(scene_dir, every: int = 1) -> None:
    """The held-out truth: the studio rebuilt from synthetic.json renders each photo's world
    camera as the generator did. Only the world -> local round trip of the camera (~1e-9 m)
    differs, which can flip a texel lookup at a boundary: 0.1 % of the pixels at most."""
    scene = load_scene(scene_dir)
    meta = json.loads((scene_dir / "synthetic.json").read_text())
    studio = Studio.from_scene(scene_dir)
    for j in range(0, len(scene.cameras), every):
        img = studio.photograph(scene.cameras[j], meta["photo_gains"][j], world=True)
        assert np.mean(np.any(img != scene.read_image(j), axis=-1)) < 1e-3, j


def test_defaults_give_the_matte_photos_of_before(tiny_scene):
    """Options off: the photos are exactly the Lambertian renders of the scanned mesh, and the
    studio of the scene reproduces them (what a held-out view's truth is made with)."""
    scene = load_scene(tiny_scene)
    meta = json.loads((tiny_scene / "synthetic.json").read_text())
    cfg, studio = PRESETS["tiny"], Studio.from_scene(tiny_scene)
    assert studio.config == cfg and len(studio.lights) == 0 and meta["lights"] == []
    assert studio.photo_raycaster is studio.scan_raycaster
    for j in (0, 7):
        cam, gain = scene.cameras[j].relative_to(cfg.offset), np.array(meta["photo_gains"][j])
        np.testing.assert_array_equal(studio.photograph(cam, gain), _matte_photo(cfg, cam, gain))
    _studio_reproduces_the_photos(tiny_scene, every=4)


def test_glossy_highlight_follows_the_view_direction():
    """A floor point under the light, seen from its mirror direction and from straight above:
    the photos differ by 255 g k_s (1 - (n . h)^s) exactly (Blinn-Phong, one visible light)."""
    cfg = SynthConfig(rooms=(1, 1), specular=0.4, shininess=50.0, lights_per_room=1, supersample=1)
    studio = Studio(cfg)
    (light,), n, gain = studio.lights, np.array([0.0, 0.0, 1.0]), 0.5  # gain 0.5: nothing clips
    for dx, dy in [(1.4, 0.5), (-1.4, 0.5), (1.4, -0.5), (-1.4, -0.5), (0.5, 1.4), (0.5, -1.4)]:
        p = light * [1, 1, 0] + [dx, dy, 0]
        to_light = (light - p) / np.linalg.norm(light - p)
        eyes = [p + 1.5 * (2 * (n @ to_light) * n - to_light), p + 1.5 * n]  # mirror, above
        t = [studio.photo_raycaster.intersect(e, (p - e)[None])[0][0] for e in eyes]
        if np.allclose(t, 1.0, atol=1e-5) and studio.photo_raycaster.visible(p[None], light)[0]:
            break  # a floor point both eyes and the light see
    else:
        pytest.fail("no unoccluded floor point near the light")
    # 9 x 9 pixels: the centre pixel's ray passes exactly through p
    centre = [studio.photograph(Camera.look_at("v", e, p, 9, 9, 10.0), gain)[4, 4].astype(float) for e in eyes]
    h = (to_light + n) / np.linalg.norm(to_light + n)
    expected = 255 * gain * cfg.specular * (1.0 - (n @ h) ** cfg.shininess)
    assert expected > 30  # the check is meaningful
    # each photo rounds to 8 bits: the difference is within one level of the exact amount
    np.testing.assert_allclose(centre[0] - centre[1], expected, atol=1.0)


def test_photographed_surface_lies_the_offset_from_the_scan():
    """Rays along the inward normals of the walls (boxes, niches included) meet the photographed
    surface exactly ``photo_surface_offset`` before the scanned one; float32 Embree: 1e-5 m."""
    cfg = SynthConfig(rooms=(1, 1), photo_surface_offset=0.03)
    studio = Studio(cfg)
    (x0, x1, y0, y1), = studio.geom.rooms
    starts, dirs = [], []
    for f in np.linspace(0.1, 0.9, 9):
        for z in (0.3, 1.0, 1.7, 2.4):
            x, y = x0 + f * (x1 - x0), y0 + f * (y1 - y0)
            for s, d in [((x0 + 0.2, y, z), (-1, 0, 0)), ((x1 - 0.2, y, z), (1, 0, 0)),
                         ((x, y0 + 0.2, z), (0, -1, 0)), ((x, y1 - 0.2, z), (0, 1, 0))]:
                starts.append(s)
                dirs.append(d)
    starts, dirs = np.array(starts), np.array(dirs, float)
    t_scan = np.array([studio.scan_raycaster.intersect(s, d[None])[0][0] for s, d in zip(starts, dirs)])
    t_photo = np.array([studio.photo_raycaster.intersect(s, d[None])[0][0] for s, d in zip(starts, dirs)])
    np.testing.assert_allclose(t_scan - t_photo, cfg.photo_surface_offset, atol=1e-5)


def test_glossy_offset_scene_records_its_truth(tmp_path):
    """The options reach synthetic.json (configuration and lights), the scan stays on mesh.ply's
    surface, and the studio rebuilt from the file reproduces the generator's glossy photos."""
    cfg = SynthConfig(points=20_000, photos=4, photo_size=(64, 43), specular=0.3, photo_surface_offset=0.02)
    out = generate_scene(cfg, tmp_path / "s", progress=False, workers=1)
    meta = json.loads((out / "synthetic.json").read_text())
    assert meta["config"]["specular"] == 0.3 and meta["config"]["photo_surface_offset"] == 0.02
    assert np.array(meta["lights"]).shape == (2 * cfg.lights_per_room, 3)
    _studio_reproduces_the_photos(out)
    matte = generate_scene(replace(cfg, specular=0.0, photo_surface_offset=0.0), tmp_path / "m", progress=False,
                           workers=1)
    assert (out / "points.ply").read_bytes() == (matte / "points.ply").read_bytes()  # the scan is the same
    assert (out / "images/photo_0000.png").read_bytes() != (matte / "images/photo_0000.png").read_bytes()


def test_bad_glossy_options_are_one_line(tmp_path, capsys):
    assert main(["scene", "synth", "--out", str(tmp_path / "s"), "--photo-surface-offset", "0.5"]) == 2
    assert "--photo-surface-offset" in capsys.readouterr().err and not (tmp_path / "s").exists()
    with pytest.raises(InputError, match="synthetic.json"):
        Studio.from_scene(tmp_path)
