"""Point cloud I/O: PLY round trips in every layout, streaming, LAS/LAZ, atomic writing."""

import numpy as np
import pytest

from dmrt.errors import InputError
from dmrt.io.pointcloud import (PointCloud, PointWriter, bounds, count_points, iter_point_chunks, point_range,
                             read_points, write_points)


def _cloud(n=1000, normals=True, colors=True, offset=(0.0, 0.0, 0.0), seed=0):
    rng = np.random.default_rng(seed)
    pos = rng.uniform(-50, 50, (n, 3)) + np.asarray(offset)
    nrm = None
    if normals:
        nrm = rng.normal(size=(n, 3)).astype(np.float32)
        nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    col = rng.integers(0, 256, (n, 3), dtype=np.uint8) if colors else None
    return PointCloud(pos, nrm, col)


def _assert_same(a: PointCloud, b: PointCloud):
    assert a.positions.dtype == np.float64
    np.testing.assert_array_equal(a.positions, b.positions)
    for x, y, dt in ((a.normals, b.normals, np.float32), (a.colors, b.colors, np.uint8)):
        assert (x is None) == (y is None)
        if x is not None:
            assert x.dtype == dt
            np.testing.assert_array_equal(x, y)


@pytest.mark.parametrize("normals", [False, True])
@pytest.mark.parametrize("colors", [False, True])
def test_ply_round_trip(tmp_path, normals, colors):
    c = _cloud(normals=normals, colors=colors)
    write_points(tmp_path / "p.ply", c)
    assert count_points(tmp_path / "p.ply") == len(c)
    _assert_same(read_points(tmp_path / "p.ply"), c)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.ply"]  # no temporaries left


def test_utm_coordinates_exact(tmp_path):
    # ~5e6 m northing: float32 would round to 0.5 m, float64 must come back bit for bit
    c = _cloud(offset=(500_000.123456789, 5_000_000.987654321, 312.25))
    c.positions += 1e-7 * np.arange(len(c))[:, None]
    write_points(tmp_path / "utm.ply", c)
    back = read_points(tmp_path / "utm.ply")
    np.testing.assert_array_equal(back.positions, c.positions)
    lo, hi = bounds(tmp_path / "utm.ply", chunk_size=77)
    np.testing.assert_array_equal(lo, c.positions.min(0))
    np.testing.assert_array_equal(hi, c.positions.max(0))


def test_chunks_equal_whole(tmp_path):
    c = _cloud(n=1003)
    write_points(tmp_path / "p.ply", c)
    chunks = list(iter_point_chunks(tmp_path / "p.ply", chunk_size=100))
    assert [len(x) for x in chunks] == [100] * 10 + [3]
    joined = PointCloud(*(np.concatenate([getattr(x, a) for x in chunks])
                          for a in ("positions", "normals", "colors")))
    _assert_same(joined, read_points(tmp_path / "p.ply"))


def test_streamed_writer_many_chunks(tmp_path):
    c = _cloud(n=500)
    with PointWriter(tmp_path / "s.ply", normals=True, colors=True) as w:
        for i in range(0, 500, 64):
            w.write(PointCloud(c.positions[i:i + 64], c.normals[i:i + 64], c.colors[i:i + 64]))
    _assert_same(read_points(tmp_path / "s.ply"), c)


def test_writer_float_positions_and_trimesh_reads_the_padded_header(tmp_path):
    import trimesh

    c = _cloud(n=300)
    with PointWriter(tmp_path / "f.ply", normals=True, colors=True, float_positions=True) as w:
        w.write(c)
    got = read_points(tmp_path / "f.ply")
    # float32 of the coordinates, exactly: the same rounding numpy applies
    np.testing.assert_array_equal(got.positions, c.positions.astype(np.float32).astype(np.float64))
    np.testing.assert_array_equal(got.colors, c.colors)
    # the vertex count is a space-padded field; an independent reader takes it too
    assert len(trimesh.load(tmp_path / "f.ply").vertices) == 300
    assert (tmp_path / "f.ply").stat().st_size == len(_ply_header_bytes(tmp_path / "f.ply")) + 300 * 27


def _ply_header_bytes(path):
    raw = path.read_bytes()
    return raw[:raw.index(b"end_header\n") + len(b"end_header\n")]


def test_point_range_splits_into_the_same_chunks(tmp_path):
    import pickle

    c = _cloud(n=1003)
    write_points(tmp_path / "p.ply", c)
    whole = point_range(tmp_path / "p.ply", chunk_size=100)
    parts = pickle.loads(pickle.dumps(whole.split(3)))
    assert [len(p) for p in parts] == [334, 334, 335]
    joined = [x for p in parts for x in p()]
    assert max(len(x) for x in joined) == 100
    np.testing.assert_array_equal(np.concatenate([x.positions for x in joined]), c.positions)
    np.testing.assert_array_equal(np.concatenate([x.colors for x in joined]), c.colors)
    # an error in a later range names the point's index in the whole file
    c.positions[700, 1] = np.nan
    write_points(tmp_path / "p.ply", c)
    with pytest.raises(InputError, match="first at point index 700"):
        list(parts[2]())


def test_writer_leaves_nothing_on_exception(tmp_path):
    c = _cloud(n=10)
    with pytest.raises(RuntimeError, match="boom"):
        with PointWriter(tmp_path / "x.ply", normals=True, colors=True) as w:
            w.write(c)
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_writer_exception_keeps_previous_file(tmp_path):
    old = _cloud(n=7)
    write_points(tmp_path / "x.ply", old)
    with pytest.raises(RuntimeError):
        with PointWriter(tmp_path / "x.ply", normals=False, colors=False) as w:
            w.write(_cloud(n=3, normals=False, colors=False))
            raise RuntimeError
    _assert_same(read_points(tmp_path / "x.ply"), old)


