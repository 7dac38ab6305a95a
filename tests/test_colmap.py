"""COLMAP model I/O: text and binary round trips, SIMPLE_PINHOLE, quaternions vs scipy."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from dmrt.camera import Camera
from dmrt.io.colmap import qvec_to_rotation, read_model, rotation_to_qvec, write_model
from dmrt.errors import InputError


def _cameras(n=6, seed=1):
    rng = np.random.default_rng(seed)
    Rs = Rotation.random(n, random_state=seed).as_matrix()
    cams = []
    for i in range(n):
        w, h = int(rng.integers(100, 4000)), int(rng.integers(100, 3000))
        cams.append(Camera(f"IMG_{i:04d}.JPG", w, h, rng.uniform(500, 5000), rng.uniform(500, 5000),
                           rng.uniform(0, w), rng.uniform(0, h), Rs[i],
                           rng.uniform(-1, 1, 3) * [1e5, 5e6, 1e3]))
    return cams


def _write_text_model(folder, cameras: str, images: str) -> None:
    """A COLMAP text model from the contents of ``cameras.txt`` and ``images.txt``."""
    (folder / "cameras.txt").write_text(cameras)
    (folder / "images.txt").write_text(images)


@pytest.mark.parametrize("binary", [False, True])
def test_round_trip(tmp_path, binary):
    cams = _cameras()
    pts = np.random.default_rng(0).normal(size=(20, 3))
    write_model(tmp_path, cams, binary=binary, points3d=pts)
    ext = ".bin" if binary else ".txt"
    assert {p.name for p in tmp_path.iterdir()} == {f"cameras{ext}", f"images{ext}", f"points3D{ext}"}
    back = read_model(tmp_path)
    assert [c.name for c in back] == [c.name for c in cams]
    for a, b in zip(back, cams):
        assert (a.width, a.height) == (b.width, b.height)
        np.testing.assert_allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.R, b.R, rtol=0, atol=1e-12)
        np.testing.assert_allclose(a.t, b.t, rtol=0, atol=1e-12)


def test_rewrite_other_format_replaces_stale_files(tmp_path):
    write_model(tmp_path, _cameras(seed=1), binary=True)
    cams = _cameras(n=3, seed=2)
    write_model(tmp_path, cams, binary=False)
    assert [c.name for c in read_model(tmp_path)] == [c.name for c in cams]
    assert not (tmp_path / "cameras.bin").exists()


def test_simple_pinhole_and_image_order(tmp_path):
    R = Rotation.from_euler("xyz", [10, -20, 30], degrees=True)
    x, y, z, w = R.as_quat()
    (tmp_path / "cameras.txt").write_text("# comment\n7 SIMPLE_PINHOLE 640 480 500.5 320 240\n"
                                          "3 PINHOLE 100 50 80 81 50 25\n")
    (tmp_path / "images.txt").write_text(
        "# IMAGE_ID QW QX QY QZ TX TY TZ CAMERA_ID NAME\n"
        "9 1 0 0 0 0 0 0 3 b.png\n"
        "1.0 2.0 -1 12\n"
        f"2 {w} {x} {y} {z} 1 2 3 7 a.png\n"
        "\n")
    a, b = read_model(tmp_path)  # ordered by image id, not file order
    assert (a.name, b.name) == ("a.png", "b.png")
    assert (a.fx, a.fy, a.cx, a.cy, a.width, a.height) == (500.5, 500.5, 320, 240, 640, 480)
    np.testing.assert_allclose(a.R, R.as_matrix(), atol=1e-12)
    np.testing.assert_array_equal(a.t, [1, 2, 3])
    assert (b.fx, b.fy, b.cx, b.cy) == (80, 81, 50, 25)


def test_unnormalized_quaternion_is_normalized(tmp_path):
    _write_text_model(tmp_path, "1 PINHOLE 10 10 5 5 5 5\n", "1 2 0 0 0 0 0 0 1 a.png\n\n")
    np.testing.assert_allclose(read_model(tmp_path)[0].R, np.eye(3), atol=1e-15)


def test_quaternion_against_scipy():
    rots = Rotation.random(200, random_state=4)
    for R, xyzw in zip(rots.as_matrix(), rots.as_quat()):
        q_truth = np.array([xyzw[3], *xyzw[:3]])  # scipy is scalar-last; COLMAP scalar-first
        q_truth *= np.sign(q_truth[0])
        q = rotation_to_qvec(R)
        np.testing.assert_allclose(q, q_truth, atol=1e-12)
        np.testing.assert_allclose(qvec_to_rotation(q_truth), R, atol=1e-12)


def test_quaternion_half_turns():
    # trace = -1: the naive w = sqrt(1 + trace) / 2 formula breaks down here
    for axis in np.eye(3):
        R = Rotation.from_rotvec(np.pi * axis).as_matrix()
        np.testing.assert_allclose(qvec_to_rotation(rotation_to_qvec(R)), R, atol=1e-12)


def test_missing_model(tmp_path):
    with pytest.raises(InputError, match="no COLMAP model"):
        read_model(tmp_path)


def test_wrong_param_count(tmp_path):
    _write_text_model(tmp_path, "1 PINHOLE 10 10 5 5 5\n", "1 1 0 0 0 0 0 0 1 a.png\n\n")
    with pytest.raises(InputError, match=r"cameras\.txt.*PINHOLE takes 4 parameters, found 3"):
        read_model(tmp_path)


def test_nan_quaternion(tmp_path):
    _write_text_model(tmp_path, "1 PINHOLE 10 10 5 5 5 5\n", "1 nan 0 0 0 0 0 0 1 a.png\n\n")
    with pytest.raises(InputError, match=r"images\.txt.*'a\.png'.*NaN"):
        read_model(tmp_path)


def test_zero_images(tmp_path):
    _write_text_model(tmp_path, "1 PINHOLE 10 10 5 5 5 5\n", "# nothing\n")
    with pytest.raises(InputError, match=r"images\.txt.*no images"):
        read_model(tmp_path)
