"""E57 input (dmrt.io.e57 through dmrt.io.pointcloud and the scene loader): the real reference files
read as their headers say; multi-scan poses, spherical coordinates, colours, intensity and invalid
records against numpy truth; chunked reads equal whole reads; broken files give one-line InputErrors."""

import uuid
from pathlib import Path

import numpy as np
import pye57
import pytest
from PIL import Image
from pye57 import libe57

from dmrt.camera import Camera
from dmrt.errors import InputError
from dmrt.io import e57
from dmrt.io.colmap import write_model
from dmrt.io.pointcloud import bounds, count_points, iter_point_chunks, read_points
from dmrt.io.scene import load_scene


REAL = Path(__file__).resolve().parents[2] / "shared" / "real" / "e57"
needs_real = pytest.mark.skipif(not REAL.is_dir(), reason=f"real E57 files not present at {REAL}")
PUMP, BUNNY, TINY = "pumpAVisualReferenceImage.e57", "bunnyDouble.e57", "tiny_pc_and_images.e57"


# ---------------------------------------------------------------------------------------- helpers

def rotation(axis, degrees):
    """Rodrigues' formula: an independent truth for the quaternion the file carries."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.radians(degrees)
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) * np.cos(a) + np.sin(a) * kx + (1 - np.cos(a)) * np.outer(k, k)


def quaternion(axis, degrees):
    """(w, x, y, z) of the rotation by ``degrees`` about ``axis``."""
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    a = np.radians(degrees) / 2
    return np.array([np.cos(a), *(np.sin(a) * k)])


def f32(a):
    """Values that pye57's single-precision writer stores exactly."""
    return np.asarray(a, np.float32).astype(np.float64)


def write_raw_scans(path, scans):
    """Write scans with libE57Format's low-level API (pye57's writer knows Cartesian floats only).

    ``scans``: list of ``(fields, pose, extra)``; ``fields`` maps an E57 field name to an array
    (float arrays become double Float nodes; integer arrays Integer nodes with ``extra["limits"]
    [name]`` or the array's range), ``pose`` is ``(quaternion wxyz, translation)`` or None.
    """
    out = pye57.E57(str(path), mode="w")
    imf = out.image_file
    keep = []  # the writer reads the numpy buffers at write(): keep them alive until close()
    for fields, pose, extra in scans:
        scan = libe57.StructureNode(imf)
        scan.set("guid", libe57.StringNode(imf, "{%s}" % uuid.uuid4()))
        if pose is not None:
            p, r, t = (libe57.StructureNode(imf) for _ in range(3))
            for c, v in zip("wxyz", pose[0]):
                r.set(c, libe57.FloatNode(imf, float(v)))
            for c, v in zip("xyz", pose[1]):
                t.set(c, libe57.FloatNode(imf, float(v)))
            p.set("rotation", r)
            p.set("translation", t)
            scan.set("pose", p)
        proto = libe57.StructureNode(imf)
        limits = (extra or {}).get("limits", {})
        arrays = {}
        for name, a in fields.items():
            if a.dtype.kind == "f":
                proto.set(name, libe57.FloatNode(imf, 0.0, libe57.E57_DOUBLE))
                arrays[name] = np.ascontiguousarray(a, np.float64)
            else:
                lo, hi = limits.get(name, (int(a.min()), int(a.max())))
                proto.set(name, libe57.IntegerNode(imf, int(lo), int(lo), int(hi)))
                arrays[name] = np.ascontiguousarray(a, np.int64).astype(np.longlong)
        points = libe57.CompressedVectorNode(imf, proto, libe57.VectorNode(imf, True))
        scan.set("points", points)
        out.data3d.append(scan)
        n = len(next(iter(arrays.values())))
        bufs = libe57.VectorSourceDestBuffer()
        for name, a in arrays.items():
            bufs.append(libe57.SourceDestBuffer(imf, name, a, n, True, True))
        keep.append(arrays)
        w = points.writer(bufs)
        w.write(n)
        w.close()
    out.close()