ASCII_PLY = """ply
format ascii 1.0
comment hand written
element camera 1
property float fov
element vertex 3
property float x
property float y
property float z
property float confidence
property uchar red
property uchar green
property uchar blue
element face 1
property list uchar int vertex_indices
end_header
60.0
1.5 2.5 3.5 0.9 255 0 10
-1 -2 -3 0.1 0 128 20
4e3 5e-1 6 0.5 1 2 3
3 0 1 2
"""


def test_ascii_ply(tmp_path):
    (tmp_path / "a.ply").write_text(ASCII_PLY)
    c = read_points(tmp_path / "a.ply")
    np.testing.assert_array_equal(c.positions, [[1.5, 2.5, 3.5], [-1, -2, -3], [4000, 0.5, 6]])
    np.testing.assert_array_equal(c.colors, [[255, 0, 10], [0, 128, 20], [1, 2, 3]])
    assert c.normals is None
    chunks = list(iter_point_chunks(tmp_path / "a.ply", chunk_size=2))
    np.testing.assert_array_equal(np.concatenate([x.positions for x in chunks]), c.positions)


def test_big_endian_ply_with_extra_elements(tmp_path):
    pos = np.array([[1.25, -2.5, 3.0], [5e6, 4e5, -7.125]])
    nrm = np.array([[0, 0, 1], [1, 0, 0]], np.float32)
    rec = np.empty(2, dtype=[("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("intensity", ">u2"),
                             ("nx", ">f4"), ("ny", ">f4"), ("nz", ">f4")])
    rec["x"], rec["y"], rec["z"] = pos.T
    rec["nx"], rec["ny"], rec["nz"] = nrm.T
    rec["intensity"] = [7, 9]
    header = ("ply\nformat binary_big_endian 1.0\nelement info 2\nproperty short a\n"
              "element vertex 2\nproperty double x\nproperty double y\nproperty double z\n"
              "property ushort intensity\nproperty float nx\nproperty float ny\nproperty float nz\n"
              "element face 1\nproperty list uchar int vertex_indices\nend_header\n")
    body = np.array([1, 2], ">i2").tobytes() + rec.tobytes() + b"\x03" + np.array([0, 1, 1], ">i4").tobytes()
    (tmp_path / "b.ply").write_bytes(header.encode() + body)
    c = read_points(tmp_path / "b.ply")
    np.testing.assert_array_equal(c.positions, pos)
    np.testing.assert_array_equal(c.normals, nrm)
    assert c.colors is None


@pytest.mark.parametrize("ext", ["las", "laz"])
def test_las_laz(tmp_path, ext):
    laspy = pytest.importorskip("laspy")
    rng = np.random.default_rng(3)
    n = 2500
    xyz = np.round(rng.uniform(0, 100, (n, 3)) + [600_000, 5_100_000, 200], 3)
    rgb = rng.integers(0, 65536, (n, 3), dtype=np.uint16)
    header = laspy.LasHeader(point_format=3, version="1.2")
    header.offsets = [600_000, 5_100_000, 0]
    header.scales = [0.001, 0.001, 0.001]
    las = laspy.LasData(header)
    las.x, las.y, las.z = xyz.T
    las.red, las.green, las.blue = rgb.T
    path = tmp_path / f"cloud.{ext}"
    las.write(path)

    assert count_points(path) == n
    c = read_points(path)
    np.testing.assert_allclose(c.positions, xyz, rtol=0, atol=1e-6)  # scaled ints: exact to 1 mm
    np.testing.assert_array_equal(c.colors, (rgb >> 8).astype(np.uint8))
    chunks = list(iter_point_chunks(path, chunk_size=1000))
    assert [len(x) for x in chunks] == [1000, 1000, 500]
    np.testing.assert_array_equal(np.concatenate([x.positions for x in chunks]), c.positions)


def test_nan_reported_per_chunk(tmp_path):
    c = _cloud(n=300, normals=False, colors=False)
    c.positions[250, 1] = np.nan
    write_points(tmp_path / "n.ply", c)
    it = iter_point_chunks(tmp_path / "n.ply", chunk_size=100)
    assert len(next(it)) == 100 and len(next(it)) == 100  # the bad chunk is the third
    with pytest.raises(InputError, match=r"n\.ply.*1 point.*NaN.*index 250"):
        next(it)


def test_nonfinite_normals(tmp_path):
    c = _cloud(n=20)
    c.normals[3] = np.inf
    write_points(tmp_path / "n.ply", c)
    with pytest.raises(InputError, match=r"n\.ply.*inf.*normals.*index 3"):
        read_points(tmp_path / "n.ply")


def test_missing_file_and_extension(tmp_path):
    with pytest.raises(InputError, match=r"nope\.ply.*does not exist"):
        read_points(tmp_path / "nope.ply")
    (tmp_path / "p.xyz").write_text("1 2 3\n")
    with pytest.raises(InputError, match=r"p\.xyz.*extension"):
        read_points(tmp_path / "p.xyz")


def test_unsupported_format(tmp_path):
    (tmp_path / "f.ply").write_bytes(b"ply\nformat binary_middle_endian 1.0\nelement vertex 1\n"
                                     b"property float x\nend_header\n")
    with pytest.raises(InputError, match=r"f\.ply.*unsupported PLY format"):
        read_points(tmp_path / "f.ply")


def test_no_vertex_element(tmp_path):
    (tmp_path / "f.ply").write_bytes(b"ply\nformat ascii 1.0\nelement face 0\n"
                                     b"property list uchar int vertex_indices\nend_header\n")
    with pytest.raises(InputError, match=r"f\.ply.*no 'vertex' element"):
        read_points(tmp_path / "f.ply")
