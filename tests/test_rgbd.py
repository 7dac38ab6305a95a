"""``dmrt scene rgbd`` (dmrt/io/rgbd.py) on RGB-D frames made here: two views of an analytic plane
(and a box in front of it for the flying pixels) written as 16-bit millimetre PNGs, colour frames
and a COLMAP model, as in ``../shared/real/kitchen-7scenes``."""

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from dmrt.app.cli import main
from dmrt.camera import Camera
from dmrt.io import colmap
from dmrt.io.pointcloud import read_points
from dmrt.io.scene import load_scene

NORMAL = np.array([0.2, -0.1, 1.0]) / np.linalg.norm([0.2, -0.1, 1.0])
OFFSET = 0.5  # the plane: NORMAL . x = OFFSET (metres)
W, H = 96, 72


def _frames(root: Path, box: bool = False) -> list[Camera]:
    """Two frames of the plane seen from 2-3 m; with ``box``, the first frame also sees a patch
    1 m nearer (rows 20-40, columns 30-60) whose rim is smeared into "flying pixels" halfway
    between the two surfaces, as depth sensors record them."""
    cams = [Camera.look_at(f"frame-{i:06d}.png", eye, eye + [0.1, 0.2, -1.0], W, H, 70.0, up=(0, 1, 0))
            for i, eye in enumerate(np.array([[0.0, 0.0, 3.0], [0.6, -0.3, 2.5]]))]
    for sub in ("depth", "images"):
        (root / sub).mkdir(parents=True)
    for cam in cams:
        dirs, centre = cam.pixel_rays()  # point = centre + z * dir, z = camera depth
        z = (OFFSET - NORMAL @ centre) / (dirs @ NORMAL)
        z = z.reshape(H, W)
        if box and cam is cams[0]:
            z[20:40, 30:60] -= 1.0
            z[19, 29:61] = z[41, 29:61] = z[20:40, 29] = z[20:40, 60] = z[0, 0] - 0.5  # flying pixels
        mm = np.round(z * 1000).astype(np.uint16)
        Image.fromarray(mm).save(root / "depth" / cam.name)
        colour = np.zeros((H, W, 3), np.uint8)
        colour[..., 0] = np.arange(W)[None, :] * 2
        Image.fromarray(colour).save(root / "images" / cam.name)
    colmap.write_model(root / "sparse", cams)
    return cams


def test_plane_points_lie_on_the_plane(tmp_path, capfd):
    _frames(tmp_path / "frames")
    assert main(["scene", "rgbd", str(tmp_path / "frames"), "--out", str(tmp_path / "scene"), "--quiet"]) == 0
    cloud = read_points(tmp_path / "scene" / "points.ply")
    # depth is stored to the millimetre: each reading's z within 0.5 mm, its position within 0.5 mm
    # times its ray's length per unit z (at most the corner's), and so its distance to the plane
    # (at most the distance along any ray); a voxel's mean of points on the plane stays on it
    tan = np.tan(np.radians(35.0))
    corner = np.sqrt(1 + tan**2 + (tan * H / W) ** 2)
    assert np.abs(cloud.positions @ NORMAL - OFFSET).max() <= 0.5e-3 * corner + 1e-9
    # two frames of 96 x 72 at 2.5-3 m: texels of 3-4 mm, each 4 mm voxel holding one or two
    assert 0.4 * 2 * W * H < len(cloud) <= 2 * W * H
    # colours come from the colour frames: red rises with the column
    assert cloud.colors is not None and cloud.colors[:, 0].max() > 150 and cloud.colors[:, 1:].max() == 0
    out = capfd.readouterr().out
    assert f"{len(cloud):,} points (voxel filter of {2 * W * H:,} depth readings from 2 of the 2 frames)" in out
    scene = load_scene(tmp_path / "scene")  # a whole scene: model and photos copied/linked beside
    assert [c.name for c in scene.cameras] == ["frame-000000.png", "frame-000001.png"]
    # every 2nd frame: the first only
    assert main(["scene", "rgbd", str(tmp_path / "frames"), "--out", str(tmp_path / "one"), "--every", "2",
                 "--voxel", "0.05", "--quiet"]) == 0
    one = read_points(tmp_path / "one" / "points.ply")
    assert f"{W * H:,} depth readings from 1 of the 2 frames" in capfd.readouterr().out
    # coarser voxels: fewer points than readings, each a mean of readings on the plane (as above)
    assert len(one) < 0.7 * W * H and np.abs(one.positions @ NORMAL - OFFSET).max() <= 0.5e-3 * corner + 1e-9


def test_flying_pixels_dropped(tmp_path):
    from dmrt.io.rgbd import back_project, read_depth

    cams = _frames(tmp_path, box=True)
    points, _ = back_project(cams[0], read_depth(tmp_path / "depth" / cams[0].name))
    dist = points @ NORMAL - OFFSET
    # on the plane, or on the patch 1 m nearer along the rays (its distance to the plane: 1 m
    # times the cosine between ray and normal, >= 0.9 here); none in between
    between = (np.abs(dist) > 1e-3) & (np.abs(dist) < 0.8)
    assert not between.any(), dist[between]
    assert (np.abs(dist) > 0.8).sum() > 0.5 * 20 * 30  # the patch's inside stays


@pytest.mark.parametrize("case", ["no_depth", "not_16bit", "exists"])
def test_bad_input(tmp_path, capfd, case):
    frames, out = tmp_path / "frames", tmp_path / "scene"
    _frames(frames)
    name = {"no_depth": frames / "depth", "not_16bit": frames / "depth" / "frame-000001.png", "exists": out}[case]
    if case == "no_depth":
        for f in (frames / "depth").iterdir():
            f.unlink()
        (frames / "depth").rmdir()
    elif case == "not_16bit":
        Image.fromarray(np.zeros((H, W), np.uint8)).save(name)
    else:
        out.mkdir()
    capfd.readouterr()
    assert main(["scene", "rgbd", str(frames), "--out", str(out)]) == 2
    err = capfd.readouterr().err
    assert len(err.splitlines()) == 1 and err.startswith(f"dmrt: error: {name}"), err
    assert sorted(p.name for p in tmp_path.iterdir()) == (["frames", "scene"] if case == "exists" else ["frames"])
