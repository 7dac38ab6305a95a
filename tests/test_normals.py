"""Normals and splat radii (dmrt.preprocess.normals) against analytic surfaces and sampling patterns."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from dmrt.preprocess.normals import (estimate_normals, iter_with_results, orient_normals, process_chunked,
                          radius_factor, splat_radii)
from dmrt.preprocess.octree import Octree, OctreeConfig


def angle_deg(a, b):
    """Unoriented angle between row vectors (a plane fit has no sign), degrees."""
    a = a / np.linalg.norm(a, axis=1, keepdims=True)
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return np.degrees(np.arccos(np.clip(np.abs(np.einsum("ij,ij->i", a, b)), 0, 1)))


def sphere(n, radius=1.0, noise=0.0, seed=0, centre=(0.0, 0.0, 0.0)):
    rng = np.random.default_rng(seed)
    u = rng.normal(size=(n, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    r = radius + rng.normal(0, noise, n) if noise else radius
    return np.asarray(centre) + u * np.reshape(r, (-1, 1)), u


def planes(n_each, noise, seed=1):
    """Three separated 2x2 m planes with different orientations, Gaussian noise along the normal."""
    rng = np.random.default_rng(seed)
    normals = np.array([[0, 0, 1.0], [1, 0, 0], [0.6, -0.48, 0.64]])
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    origins = np.array([[0, 0, 0.0], [5, 0, 0], [0, 5, 3]])
    pts, nrm = [], []
    for o, nv in zip(origins, normals):
        t1 = np.cross(nv, [0.3, 0.5, 0.8])
        t1 /= np.linalg.norm(t1)
        t2 = np.cross(nv, t1)
        uv = rng.random((n_each, 2)) * 2
        pts.append(o + uv[:, :1] * t1 + uv[:, 1:] * t2 + rng.normal(0, noise, (n_each, 1)) * nv)
        nrm.append(np.tile(nv, (n_each, 1)))
    return np.concatenate(pts), np.concatenate(nrm)


# ---------------------------------------------------------------------------------------------
# normals
# ---------------------------------------------------------------------------------------------
def test_sphere_normals_match_analytic_and_face_the_viewpoint():
    # 20k points on a unit sphere: density 1592 /m^2, so the 16-neighbourhood has a radius
    # r16 = sqrt(16 / (pi * 1592)) = 5.7 cm, an rms lateral spread of r16 / 2 per axis. A least-
    # squares slope from k points with noise sigma has a std of sigma / (sqrt(k) r16 / 2): 1.0 deg per
    # axis for sigma = 2 mm; the tilt (two axes) is Rayleigh-distributed, its 99th percentile
    # 3.03 x 1.0 = 3.0 deg, its median 1.18 x 1.0 = 1.2 deg. The curvature over r16 adds no tilt for
    # a symmetric neighbourhood (< 1.6 deg = r16 / 2R for lopsided ones). Hence 5 deg and 1.5 deg.
    p, u = sphere(20_000, noise=0.002, seed=0)
    n = estimate_normals(p, k=16, viewpoints=np.zeros((1, 3)))
    assert n.dtype == np.float32 and n.shape == p.shape
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    err = angle_deg(n, u)
    assert np.percentile(err, 99) < 5.0 and np.median(err) < 1.5
    # viewpoint at the centre: every normal points inward, n . (v - p) > 0
    assert np.all(np.einsum("ij,ij->i", n, -p) > 0)
    # six scanner stations outside: each point faces its nearest station, i.e. outward here
    stations = 3 * np.concatenate([np.eye(3), -np.eye(3)])
    n_out = estimate_normals(p, k=16, viewpoints=stations)
    j = cKDTree(stations).query(p)[1]
    assert np.all(np.einsum("ij,ij->i", n_out, stations[j] - p) > 0)
    assert np.all(np.einsum("ij,ij->i", n_out, u) > 0)


def test_noise_free_sphere_is_nearly_exact():
    p, u = sphere(20_000, seed=3)
    err = angle_deg(estimate_normals(p, k=16), u)
    # only the neighbourhoods' asymmetry on the curved surface remains: a one-sided neighbourhood of
    # radius r16 = 5.7 cm tilts the fit by at most ~r16 / 2R = 1.6 deg; typical ones much less
    assert np.percentile(err, 99) < 1.6 and np.median(err) < 0.6


def test_noisy_planes_far_from_the_origin_float32_and_per_point_viewpoints():
    # 1 m^2 holds 10000/4 = 2500 points, r16 = 4.5 cm; as for the sphere the slope std per axis is
    # sigma / (sqrt(16) r16 / 2) = 0.95 deg for sigma = 1.5 mm, the tilt's 99th percentile 2.9 deg;
    # points at the planes' borders (one-sided neighbourhoods, larger r16) take the rest up to 5 deg.
    p, truth = planes(10_000, noise=0.0015)
    rng = np.random.default_rng(5)
    # each point seen from a viewpoint on the true normal's side (a per-point scanner position)
    side = np.where(rng.random(len(p)) < 0.5, 1.0, -1.0)[:, None]
    lateral = rng.normal(0, 1.0, p.shape)
    lateral -= np.einsum("ij,ij->i", lateral, truth)[:, None] * truth  # in the plane
    view = p + side * truth * 2.0 + lateral
    expected_sign = np.sign(np.einsum("ij,ij->i", truth * side, view - p))
    assert np.all(expected_sign > 0)
    offset = np.array([600_000.0, 5_300_000.0, 300.0])  # UTM-like coordinates (float64 needed)
    for pos, vp in ((p + offset, view + offset), (p.astype(np.float32), view)):
        n = estimate_normals(pos, k=16, viewpoints=vp)
        assert np.percentile(angle_deg(n, truth), 99) < 5.0
        assert np.all(np.einsum("ij,ij->i", n, vp - pos) > 0)  # oriented, 100 %


def test_orient_normals_modes():
    p = np.array([[0, 0, 0.0], [1, 0, 0], [2, 0, 0]])
    n = np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 1, 0]])
    assert np.all(orient_normals(n, p, None)[:, 2] >= 0) and orient_normals(n, p, None)[2, 1] == 1
    up = orient_normals(n, p, [[0, 0, 10.0]])
    np.testing.assert_array_equal(up[:2, 2], [1, 1])
    per = orient_normals(n, p, [[0, 0, -1.0], [1, 0, 5], [2, -3, 0]])
    np.testing.assert_array_equal(per, [[0, 0, -1], [0, 0, 1], [0, -1, 0]])
    assert estimate_normals(np.zeros((2, 3))).shape == (2, 3)


# ---------------------------------------------------------------------------------------------
# radii
# ---------------------------------------------------------------------------------------------
def grid_plane(h=0.01, m=60, tilt=True):
    ij = np.stack(np.meshgrid(np.arange(m), np.arange(m), indexing="ij"), -1).reshape(-1, 2) * h
    p = np.c_[ij, np.zeros(len(ij))]
    if tilt:  # an arbitrary rotation and offset: nothing axis-aligned about it
        a, b = 0.4, 0.7
        rx = np.array([[1, 0, 0], [0, np.cos(a), -np.sin(a)], [0, np.sin(a), np.cos(a)]])
        rz = np.array([[np.cos(b), -np.sin(b), 0], [np.sin(b), np.cos(b), 0], [0, 0, 1]])
        p = p @ (rz @ rx).T + [12.0, -3.0, 7.0]
    interior = np.all((ij > 2.5 * h) & (ij < (m - 3.5) * h), axis=1)
    return p, interior


@pytest.mark.parametrize("k", [4, 8])
def test_radii_on_a_grid_are_half_the_cell_diagonal(k):
    h = 0.01
    p, interior = grid_plane(h)
    r = splat_radii(p, k=k)
    assert r.dtype == np.float32
    # k = 4: d_4 = h, k = 8: d_8 = sqrt(2) h; both give h / sqrt(2) (float32 and the rotation: 1e-5)
    np.testing.assert_allclose(r[interior], h / np.sqrt(2), rtol=1e-5)
    assert np.all(r[~interior] >= r[interior].min() * (1 - 1e-5))  # borders see fewer neighbours
    np.testing.assert_allclose(splat_radii(p, k=k, scale=2.5)[interior], 2.5 * h / np.sqrt(2), rtol=1e-5)


def test_grid_radii_cover_the_plane_without_gaps():
    h = 0.01
    p, interior = grid_plane(h, tilt=False)
    r = splat_radii(p, k=8)
    rng = np.random.default_rng(0)
    probes = np.c_[rng.uniform(5 * h, 50 * h, (20_000, 2)), np.zeros(20_000)]
    d, j = cKDTree(p).query(probes)
    assert np.all(d <= r[j] * (1 + 1e-6))  # every probe lies inside its nearest point's disc
    # and the radius is tight: 0.9x the radius leaves holes
    assert np.any(d > 0.9 * r[j])


def test_radii_follow_density_falloff():
    # density on a plane falls as exp(-x / 2) over x in [0, 6]: radii ~ 1 / sqrt(density) grow as
    # exp(x / 4); between bin centres 1 and 5 the ratio is e = 2.72
    rng = np.random.default_rng(2)
    n = 60_000
    x = -2 * np.log(1 - rng.random(n) * (1 - np.exp(-3)))  # inverse CDF of exp(-x/2) on [0, 6]
    p = np.c_[x, rng.random(n) * 4, np.zeros(n)]
    r = splat_radii(p, k=8)
    inner = (p[:, 1] > 0.5) & (p[:, 1] < 3.5)
    med = [np.median(r[inner & (np.abs(x - c) < 0.25)]) for c in (0.5, 1, 2, 3, 4, 5)]
    assert all(a < b for a, b in zip(med, med[1:]))
    assert med[-1] / med[1] == pytest.approx(np.e, rel=0.15)


def test_random_sampling_with_scale_closes_holes():
    # documented guidance: Poisson sampling needs scale ~1.5 for (almost) hole-free coverage
    rng = np.random.default_rng(4)
    p = np.c_[rng.random((40_000, 2)), np.zeros(40_000)]
    probes = np.c_[rng.uniform(0.1, 0.9, (20_000, 2)), np.zeros(20_000)]
    tree = cKDTree(p)
    uncovered = {}
    for scale in (1.0, 1.5):
        r = splat_radii(p, k=8, scale=scale)
        # a probe is covered if any disc within the largest radius reaches it
        hits = tree.query_ball_point(probes, r.max())
        uncovered[scale] = np.mean([not np.any(np.linalg.norm(p[h] - q, axis=1) <= r[h])
                                    for q, h in zip(probes, hits)])
    assert uncovered[1.5] < 0.01 < uncovered[1.0]


def test_radius_factor():
    assert radius_factor(8) == pytest.approx(0.5)
    assert radius_factor(4) == pytest.approx(np.sqrt(2) / 2)


# ---------------------------------------------------------------------------------------------
# out of core
# ---------------------------------------------------------------------------------------------
def scene(n_sphere=60_000, n_plane=40_000):
    ps, _ = sphere(n_sphere, radius=2.0, noise=0.002, seed=7, centre=(3, 3, 2.5))
    pp, _ = planes(n_plane // 3 + 1, noise=0.002, seed=8)
    return np.concatenate([ps, pp])


def test_chunked_equals_in_memory(tmp_path):
    p = scene()
    stations = np.array([[3, 3, 2.5], [-5, -5, 5], [10, 10, 5], [2, 8, 8]])
    chunks = lambda: ((p[s:s + 7000], {}) for s in range(0, len(p), 7000))
    res = process_chunked(chunks, tmp_path, viewpoints=stations, memory_limit_mb=1.5, progress=False)
    assert res.n_points == len(p) and res.n_buckets > 10 and res.n_unverified == 0
    assert res.max_bucket_points < len(p) / 4  # buckets with their halos stay a fraction of the cloud
    n_mem = estimate_normals(p, k=16, viewpoints=stations, per_point=False)
    r_mem = splat_radii(p, k=8)
    assert res.normals.dtype == np.float32 and res.normals.shape == (len(p), 3)
    # same neighbourhoods, same fit: equal up to float32 rounding (sign included)
    np.testing.assert_allclose(res.normals, n_mem, atol=2e-5)
    np.testing.assert_allclose(res.radii, r_mem, rtol=1e-5)
    assert sorted(x.name for x in tmp_path.iterdir()) == ["normals.npy", "radii.npy"]

    # a halo too thin for the neighbourhoods is detected and reported, not silently wrong
    thin = process_chunked(chunks, tmp_path / "thin", margin=0.004, memory_limit_mb=1.5, progress=False)
    assert thin.n_unverified > 0

    # within the budget the cloud is processed whole: one tree, same results, same files
    whole = process_chunked(chunks, tmp_path / "whole", viewpoints=stations, memory_limit_mb=64, progress=False)
    assert whole.n_buckets == 1 and whole.n_unverified == 0 and whole.max_bucket_points == len(p)
    np.testing.assert_allclose(whole.normals, n_mem, atol=2e-5)
    np.testing.assert_allclose(whole.radii, r_mem, rtol=1e-5)
    assert sorted(x.name for x in (tmp_path / "whole").iterdir()) == ["normals.npy", "radii.npy"]


def test_chunked_results_feed_the_octree_and_per_lod_radii(tmp_path):
    p = scene(20_000, 12_000)
    chunks = lambda: ((p[s:s + 5000], {"id": np.arange(s, min(s + 5000, len(p)))}) for s in range(0, len(p), 5000))
    res = process_chunked(chunks, tmp_path / "hd", viewpoints=[[3, 3, 2.5]], memory_limit_mb=1, progress=False)
    tree = Octree.build(lambda: iter_with_results(chunks, res), tmp_path / "oct",
                        OctreeConfig(levels=6, memory_limit_mb=1), progress=False)
    assert set(tree.fields) == {"positions", "id", "normals", "radii"}
    lvl = tree.read_level(2)
    np.testing.assert_array_equal(lvl["normals"], res.normals[lvl["id"]])  # attributes travelled
    # radii of a coarse level of detail, from that LOD's own (lower) density: the coarsest LOD with
    # at most 1/8 of the points; on surfaces radii grow like sqrt(sub-sampling factor)
    f = tree.subsampling_factors()
    k = max(i + 1 for i, x in enumerate(f) if x >= 8)
    assert tree.lod_counts()[k - 1] > 500
    lod = process_chunked(lambda: tree.iter_levels(range(k), chunk_size=2000), tmp_path / "lod",
                          normals=False, memory_limit_mb=1, progress=False)
    np.testing.assert_allclose(lod.radii, splat_radii(tree.read_lod(k)["positions"]), rtol=1e-5)
    assert np.median(lod.radii) / np.median(res.radii) > 0.7 * np.sqrt(f[k - 1])


# ---------------------------------------------------------------------------------------------
# out of core, the input passes as tasks over the parts of a splittable source
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def pool():
    """Two spawned worker processes (the local default executor)."""
    from dmrt.preprocess.parallel import ProcessPool

    ex = ProcessPool(2)
    yield ex
    ex.close()


class WholeSource:
    """A splittable source that stays whole (as a PointRange of a format that cannot seek)."""

    def __init__(self, src):
        self.src = src

    def __call__(self):
        return self.src()

    def split(self, parts):
        return [self]


def assert_same_result(a, b):
    assert (a.n_points, a.n_buckets, a.margin, a.n_unverified, a.max_bucket_points) == \
           (b.n_points, b.n_buckets, b.margin, b.n_unverified, b.max_bucket_points)
    for x, y in ((a.normals, b.normals), (a.radii, b.radii)):
        assert (x is None) == (y is None)
        if x is not None:
            assert x.dtype == y.dtype and x.shape == y.shape and x.tobytes() == y.tobytes()


@pytest.fixture(scope="module")
def octree_50k(tmp_path_factory):
    p = scene(30_000, 20_000)
    out = tmp_path_factory.mktemp("oct") / "oct"
    return Octree.build(lambda: ((p[s:s + 10_000], {}) for s in range(0, len(p), 10_000)), out,
                        OctreeConfig(levels=5, memory_limit_mb=4), progress=False)


@pytest.mark.parametrize("given_bbox", [False, True])
def test_input_passes_as_tasks_equal_serial(octree_50k, pool, tmp_path, given_bbox):
    from dmrt.preprocess.buckets import split_input

    src = octree_50k.point_range(chunk_size=3000)
    assert len(split_input(src, pool)) == 2  # the input passes run as 2 tasks each
    # a bbox larger than the cloud's shifts the grids: buckets, halos and part boundaries differ
    p = octree_50k.read_lod(octree_50k.levels)["positions"]
    bbox = (p.min(0) - 0.3, p.max(0) + 0.1) if given_bbox else None
    # 1 MiB: a count cap of 4096 cells that each part's table (25k points) exceeds, and ~40 buckets
    kw = dict(viewpoints=[[3, 3, 2.5]], memory_limit_mb=1, bbox=bbox, progress=False)
    serial = process_chunked(src, tmp_path / "serial", **kw)
    assert serial.n_buckets > 10 and serial.n_unverified == 0 and serial.n_points == octree_50k.n_points
    par = process_chunked(src, tmp_path / "par", executor=pool, **kw)
    assert_same_result(serial, par)  # bit for bit
    assert sorted(x.name for x in (tmp_path / "par").iterdir()) == ["normals.npy", "radii.npy"]


def test_source_that_stays_whole_and_plain_callables_with_a_pool(octree_50k, pool, tmp_path):
    src = octree_50k.point_range(chunk_size=3000)
    kw = dict(normals=False, memory_limit_mb=1, progress=False)
    serial = process_chunked(src, tmp_path / "serial", **kw)
    # one part (input passes here, buckets as tasks), and a plain callable without split
    assert_same_result(serial, process_chunked(WholeSource(src), tmp_path / "whole", executor=pool, **kw))
    assert_same_result(serial, process_chunked(lambda: src(), tmp_path / "plain", executor=pool, **kw))
    # a cloud within the budget: the bbox pass as tasks, then processed whole here
    whole = dict(kw, memory_limit_mb=64)
    a = process_chunked(src, tmp_path / "whole-serial", **whole)
    b = process_chunked(src, tmp_path / "whole-par", executor=pool, **whole)
    assert b.n_buckets == 1
    assert_same_result(a, b)


def test_float32_positions_spill_in_float32_with_the_same_results(octree_50k, tmp_path):
    from dmrt.preprocess.buckets import positions_dtype

    src = octree_50k.point_range(chunk_size=3000)  # the octree's positions are float32
    as64 = lambda: ({**c, "positions": c["positions"].astype(np.float64)} for c in src())  # noqa: E731
    assert (positions_dtype(src), positions_dtype(as64)) == ("float32", "float64")
    kw = dict(viewpoints=[[3, 3, 2.5]], memory_limit_mb=1, progress=False)
    a = process_chunked(src, tmp_path / "f32", **kw)
    b = process_chunked(as64, tmp_path / "f64", **kw)
    assert a.n_buckets > 10
    assert_same_result(a, b)  # the float32 spill held the same values: bit for bit
