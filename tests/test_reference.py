"""The camera convention and the Embree reference, against analytic truths."""

import numpy as np
import pytest
import trimesh

from dmrt.camera import Camera
from dmrt.io.frames import empty_frame, read_frame, write_frame
from reference.metrics import compare, psnr, texel_footprint
from reference.raycast import MeshRaycaster
from reference.render import EmbreeReference, sample_bilinear

ROOM_LO, ROOM_HI = np.array([0.0, 0.0, 0.0]), np.array([4.0, 5.0, 3.0])
UTM = np.array([512300.0, 5312700.0, 210.0])


def analytic_box_depth(camera: Camera, lo, hi) -> np.ndarray:
    """Camera z of the first wall of an axis-aligned room seen from inside, per pixel."""
    dirs, c = camera.pixel_rays()  # scaled so the ray parameter is camera z
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.stack([np.where(dirs[:, k] > 0, (hi[k] - c[k]) / dirs[:, k], (lo[k] - c[k]) / dirs[:, k])
                      for k in range(3)], axis=1)
    t[~np.isfinite(t) | (t <= 0)] = np.inf
    return t.min(axis=1).reshape(camera.height, camera.width)


@pytest.mark.parametrize("offset", [np.zeros(3), UTM], ids=["local", "utm"])
def test_embree_depth_equals_analytic_box_room(offset):
    rng = np.random.default_rng(1)
    room = trimesh.creation.box(bounds=np.stack([ROOM_LO, ROOM_HI]) + offset)
    rc = MeshRaycaster(room.vertices, room.faces, origin=offset + np.array([2.0, 2.0, 1.0]))
    for k in range(4):
        eye = rng.uniform(ROOM_LO + 0.5, ROOM_HI - 0.5) + offset
        target = rng.uniform(ROOM_LO, ROOM_HI) + offset
        cam = Camera.look_at("c", eye, target, 64, 43, fov_x_deg=rng.uniform(40, 90))
        depth, face, normal = rc.cast_camera(cam)
        truth = analytic_box_depth(cam, ROOM_LO + offset, ROOM_HI + offset)
        assert (face >= 0).all()
        # 1e-4 m: Embree's float32 arithmetic in a frame centred near the room (metres-sized
        # coordinates) is good to ~1e-6 m; the bound is 1e-4 m.
        np.testing.assert_allclose(depth, truth, atol=1e-4, rtol=0)
        # Normals face the camera and are axis-aligned.
        dirs, _ = cam.pixel_rays()
        assert (np.einsum("ij,ij->i", normal.reshape(-1, 3), dirs) < 0).all()
        np.testing.assert_allclose(np.abs(normal).max(-1), 1.0, atol=1e-6)


def test_project_inverts_pixel_rays():
    cam = Camera.look_at("c", (1, 2, 3), (4, 0, 2), 40, 30, 60)
    dirs, c = cam.pixel_rays()
    z = np.linspace(0.5, 9, len(dirs))
    uv, zz = cam.project(c + dirs * z[:, None])
    j, i = np.meshgrid(np.arange(40) + 0.5, np.arange(30) + 0.5)
    np.testing.assert_allclose(uv, np.stack([j.ravel(), i.ravel()], 1), atol=1e-9)
    np.testing.assert_allclose(zz, z, atol=1e-12)


def test_gl_matrix_maps_to_pixels_and_depth():
    """clip = M @ [x, 1]: ndc x = 2u/W - 1, ndc y = 2v/H - 1 (image row 0 = framebuffer row 0), w = z."""
    rng = np.random.default_rng(2)
    cam = Camera.look_at("c", UTM + (1, 2, 1.5), UTM + (3, 5, 1), 64, 48, 70)
    pts = cam.center + rng.normal(0, 2, (100, 3)) + 4 * cam.R[2]
    uv, z = cam.project(pts)
    M = cam.gl_view_projection(0.1, 100.0, origin=UTM)
    clip = np.c_[pts - UTM, np.ones(len(pts))] @ M.T.astype(np.float64)
    np.testing.assert_allclose(clip[:, 3], z, rtol=1e-5)
    np.testing.assert_allclose((clip[:, 0] / clip[:, 3] + 1) / 2 * 64, uv[:, 0], atol=1e-3)
    np.testing.assert_allclose((clip[:, 1] / clip[:, 3] + 1) / 2 * 48, uv[:, 1], atol=1e-3)


