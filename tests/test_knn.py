"""The kNN kernels (dmrt.preprocess.knn) against plain numpy / scipy twins and analytic surfaces."""

from __future__ import annotations

import numpy as np
import pytest

from dmrt.preprocess import knn
from dmrt.preprocess.normals import estimate_normals, splat_radii


def angle_deg(a, b):
    """Unoriented angle between row vectors, degrees (a plane fit has no sign); from the cross
    product's norm, in float64: an arccos of the dot product can resolve no angle below ~1e-2
    degrees for float32 vectors."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    return np.degrees(np.arctan2(np.linalg.norm(np.cross(a, b), axis=1), np.abs(np.einsum("ij,ij->i", a, b))))


def brute_knn(p, k):
    """Twin of KnnTree.query over its own points: all pairwise distances, sorted."""
    d = np.linalg.norm(p[:, None] - p[None], axis=2)
    idx = np.argsort(d, axis=1, kind="stable")[:, :k]
    return np.take_along_axis(d, idx, axis=1), idx


def eigh_normals(p, idx):
    """Twin of pca_normals: the covariance's smallest eigenvector by LAPACK (the former kernel)."""
    nb = p[idx] - p[idx].mean(axis=1, keepdims=True)
    return np.linalg.eigh(np.einsum("bki,bkj->bij", nb, nb))[1][:, :, 0]


def scan_like(n, seed=0):
    """A wavy surface with anisotropic sampling and noise, centred: neighbourhoods of every shape."""
    rng = np.random.default_rng(seed)
    uv = rng.random((n, 2)) * [4.0, 1.0]
    z = 0.2 * np.sin(3 * uv[:, 0]) * np.cos(5 * uv[:, 1]) + rng.normal(0, 0.002, n)
    return np.c_[uv, z] - [2.0, 0.5, 0.0]


@pytest.fixture(autouse=True)
def small_blocks(monkeypatch):
    # blocks, runs and query chunks of a few hundred rows, so that a few thousand points cross
    # every boundary of the kernels' loops
    monkeypatch.setattr(knn, "_BLOCK", 64)
    monkeypatch.setattr(knn, "PCA_RUN", 256)
    monkeypatch.setattr(knn, "_CHUNK", 700)


def test_query_equals_brute_force():
    p = scan_like(1500)
    d, idx = knn.KnnTree(p).query(p, 16)
    d0, idx0 = brute_knn(p, 16)
    # continuous random positions: no ties, so the same neighbours in the same order; distances
    # from the same squared sums, to rounding
    np.testing.assert_array_equal(idx, idx0)
    np.testing.assert_allclose(d, d0, rtol=1e-12, atol=1e-15)
    d1, idx1 = knn.KnnTree(p).query(p[:5] + 0.01, 1, workers=-1)  # other query points, k = 1: 2-D
    assert d1.shape == idx1.shape == (5, 1)
    np.testing.assert_array_equal(idx1[:, 0], np.argmin(np.linalg.norm(p[None] - (p[:5] + 0.01)[:, None], axis=2), 1))


def test_query_refuses_more_neighbours_than_points():
    tree = knn.KnnTree(np.zeros((4, 3)))
    assert tree.query(np.zeros((1, 3)), 4)[1].shape == (1, 4)
    with pytest.raises(ValueError, match="k = 5 neighbours of 4 points"):
        tree.query(np.zeros((1, 3)), 5)
    with pytest.raises(ValueError, match=r"shape \(m, 3\)"):
        knn.KnnTree(np.zeros((4, 2)))


def test_pca_normals_equal_eigh():
    p = scan_like(3000, seed=1)
    _, idx = knn.KnnTree(p).query(p, 16)
    new, old = knn.pca_normals(p, idx), eigh_normals(p, idx)
    np.testing.assert_allclose(np.linalg.norm(new, axis=1), 1.0, atol=1e-12)
    # both are exact up to rounding; the closed form's acos near a flat neighbourhood's r = 1 keeps
    # sqrt(eps) ~ 1e-8 of the eigenvalue, 1e-8 rad = 6e-7 degrees (smallest_eigenvectors' notes)
    assert angle_deg(new, old).max() < 1e-5


def test_smallest_eigenvectors_random_and_degenerate():
    rng = np.random.default_rng(2)
    q, _ = np.linalg.qr(rng.normal(size=(500, 3, 3)))
    lam = np.sort(rng.random((500, 3)), axis=1) * [1.0, 1.0, 1.0]
    lam[:100, 0] = 0.0  # exact planes
    lam[100:200, 1] = lam[100:200, 2]  # lambda_mid = lambda_max: isotropic discs (r = 1)
    a = np.einsum("bij,bj,bkj->bik", q, lam, q)
    v = knn.smallest_eigenvectors(a[:, 0, 0], a[:, 1, 1], a[:, 2, 2], a[:, 0, 1], a[:, 0, 2], a[:, 1, 2])
    # well-separated eigenvalues (gap >= ~1e-3 here): 1e-8 p / gap rad stays below 1e-4 degrees
    gap = lam[:, 1] - lam[:, 0]
    sep = gap > 1e-3
    assert angle_deg(v[sep], q[sep, :, 0]).max() < 1e-4
    # collinear neighbours: any unit vector orthogonal to the line
    d = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
    line = np.outer(np.linspace(-1, 1, 16), d)[None]
    n = knn.pca_normals(line[0], np.arange(16)[None])
    assert abs(n[0] @ d) < 1e-9 and np.linalg.norm(n[0]) == pytest.approx(1.0)
    # identical neighbours (p = 0): (0, 0, 1)
    np.testing.assert_array_equal(knn.pca_normals(np.ones((16, 3)), np.arange(16)[None]), [[0.0, 0.0, 1.0]])