def two_scan_file(path, seed=0):
    """Two Cartesian scans via pye57's own writer; the second posed. Returns the numpy truth."""
    rng = np.random.default_rng(seed)
    R2, t2 = rotation((1, 2, 3), 40.0), np.array([12.5, -3.25, 100.0])
    truth = {"positions": [], "colors": [], "intensity": [], "scan": []}
    with pye57.E57(str(path), mode="w") as out:
        for i, (n, q, t) in enumerate([(500, np.array([1.0, 0, 0, 0]), np.zeros(3)),
                                       (300, quaternion((1, 2, 3), 40.0), t2)]):
            local = f32(rng.uniform(-5, 5, (n, 3)))
            rgb = rng.integers(0, 256, (n, 3), dtype=np.uint8)
            inten = rng.uniform(0, 1, n).astype(np.float32)
            data = {"cartesianX": local[:, 0], "cartesianY": local[:, 1], "cartesianZ": local[:, 2],
                    "intensity": inten, "colorRed": rgb[:, 0], "colorGreen": rgb[:, 1],
                    "colorBlue": rgb[:, 2]}
            out.write_scan_raw(data, rotation=q, translation=t)
            R = np.eye(3) if i == 0 else R2
            truth["positions"].append((R @ local.T).T + t)
            truth["colors"].append(rgb)
            truth["intensity"].append(inten)
            truth["scan"].append(np.full(n, i))
    truth = {k: np.concatenate(v) for k, v in truth.items()}
    truth["scanners"] = np.array([np.zeros(3), t2])
    return truth


def assert_one_line_error(exc_info, path):
    msg = str(exc_info.value)
    assert str(path) in msg, msg
    assert "\n" not in msg, msg
    return msg


# -------------------------------------------------------------------- 1. the real reference files

@needs_real
@pytest.mark.parametrize("name", [PUMP, BUNNY, TINY])
def test_real_files_match_their_headers(name):
    path = REAL / name
    with pye57.E57(str(path)) as f:  # expected values straight from the file's XML section
        assert f.scan_count == 1
        h = f.get_header(0)
        n_header, fields = h.point_count, set(h.point_fields)
        hdr_bounds = None
        if "cartesianBounds" in h.scan_fields:
            hdr_bounds = (np.array([h.xMinimum, h.yMinimum, h.zMinimum]),
                          np.array([h.xMaximum, h.yMaximum, h.zMaximum]))
        raw = f.read_scan_raw(0, ignore_unsupported_fields=True)  # pye57's own whole-scan read
    # and the same numbers from the folder's README (which decoded them from the XML)
    assert n_header == {PUMP: 155_201, BUNNY: 30_571, TINY: 2}[name]

    pc = read_points(path)
    assert count_points(path) == n_header and len(pc) == n_header  # all records valid (README)
    assert pc.positions.dtype == np.float64 and pc.positions.shape == (n_header, 3)
    lo, hi = bounds(path, chunk_size=20_000)
    np.testing.assert_array_equal(lo, pc.positions.min(0))
    np.testing.assert_array_equal(hi, pc.positions.max(0))
    if hdr_bounds is not None:
        # The pump's writer rounded its bounds outwards to the 1e-6 m quantum of its
        # ScaledInteger coordinates; allow two quanta.
        np.testing.assert_allclose(lo, hdr_bounds[0], atol=2e-6, rtol=0)
        np.testing.assert_allclose(hi, hdr_bounds[1], atol=2e-6, rtol=0)
        assert np.all(lo >= hdr_bounds[0] - 1e-12) and np.all(hi <= hdr_bounds[1] + 1e-12)
    else:  # tiny file: no cartesianBounds; its README gives the two points (0,0,0) and (1,1,1)
        np.testing.assert_array_equal(pc.positions, [[0, 0, 0], [1, 1, 1]])

    xyz = np.stack([raw["cartesianX"], raw["cartesianY"], raw["cartesianZ"]], axis=1)
    np.testing.assert_array_equal(pc.positions, xyz)  # none of the three has a pose
    has_rgb = {"colorRed", "colorGreen", "colorBlue"} <= fields
    assert (pc.colors is not None) == has_rgb == (name == PUMP)
    assert (pc.intensity is not None) == ("intensity" in fields) == (name == PUMP)
    if has_rgb:
        assert pc.colors.dtype == np.uint8
        np.testing.assert_array_equal(pc.colors, np.stack([raw["colorRed"], raw["colorGreen"],
                                                           raw["colorBlue"]], axis=1))
        assert pc.intensity.dtype == np.float32
        np.testing.assert_array_equal(pc.intensity, raw["intensity"])
        # README: decoded intensities 0.384..0.698 (ScaledInteger 0..32767, scale 1/32767)
        assert 0.383 < pc.intensity.min() < 0.385 and 0.697 < pc.intensity.max() < 0.699
    assert pc.normals is None
    np.testing.assert_array_equal(pc.scan_index, 0)
    np.testing.assert_array_equal(e57.scanner_positions(path), [[0.0, 0.0, 0.0]])


