"""The GPU grid kNN (dmrt.preprocess.gpu_knn, shaders/knn_grid.glsl) against pykdtree (KnnTree)."""

from __future__ import annotations

import numpy as np
import pytest
from test_knn import angle_deg

from dmrt.preprocess import gpu_knn, knn

# float32 rounding of the distances: the GPU sees the positions rounded to float32 about the
# bucket's centre (each coordinate moves by <= 2**-24 |c|, a distance by <= sqrt(3) 2**-23 |c|)
# and sums the squares in float32 (a few 2**-24 relative); 8 * 2**-23 of the largest coordinate
# plus the distance bounds both with a margin, and is still ~1e-6 of the spacing of these clouds
EPS32 = float(np.finfo(np.float32).eps)


def centred(p):
    return p - (p.min(axis=0) + p.max(axis=0)) / 2


def assert_knn_equal(p, d, idx, k):
    """``(d, idx)`` of GridKnn(p).query(k) against KnnTree's: the same sorted distances and the
    same neighbour sets, except for candidates tied with the k-th distance."""
    c = centred(np.asarray(p, np.float64))
    d0, i0 = knn.KnnTree(c).query(c, k)
    tol = 8 * EPS32 * (np.abs(c).max() + d0)
    assert d.shape == idx.shape == (len(c), k) and d.dtype == np.float32 and idx.dtype == np.uint32
    np.testing.assert_array_less(np.abs(d - d0), tol + 1e-30)
    # the distances are those of the indices returned, ascending, the point itself first
    true = np.linalg.norm(c[idx] - c[:, None], axis=2)
    np.testing.assert_array_less(np.abs(true - d), tol + 1e-30)
    assert np.all(np.diff(d, axis=1) >= 0)
    np.testing.assert_array_equal(idx[:, 0], np.arange(len(c)))
    s, s0 = np.sort(idx, axis=1), np.sort(i0.astype(np.int64), axis=1)
    assert np.all(np.diff(s, axis=1) > 0), "a neighbour listed twice"
    rows = np.flatnonzero(np.any(s != s0, axis=1))
    for r in rows:  # a different neighbour is one tied with the k-th, within the tolerance
        other = np.setxor1d(s[r], s0[r])
        dist = np.linalg.norm(c[other] - c[r], axis=1)
        np.testing.assert_array_less(np.abs(dist - d0[r, -1]), tol[r, -1])
    return len(rows)


def scan_cloud(seed=0):
    """Points on a floor and two walls seen from a scanner at (0, 0, 1.5): the density falls with
    the squared range (a 100-fold spread), plus a few exact duplicates and an isolated point."""
    rng = np.random.default_rng(seed)
    scanner = np.array([0.0, 0.0, 1.5])
    # ranges with density ~ 1 / range^2 on each surface: a uniform angle, not a uniform position
    a = rng.uniform(0.1, 1.45, 3000)
    floor = np.c_[scanner[2] / np.tan(a) * np.cos(t := rng.uniform(0, 2 * np.pi, 3000)),
                  scanner[2] / np.tan(a) * np.sin(t), np.zeros(3000)]
    floor = floor[np.abs(floor[:, :2]).max(axis=1) < 8]
    y = 8 * np.tan(rng.uniform(-1.2, 1.2, 1500))
    wall_x = np.c_[np.full(1500, 8.0), y, rng.uniform(0, 3, 1500)][np.abs(y) < 8]
    x = 8 * np.tan(rng.uniform(-1.2, 1.2, 1500))
    wall_y = np.c_[x, np.full(1500, 8.0), rng.uniform(0, 3, 1500)][np.abs(x) < 8]
    p = np.vstack([floor, wall_x, wall_y, [[-7.5, -7.5, 2.9]]])
    return np.vstack([p, p[rng.choice(len(p), 20)]]) + [1000.0, 2000.0, 30.0]  # real-world offsets


@pytest.fixture(autouse=True)
def small_slices(monkeypatch):
    # several dispatches on these small clouds (and not a multiple of the workgroup), as a large
    # bucket takes them
    monkeypatch.setattr(gpu_knn, "_SLICE", 1000)


@pytest.mark.gpu
@pytest.mark.parametrize("k", [1, 16, 32])
def test_random_cube(k):
    p = np.random.default_rng(1).random((3000, 3)) * [10.0, 5.0, 2.0]
    grid = gpu_knn.GridKnn(p)
    try:
        d, idx = grid.query(k)
    finally:
        grid.release()
    # continuous positions: ties (within float32 rounding) in a few rows at most
    assert assert_knn_equal(p, d, idx, k) <= 3


@pytest.mark.gpu
@pytest.mark.parametrize("cell_points", [1.0, 8.0, 200.0])
def test_scan_cloud(cell_points):
    """Uneven density, duplicates (ties at distance 0), an outlier: exact for tiny cells (many
    rings), the default and huge cells (few, crowded)."""
    p = scan_cloud()
    grid = gpu_knn.GridKnn(p, cell_points=cell_points)
    try:
        d, idx = grid.query(16)
    finally:
        grid.release()
    assert_knn_equal(p, d, idx, 16)


@pytest.mark.gpu
def test_edge_cases():
    p = np.random.default_rng(2).random((6, 3))
    grid = gpu_knn.GridKnn(p)
    assert_knn_equal(p, *grid.query(6), 6)  # every point's neighbours are all the points
    for k, what in ((7, "k = 7 neighbours of 6 points"), (0, "k = 0")):
        with pytest.raises(ValueError, match=what):
            grid.query(k)
    grid.release()
    many = np.random.default_rng(3).random((40, 3))
    with pytest.raises(ValueError, match="at most 32"):
        gpu_knn.GridKnn(many).query(33)
    one_cell = gpu_knn.GridKnn(many, cell_points=1e6)
    assert one_cell.n_cells == 1
    assert_knn_equal(many, *one_cell.query(32), 32)
    same = np.tile([[5.0, 6.0, 7.0]], (20, 1))  # all in one cell, all tied at distance 0
    d, idx = gpu_knn.GridKnn(same).query(16)
    assert not d.any() and np.all(idx[:, 0] == np.arange(20))
    assert all(len(set(r)) == 16 for r in idx.tolist())
    with pytest.raises(ValueError, match=r"shape \(n, 3\)"):
        gpu_knn.GridKnn(np.zeros((4, 2)))


@pytest.mark.gpu
def test_neighbourhoods_as_knn():
    p = centred(scan_cloud(seed=4))
    normals, d_k = gpu_knn.grid_neighbourhoods(p, k_normals=16, k_radius=8)
    normals0, d_k0 = knn.neighbourhoods(knn.KnnTree(p), p, k_normals=16, k_radius=8)
    np.testing.assert_array_less(np.abs(d_k - d_k0), 8 * EPS32 * (np.abs(p).max() + d_k0))  # as above
    # the same neighbourhoods give the same plane to rounding; a tie swapped at the 16th
    # neighbour may tilt a plane, in a handful of rows
    angle = angle_deg(normals, normals0)
    assert np.count_nonzero(angle > 1e-4) <= 5, np.sort(angle)[-10:]
    only_r = gpu_knn.grid_neighbourhoods(p, k_radius=8)
    assert only_r[0] is None and np.array_equal(only_r[1], d_k)