def test_plane_and_sphere_analytic():
    rng = np.random.default_rng(3)
    # a tilted plane 50 m from the origin: exact normals (no noise, no curvature), only rounding of
    # the float64 coordinates relative to each neighbourhood's first point (~1e-14 m over ~3 cm)
    nrm = np.array([0.6, -0.48, 0.64])
    t1 = np.cross(nrm, [0, 0, 1.0])
    t1 /= np.linalg.norm(t1)
    t2 = np.cross(nrm, t1)
    uv = rng.random((4000, 2))
    p = 50.0 + uv[:, :1] * t1 + uv[:, 1:] * t2
    n, _ = knn.neighbourhoods(knn.KnnTree(p), p, k_normals=16)
    assert angle_deg(n, np.tile(nrm, (len(p), 1))).max() < 1e-6
    # a unit sphere, 4000 points: the 16-neighbourhood's radius r16 = sqrt(16 / (pi 4000 / 4 pi))
    # = 0.13; a one-sided neighbourhood tilts the fit by at most ~r16 / 2R = 3.6 degrees
    u = rng.normal(size=(4000, 3))
    u /= np.linalg.norm(u, axis=1, keepdims=True)
    n, _ = knn.neighbourhoods(knn.KnnTree(u), u, k_normals=16)
    assert angle_deg(n, u).max() < 3.6


def test_neighbourhoods_one_query_equals_twins():
    p = scan_like(1500, seed=4)
    tree = knn.KnnTree(p)
    n, d8 = knn.neighbourhoods(tree, p, k_normals=16, k_radius=8)
    d0, idx0 = brute_knn(p, 16)
    np.testing.assert_allclose(d8, d0[:, 8], rtol=1e-12)
    assert angle_deg(n, eigh_normals(p, idx0)).max() < 1e-5
    n_only, none = knn.neighbourhoods(tree, p, k_normals=16)
    none2, d_only = knn.neighbourhoods(tree, p, k_radius=8)
    assert none is None and none2 is None
    np.testing.assert_array_equal(n_only, n)
    np.testing.assert_array_equal(d_only, d8)


def test_estimate_normals_and_splat_radii_equal_the_scipy_path():
    from scipy.spatial import cKDTree

    p = scan_like(3000, seed=5) + [1000.0, 2000.0, 30.0]  # far from the origin: centred inside
    c = p - p.mean(axis=0)
    d, idx = cKDTree(c).query(c, k=16)
    want = eigh_normals(c, idx)
    want[want[:, 2] < 0] *= -1  # the sign estimate_normals gives without viewpoints: n_z >= 0
    got = estimate_normals(p, k=16)
    # float32 output: 6e-8 relative per component, ~1e-5 degrees
    assert angle_deg(got, want).max() < 1e-4
    assert np.all(np.einsum("ij,ij->i", got, want) > 0)
    np.testing.assert_allclose(splat_radii(p, k=8, scale=1.5), (d[:, 8] * 1.5 * 0.5).astype(np.float32), rtol=1e-6)


def test_morton_ordered_query_equals_plain():
    # bench_normals --query-variants times the query with the tree and the queries in Morton order,
    # the results mapped back to the caller's order: they must be the plain query's, exactly
    from bench.bench_normals import ordered_query
    from dmrt.morton import morton_order

    p = scan_like(3000, seed=6)
    o = morton_order(p)
    np.testing.assert_array_equal(np.sort(o), np.arange(len(p)))
    # a locality order: consecutive points in it are far nearer than in the (random) input order
    step = lambda q: np.linalg.norm(np.diff(q, axis=0), axis=1).mean()  # noqa: E731
    assert step(p[o]) < 0.2 * step(p)
    _, d0, i0 = ordered_query(p, p, k=16, rows=700)
    ps = np.ascontiguousarray(p[o])
    _, d, i = ordered_query(ps, ps, k=16, perm=o, rows_of=o, rows=700)
    np.testing.assert_array_equal(i, i0)
    np.testing.assert_array_equal(d, d0)  # the same squared sums of the same pairs
    _, _, wrong = ordered_query(ps, ps, k=16, rows_of=o, rows=700)  # indices not mapped back
    assert not np.array_equal(wrong, i0)