# ---------------------------------------------------------------- 2. two scans, the second posed

def test_two_scans_with_pose(tmp_path):
    path = tmp_path / "two.e57"
    truth = two_scan_file(path)
    scans = e57.read_scans(path)
    assert [s.n_records for s in scans] == [500, 300]
    pc = read_points(path)
    assert count_points(path) == 800 and len(pc) == 800
    # float32-exact inputs, float64 maths on both sides: only rounding in R·p + t differs
    np.testing.assert_allclose(pc.positions, truth["positions"], atol=1e-12, rtol=0)
    np.testing.assert_array_equal(pc.colors, truth["colors"])
    np.testing.assert_array_equal(pc.intensity, truth["intensity"])
    np.testing.assert_array_equal(pc.scan_index, truth["scan"])
    np.testing.assert_allclose(e57.scanner_positions(path), truth["scanners"], atol=0, rtol=0)
    np.testing.assert_allclose(scans[1].rotation, rotation((1, 2, 3), 40.0), atol=1e-15)


# ---------------------------------------------------------------------- 3. spherical coordinates

def test_spherical_coordinates_and_non_unit_quaternion(tmp_path):
    # pye57's writer only writes cartesianX/Y/Z and none of the real files has spherical
    # coordinates (the pump has only sphericalBounds), so this scan is written field by field.
    rng = np.random.default_rng(1)
    n = 400
    r = rng.uniform(0.5, 50, n)
    az = rng.uniform(-np.pi, np.pi, n)
    el = rng.uniform(-np.pi / 2, np.pi / 2, n)
    # hand-picked directions first: +x, +y, +z, -x with known xyz
    r[:4], az[:4], el[:4] = [2, 3, 4, 5], [0, np.pi / 2, 1.0, np.pi], [0, 0, np.pi / 2, 0]
    q = 2.5 * quaternion((0, 0, 1), 90.0)  # not unit length: the rotation it means is 90° about z
    t = np.array([1.0, 2.0, 3.0])
    write_raw_scans(tmp_path / "s.e57", [({"sphericalRange": r, "sphericalAzimuth": az,
                                          "sphericalElevation": el}, (q, t), None)])
    (scan,) = e57.read_scans(tmp_path / "s.e57")
    assert scan.coordinates == "spherical"
    pc = read_points(tmp_path / "s.e57")
    # E57 convention (libe57.org "bestCoordinates"): azimuth in the xy plane from +x towards +y,
    # elevation from the xy plane towards +z
    local = np.stack([r * np.cos(el) * np.cos(az), r * np.cos(el) * np.sin(az), r * np.sin(el)], 1)
    np.testing.assert_allclose(local[:4], [[2, 0, 0], [0, 3, 0], [0, 0, 4], [-5, 0, 0]], atol=1e-12)
    Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(pc.positions, local @ Rz.T + t, atol=1e-12, rtol=0)
    np.testing.assert_allclose(np.linalg.norm(pc.positions - t, axis=1), r, rtol=1e-13)
    np.testing.assert_array_equal(e57.scanner_positions(tmp_path / "s.e57"), [t])


