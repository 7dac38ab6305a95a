"""Scene loading: a valid scene loads; each kind of broken input gives an InputError naming the file
and the problem (the bad-input corpus)."""

import shutil

import numpy as np
import pytest
from PIL import Image

from dmrt.camera import Camera
from dmrt.io.colmap import read_model, write_model
from dmrt.errors import InputError
from dmrt.io.pointcloud import PointCloud, write_points
from dmrt.io.scene import load_scene

W, H = 64, 48
XYZ_HEADER = "property double x\nproperty double y\nproperty double z\n"


def make_scene(root, offset=(10.3, -20.7, 3.2), n=500, binary=False):
    """A small valid scene: n random points in a 10 m cube around ``offset``, two cameras, PNGs."""
    rng = np.random.default_rng(0)
    offset = np.asarray(offset, dtype=np.float64)
    pts = rng.uniform(-5, 5, (n, 3)) + offset
    cols = rng.integers(0, 256, (n, 3), dtype=np.uint8)
    root.mkdir()
    write_points(root / "points.ply", PointCloud(pts, None, cols))
    cams = [Camera.look_at(f"img{i}.png", offset + eye, offset, W, H)
            for i, eye in enumerate([(20.0, 0.0, 5.0), (0.0, 20.0, 5.0)])]
    write_model(root / "sparse", cams, binary=binary)
    (root / "images").mkdir()
    for c in cams:
        Image.fromarray(rng.integers(0, 256, (H, W, 3), dtype=np.uint8)).save(root / "images" / c.name)
    return pts, cams


@pytest.fixture
def scene(tmp_path):
    root = tmp_path / "scene"
    make_scene(root)
    return root


def test_valid_scene(scene):
    s = load_scene(scene)
    assert s.n_points == 500 and len(s.cameras) == 2 and s.mesh_path is None
    assert [p.name for p in s.image_paths] == ["img0.png", "img1.png"]
    pts = s.read_points().positions
    centre = (pts.min(0) + pts.max(0)) / 2
    assert np.all(np.abs(s.origin - centre) <= 0.5) and np.all(s.origin == np.round(s.origin))
    assert s.read_image(1).shape == (H, W, 3) and s.read_image(1).dtype == np.uint8
    assert s.camera_index("img1.png") == 1
    with pytest.raises(InputError, match="no image named 'x.png'.*'img0.png'"):
        s.camera_index("x.png")
    assert sum(len(c) for c in s.iter_points(chunk_size=128)) == 500


def test_utm_origin(tmp_path):
    root = tmp_path / "utm"
    make_scene(root, offset=(612_345.678, 5_412_345.321, 287.5))
    s = load_scene(root)
    pts = s.read_points().positions
    centre = (pts.min(0) + pts.max(0)) / 2
    assert np.all(np.abs(s.origin - centre) < 1.0)
    # what the GPU will see: float32 offsets that are small and keep sub-millimetre precision
    local = (pts - s.origin).astype(np.float32)
    assert np.abs(local).max() < 10
    assert np.abs(local.astype(np.float64) + s.origin - pts).max() < 1e-6


def test_binary_model_and_sparse_0_and_mesh(tmp_path):
    import trimesh

    root = tmp_path / "s"
    make_scene(root, binary=True)
    shutil.move(root / "sparse", tmp_path / "model")
    (root / "sparse").mkdir()
    shutil.move(tmp_path / "model", root / "sparse" / "0")  # COLMAP mapper layout
    trimesh.creation.box().export(root / "mesh.ply")
    rgba = Image.new("RGBA", (W, H), (10, 20, 30, 40))
    rgba.save(root / "images" / "img0.png")
    s = load_scene(root)
    assert s.mesh_path == root / "mesh.ply"
    assert len(s.cameras) == 2
    np.testing.assert_array_equal(s.read_image(0)[0, 0], [10, 20, 30])


def test_check_images_off(scene):
    shutil.rmtree(scene / "images")
    assert len(load_scene(scene, check_images=False).cameras) == 2


# -- the bad-input corpus ------------------------------------------------------------------------
def _ply(root, header_props, n, body=b"", fmt="binary_little_endian"):
    head = f"ply\nformat {fmt} 1.0\nelement vertex {n}\n{header_props}end_header\n"
    (root / "points.ply").write_bytes(head.encode() + body)


def _points_with(root, value):
    pts = np.random.default_rng(1).uniform(-1, 1, (500, 3))
    pts[123, 2] = value
    write_points(root / "points.ply", PointCloud(pts))


def _rewrite_line(path, old, new):
    path.write_text(path.read_text().replace(old, new, 1))


def _binary_truncated(root, name):
    cams = read_model(root / "sparse")
    write_model(root / "sparse", cams, binary=True)
    p = root / "sparse" / name
    p.write_bytes(p.read_bytes()[:-10])


def _images_txt_line(root, k):
    """The k-th image line of images.txt (k = 0, 1)."""
    lines = [ln for ln in (root / "sparse" / "images.txt").read_text().splitlines()
             if ln and not ln.startswith("#")]
    return lines[k]