def test_resized_keeps_aspect_and_geometry():
    cam = Camera.look_at("c", (0, 0, 1), (5, 1, 1), 256, 171)
    big = cam.resized(1024)
    assert (big.width, big.height) == (1024, 684)
    p = np.array([[5.0, 1.2, 0.7]])
    uv, _ = cam.project(p)
    uv2, _ = big.project(p)
    np.testing.assert_allclose(uv2[0] / [1024, 684], uv[0] / [256, 171], atol=1e-3)


def test_reference_textures_from_the_most_frontal_photo():
    """Two photos of a flat wall: the frontal close one wins; colours come from its pixels."""
    wall = trimesh.creation.box(bounds=[[-5, -5, -0.1], [5, 5, 0.0]])
    rc = MeshRaycaster(wall.vertices, wall.faces)
    frontal = Camera.look_at("a", (0, 0, 2), (0, 0, 0), 32, 32, 60, up=(0, 1, 0))
    oblique = Camera.look_at("b", (3, 0, 1.5), (0, 0, 0), 32, 32, 60, up=(0, 0, 1))
    images = [np.full((32, 32, 3), (200, 10, 10), np.uint8), np.full((32, 32, 3), (10, 200, 10), np.uint8)]
    frame = EmbreeReference(rc, [frontal, oblique], images).render(frontal)
    assert (frame["depth"] > 0).all()
    np.testing.assert_allclose(frame["depth"], 2.0, atol=1e-4)  # looking straight at the wall
    assert (frame["label"] == 0).all()
    assert (frame["color"] == (200, 10, 10)).all()


def test_sample_bilinear_on_a_ramp():
    img = np.arange(5 * 4, dtype=np.float32).reshape(4, 5)[..., None]  # value = 5 * row + col
    uv = np.array([[0.5, 0.5], [1.0, 0.5], [2.5, 3.5], [1.75, 2.25]])
    expect = 5 * (uv[:, 1] - 0.5) + (uv[:, 0] - 0.5)
    np.testing.assert_allclose(sample_bilinear(img, uv)[:, 0], expect, atol=1e-5)


def test_metrics_on_constructed_frames():
    ref = empty_frame(10, 10)
    ref["depth"][:, :8] = 2.0
    ref["color"][:] = 100
    f = empty_frame(10, 10)
    f["depth"][:, :6] = 2.01  # 20 holes of 80 surface pixels
    f["depth"][:, 9] = 3.0   # 10 extra of 20 background pixels
    f["color"][:] = 110
    m = compare(f, ref, footprint=np.full((10, 10), 0.005))
    assert m["hole_rate"] == pytest.approx(20 / 80)
    assert m["extra_rate"] == pytest.approx(10 / 20)
    assert m["depth_median_m"] == pytest.approx(0.01, abs=1e-6)
    assert m["depth_median_texels"] == pytest.approx(2.0, rel=1e-3)
    assert m["psnr_db"] == pytest.approx(10 * np.log10(255 ** 2 / 100))
    assert np.isnan(m["maps"]["depth_error_m"][0, 7]) and m["maps"]["holes"][0, 7] == 1
    assert psnr(f["color"], f["color"]) == np.inf


def test_texel_footprint_scales_with_distance_and_resolution():
    cam = Camera.look_at("c", (0, 0, 0), (0, 0, 1), 1000, 500, 90, up=(0, 1, 0))  # fx = 500
    pts = np.array([[0, 0, 2.0], [0, 0, 4.0]])
    fp = texel_footprint(pts, np.array([0, 0]), [cam], depthmap_width=500)
    np.testing.assert_allclose(fp, [2 / 250, 4 / 250])
    assert np.isnan(texel_footprint(pts, np.array([-1, 0]), [cam], 500)[0])


def test_frame_exr_round_trip(tmp_path):
    rng = np.random.default_rng(3)
    f = empty_frame(7, 9)
    f["depth"][:] = rng.uniform(0, 10, (7, 9))
    f["label"][:] = rng.integers(-1, 190, (7, 9))
    f["color"][:] = rng.integers(0, 256, (7, 9, 3))
    f["normal"][:] = rng.normal(size=(7, 9, 3))
    write_frame(tmp_path / "f.exr", f)
    g = read_frame(tmp_path / "f.exr")
    for k in f:
        np.testing.assert_array_equal(f[k], g[k])
    assert [p.name for p in tmp_path.iterdir()] == ["f.exr"]  # no temporary left behind