def test_invalid_states_and_16bit_colours(tmp_path):
    path = tmp_path / "s.e57"
    xyz = np.arange(18, dtype=float).reshape(6, 3)
    state = np.array([0, 1, 2, 0, 0, 2])  # 1 = direction only, 2 = no data: both dropped
    rgb16 = np.array([[0, 65535, 257]] * 6)  # prototype range 0..65535, no colorLimits
    sph = {"sphericalRange": np.array([1.0, 2.0]), "sphericalAzimuth": np.zeros(2),
           "sphericalElevation": np.zeros(2), "sphericalInvalidState": np.array([2, 0]),
           "colorRed": np.array([0, 65535]), "colorGreen": np.array([0, 0]),
           "colorBlue": np.array([65535, 65535])}
    lim = {c: (0, 65535) for c in ("colorRed", "colorGreen", "colorBlue")}
    write_raw_scans(path, [
        ({"cartesianX": xyz[:, 0], "cartesianY": xyz[:, 1], "cartesianZ": xyz[:, 2],
          "cartesianInvalidState": state, "colorRed": rgb16[:, 0], "colorGreen": rgb16[:, 1],
          "colorBlue": rgb16[:, 2]}, None, {"limits": lim}),
        (sph, None, {"limits": lim}),
    ])
    assert count_points(path) == 8  # the header's records
    pc = read_points(path)
    np.testing.assert_array_equal(pc.positions, np.vstack([xyz[[0, 3, 4]], [[2.0, 0, 0]]]))
    np.testing.assert_array_equal(pc.colors, [[0, 255, 1]] * 3 + [[255, 0, 255]])
    assert pc.intensity is None  # no scan has intensity
    np.testing.assert_array_equal(pc.scan_index, [0, 0, 0, 1])


# --------------------------------------------------------------------------- 4. chunked reading

@needs_real
def test_chunks_equal_whole_real():
    path = REAL / PUMP
    whole = read_points(path)
    chunks = list(iter_point_chunks(path, chunk_size=10_000))
    assert len(chunks) == 16 and all(len(c) <= 10_000 for c in chunks)
    for field in ("positions", "colors", "intensity", "scan_index"):
        np.testing.assert_array_equal(np.concatenate([getattr(c, field) for c in chunks]),
                                      getattr(whole, field))


def test_chunks_across_scans(tmp_path):
    path = tmp_path / "two.e57"
    truth = two_scan_file(path)
    chunks = list(iter_point_chunks(path, chunk_size=7))
    # chunks never span scans: 500 = 71·7 + 3 and 300 = 42·7 + 6
    assert [len(c) for c in chunks] == [7] * 71 + [3] + [7] * 42 + [6]
    whole = list(iter_point_chunks(path, chunk_size=10**6))
    assert len(whole) == 2  # one chunk per scan
    for field in ("positions", "colors", "intensity", "scan_index"):
        np.testing.assert_array_equal(np.concatenate([getattr(c, field) for c in chunks]),
                                      np.concatenate([getattr(c, field) for c in whole]))
    np.testing.assert_allclose(np.concatenate([c.positions for c in chunks]), truth["positions"],
                               atol=1e-12, rtol=0)


# ----------------------------------------------------------------------------- 5. broken files