def _dup_names(root):
    line = _images_txt_line(root, 1)
    _rewrite_line(root / "sparse" / "images.txt", line, line.replace("img1.png", "img0.png"))


def _unknown_camera(root):
    line = _images_txt_line(root, 1)
    w = line.split()
    w[8] = "99"
    _rewrite_line(root / "sparse" / "images.txt", line, " ".join(w))


def _nan_translation(root):
    line = _images_txt_line(root, 0)
    w = line.split()
    w[5] = "nan"
    _rewrite_line(root / "sparse" / "images.txt", line, " ".join(w))


CASES = {
    "ply_magic": (lambda r: (r / "points.ply").write_bytes(b"PLX\x00garbage" * 10),
                  r"points\.ply.*magic 'ply' missing"),
    "ply_truncated_body": (lambda r: (r / "points.ply").write_bytes((r / "points.ply").read_bytes()[:-100]),
                           r"points\.ply.*truncated.*500 vertices.*only \d+ bytes"),
    "ply_truncated_header": (lambda r: (r / "points.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 500\nproperty dou"),
                             r"points\.ply.*header truncated.*end_header"),
    "ply_nan": (lambda r: _points_with(r, np.nan), r"points\.ply.*NaN.*index 123"),
    "ply_inf": (lambda r: _points_with(r, -np.inf), r"points\.ply.*inf.*index 123"),
    "ply_empty": (lambda r: _ply(r, XYZ_HEADER, 0), r"points\.ply.*empty point cloud"),
    "ply_missing_x": (lambda r: _ply(r, "property double y\nproperty double z\n", 1, b"\0" * 16),
                      r"points\.ply.*no 'x' property"),
    "ply_ascii_garbage": (lambda r: _ply(r, XYZ_HEADER, 2, b"1 2 3\n4 five 6\n", fmt="ascii"),
                          r"points\.ply.*non-numeric"),
    "no_points_file": (lambda r: (r / "points.ply").unlink(), r"scene.*no point cloud"),
    "image_missing": (lambda r: (r / "images" / "img1.png").unlink(), r"img1\.png.*missing"),
    "images_dir_missing": (lambda r: shutil.rmtree(r / "images"), r"images.*'images/' is missing"),
    "image_wrong_size": (lambda r: Image.new("RGB", (W, H + 1)).save(r / "images" / "img0.png"),
                         rf"img0\.png.*{W}x{H + 1}.*camera says {W}x{H}"),
    "image_corrupt": (lambda r: (r / "images" / "img1.png").write_bytes(b"\x89PNG not really" * 50),
                      r"img1\.png.*corrupt"),
    # distorted models OpenCV undistorts are read (test_undistort.py); others are one line
    "camera_model_thin_prism": (lambda r: _rewrite_line(r / "sparse" / "cameras.txt", "2 PINHOLE",
                                                        "2 THIN_PRISM_FISHEYE"),
                                r"cameras\.txt.*camera 2 uses model THIN_PRISM_FISHEYE, which this suite "
                                r"cannot undistort.*colmap image_undistorter"),
    "cameras_bin_truncated": (lambda r: _binary_truncated(r, "cameras.bin"),
                              r"cameras\.bin.*truncated"),
    "images_bin_truncated": (lambda r: _binary_truncated(r, "images.bin"),
                             r"images\.bin.*truncated"),
    "unknown_camera_id": (_unknown_camera, r"images\.txt.*'img1\.png'.*unknown camera id 99"),
    "cameras_txt_non_numeric": (lambda r: _rewrite_line(r / "sparse" / "cameras.txt", f" {W} {H} ",
                                                        f" {W} forty-eight "),
                                r"cameras\.txt.*line \d+: non-numeric"),
    "sparse_missing": (lambda r: shutil.rmtree(r / "sparse"), r"sparse.*missing"),
    "sparse_empty": (lambda r: [p.unlink() for p in (r / "sparse").iterdir()],
                     r"sparse.*no COLMAP model"),
    "mesh_empty": (lambda r: (r / "mesh.ply").write_bytes(
        b"ply\nformat ascii 1.0\nelement vertex 0\n" + XYZ_HEADER.encode()
        + b"element face 0\nproperty list uchar int vertex_indices\nend_header\n"),
                   r"mesh\.ply.*empty"),
    "mesh_garbage": (lambda r: (r / "mesh.ply").write_bytes(b"not a mesh at all"),
                     r"mesh\.ply.*unreadable"),
    "duplicate_image_names": (_dup_names, r"images\.txt.*duplicate image name 'img0\.png'"),
    "nan_in_camera_pose": (_nan_translation, r"images\.txt.*'img0\.png'.*NaN"),
    "no_images_in_model": (lambda r: (r / "sparse" / "images.txt").write_text("# none\n"),
                           r"images\.txt.*no images"),
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_bad_input(scene, case):
    breaker, pattern = CASES[case]
    breaker(scene)
    with pytest.raises(InputError, match=pattern) as info:
        load_scene(scene)
    assert info.value.path is not None and str(info.value).startswith(str(info.value.path))


def test_missing_scene_dir(tmp_path):
    with pytest.raises(InputError, match=r"nowhere.*does not exist"):
        load_scene(tmp_path / "nowhere")