def _bad_files(tmp_path):
    """(name, file) pairs, each a points.e57 in its own folder."""
    files = {}

    def slot(name):
        d = tmp_path / name
        d.mkdir()
        return d / "points.e57"

    p = files["random bytes"] = slot("random")
    p.write_bytes(np.random.default_rng(0).integers(0, 256, 5000, dtype=np.uint8).tobytes())
    p = files["zero scans"] = slot("empty")
    pye57.E57(str(p), mode="w").close()
    p = files["no coordinates"] = slot("nocoords")
    write_raw_scans(p, [({"intensity": np.linspace(0, 1, 10)}, None, None)])
    if REAL.is_dir():
        data = (REAL / PUMP).read_bytes()
        p = files["truncated"] = slot("truncated")
        p.write_bytes(data[: len(data) // 2])
        # right length, garbage in the binary point section: caught by the page checksums
        p = files["corrupt points"] = slot("corrupt")
        b = bytearray(data)
        b[1_000_000:1_000_100] = bytes(100)
        p.write_bytes(bytes(b))
        # garbage inside the XML section (bunny's starts at byte 740,736, README)
        p = files["corrupt xml"] = slot("xml")
        b = bytearray((REAL / BUNNY).read_bytes())
        b[740_800:740_900] = b"x" * 100
        p.write_bytes(bytes(b))
    return files


EXPECTED = {"random bytes": "not an E57 file", "zero scans": "no scans",
            "no coordinates": "neither cartesianX/Y/Z nor sphericalRange",
            "truncated": "E57 file truncated", "corrupt points": "corrupt point data",
            "corrupt xml": "checksum mismatch"}


def test_broken_files(tmp_path):
    files = _bad_files(tmp_path)
    if not REAL.is_dir():
        assert set(files) == {"random bytes", "zero scans", "no coordinates"}
    for what, path in files.items():
        with pytest.raises(InputError) as err:
            list(iter_point_chunks(path, chunk_size=50_000))
        msg = assert_one_line_error(err, path)
        assert EXPECTED[what] in msg, (what, msg)
        # what the scene loader sees: same error, same file
        scene = path.parent
        make_scene_files(scene)
        with pytest.raises(InputError) as err:
            load_scene(scene)
        assert EXPECTED[what] in assert_one_line_error(err, path), what


def test_unreadable_pose(tmp_path):
    path = tmp_path / "p.e57"
    write_raw_scans(path, [({"cartesianX": np.zeros(2), "cartesianY": np.zeros(2),
                             "cartesianZ": np.zeros(2)}, (np.zeros(4), np.zeros(3)), None)])
    with pytest.raises(InputError, match="zero or non-finite") as err:
        count_points(path)
    assert_one_line_error(err, path)


# --------------------------------------------------------------------------- 6. the scene loader

W, H = 32, 24


def make_scene_files(root, centre=(0.0, 0.0, 0.0)):
    """Two cameras (COLMAP text model) and their PNGs; the point cloud is the caller's."""
    root.mkdir(exist_ok=True)
    centre = np.asarray(centre, float)
    cams = [Camera.look_at(f"img{i}.png", centre + eye, centre, W, H)
            for i, eye in enumerate([(20.0, 0.0, 5.0), (0.0, 20.0, 5.0)])]
    write_model(root / "sparse", cams)
    (root / "images").mkdir(exist_ok=True)
    for c in cams:
        Image.new("RGB", (W, H), (90, 120, 150)).save(root / "images" / c.name)


@needs_real
def test_scene_with_real_e57(tmp_path):
    root = tmp_path / "scene"
    make_scene_files(root)
    (root / "points.e57").symlink_to(REAL / PUMP)  # refer to the real file, never copy it
    s = load_scene(root)
    assert s.points_path.name == "points.e57" and s.n_points == 155_201
    np.testing.assert_array_equal(s.scanner_positions, [[0.0, 0.0, 0.0]])
    # README bounds x -2.904..1.722, y -5.301..-0.793, z -1.900..1.843: centre (-0.59, -3.05,
    # -0.03) rounds to (-1, -3, 0)
    np.testing.assert_array_equal(s.origin, [-1.0, -3.0, 0.0])
    assert sum(len(c) for c in s.iter_points(chunk_size=40_000)) == 155_201


def test_scene_with_posed_scans_and_invalid_records(tmp_path):
    root = tmp_path / "scene"
    make_scene_files(root)
    truth = two_scan_file(root / "points.e57")
    s = load_scene(root, chunk_size=64)
    assert s.n_points == 800
    np.testing.assert_array_equal(s.scanner_positions, truth["scanners"])
    pc = s.read_points()
    np.testing.assert_allclose(pc.positions, truth["positions"], atol=1e-12, rtol=0)
    assert pc.scan_index.max() == len(s.scanner_positions) - 1

    # n_points counts what is read, not the header's records (flagged records are dropped)
    root2 = tmp_path / "scene2"
    make_scene_files(root2)
    write_raw_scans(root2 / "points.e57", [({"cartesianX": np.arange(5.0),
                                             "cartesianY": np.zeros(5), "cartesianZ": np.zeros(5),
                                             "cartesianInvalidState": np.array([0, 2, 0, 1, 0])},
                                            None, None)])
    assert count_points(root2 / "points.e57") == 5
    assert load_scene(root2).n_points == 3


def test_ply_scene_has_no_scanner_positions(tmp_path):
    from dmrt.io.pointcloud import PointCloud, write_points

    root = tmp_path / "scene"
    make_scene_files(root)
    write_points(root / "points.ply", PointCloud(np.random.default_rng(0).uniform(-1, 1, (50, 3))))
    assert load_scene(root).scanner_positions is None
