"""Proxy-point labeling (dmrt.preprocess.labeling): energy terms, solver guarantees, real PyMaxflow.

Every energy below is checked against an independent plain-loop implementation of the terms in
the module docstring; the graph-cut solver is checked against winner-take-all, ICM, and the
exhaustive optimum of tiny problems.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from dmrt.camera import Camera
from dmrt.preprocess.labeling import (Candidates, LabelingConfig, _Expansion, _submodular, alpha_expansion,
                           candidate_data_costs, data_costs, energy, icm, knn_edges,
                           label_points, smoothness_costs, winner_take_all)


# ---------------------------------------------------------------------------------------------
# helpers
# ---------------------------------------------------------------------------------------------
def loop_energy(labels, cand, col, cost, edges, lam, lam0):
    """The energy of the module docstring, one point and one edge at a time."""
    e_d = e_s = 0.0
    for i, a in enumerate(labels):
        if a >= 0:
            assert cand[i, a]
            e_d += float(cost[i, a])
    for p, q in edges:
        a, b = labels[p], labels[q]
        if a < 0 or b < 0 or a == b:
            continue
        cpa, cqb = col[p, a].astype(np.float64), col[q, b].astype(np.float64)
        cpb = col[p, b] if cand[p, b] else cqb  # seam fallback: nearest sample of photo b
        cqa = col[q, a] if cand[q, a] else cpa
        e_s += lam * (np.linalg.norm(cpa - cpb) + np.linalg.norm(cqa - cqb)) + lam0
    return e_d + e_s, e_d, e_s


def random_problem(n, m, n_edges, seed, p_cand=0.6, potts=False, no_cand=()):
    """Random candidates (>= 1 per point except ``no_cand``), costs, colours and edges."""
    rng = np.random.default_rng(seed)
    cand = rng.random((n, m)) < p_cand
    cand[np.arange(n), rng.integers(0, m, n)] = True
    cand[list(no_cand)] = False
    cost = np.where(cand, rng.random((n, m)) * 2, np.inf).astype(np.float32)
    if potts:  # every photo sees the same colour: V = λ0 for any label change (a metric)
        col = np.repeat(rng.random((n, 1, 3)), m, axis=1).astype(np.float32)
    else:
        col = rng.random((n, m, 3)).astype(np.float32)
    pairs = set()
    while len(pairs) < n_edges:
        i, j = rng.integers(0, n, 2)
        if i != j:
            pairs.add((min(i, j), max(i, j)))
    return cand, cost, col, np.array(sorted(pairs), np.int64)


def synthetic_scene(n=3000, n_cams=12, seed=0):
    """Points on a floor and two walls of a room corner, cameras looking at them, candidates
    from a frustum + facing + distance rule, colours with per-photo exposure and noise, and a
    small patch facing away from every camera (no candidates)."""
    rng = np.random.default_rng(seed)
    n_back = 40
    k = rng.integers(0, 3, n - n_back)
    u, v = rng.random(n - n_back) * 6, rng.random(n - n_back) * 3
    pos = np.where(k[:, None] == 0, np.stack([u, 2 * v, 0 * u], 1),          # floor z = 0
                   np.where(k[:, None] == 1, np.stack([u, 6 + 0 * u, v], 1),  # wall y = 6
                            np.stack([0 * u, u, v], 1)))                     # wall x = 0
    nrm = np.where(k[:, None] == 0, [0, 0, 1.0], np.where(k[:, None] == 1, [0, -1.0, 0],
                                                           [1.0, 0, 0]))
    back = np.stack([6.5 + 0 * rng.random(n_back), rng.random(n_back), rng.random(n_back)], 1)
    pos = np.concatenate([pos, back])
    nrm = np.concatenate([nrm, np.tile([1.0, 0, 0], (n_back, 1))])  # facing +x, away from all
    cams = []
    for j in range(n_cams):
        eye = rng.uniform([2.0, 1.0, 1.0], [5.5, 4.5, 2.2])
        target = pos[rng.integers(0, n - n_back)]
        cams.append(Camera.look_at(f"c{j}", eye, target, 320, 240, 90.0))
    cand = np.zeros((n, n_cams), bool)
    for j, c in enumerate(cams):
        uv, z = c.project(pos)
        d = c.center - pos
        dist = np.linalg.norm(d, axis=1)
        cand[:, j] = ((z > 0.1) & (uv[:, 0] >= 0) & (uv[:, 0] < c.width) & (uv[:, 1] >= 0)
                      & (uv[:, 1] < c.height) & (np.einsum("ij,ij->i", d, nrm) > 0.05 * dist)
                      & (dist < 8.0))
    albedo = 0.5 + 0.3 * np.sin(pos @ [1.3, 0.7, 2.1])[:, None] * [1.0, 0.8, 0.6]
    gain = rng.uniform(0.7, 1.3, (n_cams, 1)) * rng.uniform(0.9, 1.1, (n_cams, 3))
    col = albedo[:, None, :] * gain[None] + rng.normal(0, 0.02, (n, n_cams, 3))
    col = np.clip(col, 0, 1).astype(np.float32)
    return pos.astype(np.float32), nrm.astype(np.float32), cand, col, cams


@pytest.fixture(scope="module")
def scene():
    return synthetic_scene()


@pytest.fixture(scope="module")
def scene_result(scene):
    pos, nrm, cand, col, cams = scene
    cfg = LabelingConfig()
    res = label_points(pos, nrm, cand, cams, col, cfg, progress=False)
    return cfg, res


def centers_focals(cams):
    return (np.array([c.center for c in cams]), np.array([np.sqrt(c.fx * c.fy) for c in cams]))


# ---------------------------------------------------------------------------------------------
# sparse candidate lists
# ---------------------------------------------------------------------------------------------
def test_candidates_dense_sparse_roundtrip():
    cand, cost, col, _ = random_problem(40, 6, 10, seed=1, no_cand=(3, 17))
    c = Candidates.from_dense(cand, col, cost)
    assert c.n_points == 40 and c.n_photos == 6 and c.nnz == cand.sum()
    d_cand, d_col, d_cost = c.dense()
    assert np.array_equal(d_cand, cand)
    assert np.array_equal(d_col[cand], col[cand])
    assert np.array_equal(d_cost, cost)
    # unordered pairs with duplicates give the same lists
    r, j = np.nonzero(cand)
    rng = np.random.default_rng(0)
    perm = rng.permutation(np.concatenate([np.arange(r.size), np.arange(5)]))
    c2 = Candidates.from_pairs(r[perm], j[perm], col[r[perm], j[perm]], 40, 6)
    assert np.array_equal(c2.indptr, c.indptr) and np.array_equal(c2.photos, c.photos)
    assert np.array_equal(c2.colors, c.colors)
    # lookup and take
    idx, found = c.lookup(r, j)
    assert found.all() and np.array_equal(c.colors[idx], col[r, j])
    _, found = c.lookup([3, 0], [0, np.flatnonzero(~cand[0])[0]])
    assert not found.any()
    order = rng.permutation(40)
    t = c.take(order)
    assert np.array_equal(t.dense()[0], cand[order]) and np.array_equal(t.dense()[2], cost[order])
    with pytest.raises(ValueError):
        Candidates([0, 2], [3, 1], None, 6)  # photos not ascending within the point
    with pytest.raises(ValueError):
        Candidates([0, 1], [6], None, 6)     # photo out of range


# ---------------------------------------------------------------------------------------------
# energy terms
# ---------------------------------------------------------------------------------------------
def test_data_costs_analytic():
    """Footprint d / (f cos θ) in octaves above the best: analytic values."""
    p = np.zeros((1, 3), np.float32)
    nrm = np.array([[0, 0, 1.0]], np.float32)
    s60, c60 = np.sin(np.radians(60)), np.cos(np.radians(60))
    cams = [Camera.look_at("near", [0, 0, 2], [0, 0, 0], 320, 240),      # head-on, 2 m
            Camera.look_at("far", [0, 0, 8], [0, 0, 0], 320, 240),       # head-on, 8 m: 4x
            Camera.look_at("oblique", [2 * s60, 0, 2 * c60], [0, 0, 0], 320, 240),  # 60 deg: 2x
            Camera.look_at("sharp", [0, 0, 2], [0, 0, 0], 640, 480),     # twice the focal
            Camera.look_at("grazing", [2, 0, 0.02], [0, 0, 0], 320, 240)]  # cos 0.01 < min_cos
    C, f = centers_focals(cams)
    assert f[3] == pytest.approx(2 * f[0])
    cand = np.ones((1, 5), bool)
    cfg = LabelingConfig()
    d = data_costs(p, nrm, C, f, cand, cfg)[0]
    grazing = 1 + np.log2(1 / cfg.min_cos) + np.log2(np.hypot(2, 0.02) / 2)
    np.testing.assert_allclose(d, [1, 3, 2, 0, grazing], atol=1e-5)
    assert d[0] < d[1] and d[0] < d[2]      # near head-on beats far and oblique
    # unoriented normals: the flipped normal gives the same costs
    np.testing.assert_allclose(data_costs(p, -nrm, C, f, cand, cfg)[0], d, atol=1e-6)
    # non-candidates are inf, the rest re-normalised to their own best
    cand2 = np.array([[True, True, True, False, False]])
    np.testing.assert_allclose(data_costs(p, nrm, C, f, cand2, cfg)[0],
                               [0, 2, 1, np.inf, np.inf], atol=1e-5)
    # weights: distance only
    cfg_d = LabelingConfig(orthogonality_weight=0.0)
    np.testing.assert_allclose(data_costs(p, nrm, C, f, cand2, cfg_d)[0],
                               [0, 2, 0, np.inf, np.inf], atol=1e-5)
    # the sparse form gives the same numbers, far from the origin too (UTM-like offsets)
    off = np.array([512300.0, 5312700.0, 210.0])
    sp = candidate_data_costs(p + off, nrm, C + off, f, Candidates.from_dense(cand), cfg)
    np.testing.assert_allclose(sp, d, atol=1e-4)


def test_knn_edges_brute_force():
    rng = np.random.default_rng(3)
    pts = rng.random((300, 3)).astype(np.float32)
    e = knn_edges(pts, 5)
    assert e.dtype == np.int64 and e.shape[1] == 2
    assert np.all(e[:, 0] < e[:, 1])
    assert len(np.unique(e, axis=0)) == len(e)
    d = np.linalg.norm(pts[:, None] - pts[None], axis=2)
    np.fill_diagonal(d, np.inf)
    nb = np.argsort(d, axis=1)[:, :5]
    want = {(min(i, j), max(i, j)) for i in range(300) for j in nb[i]}
    assert set(map(tuple, e.tolist())) == want
    assert knn_edges(pts[:1], 5).shape == (0, 2)


def test_energy_matches_plain_loop():
    cfg = LabelingConfig(smoothness_weight=1.7, label_change_cost=0.3)
    cand, cost, col, edges = random_problem(60, 5, 150, seed=4, no_cand=(7, 8))
    rng = np.random.default_rng(5)
    for trial in range(5):
        labels = np.array([rng.choice(np.flatnonzero(r)) if r.any() else -1 for r in cand])
        want = loop_energy(labels, cand, col, cost, edges, 1.7, 0.3)
        got = energy(labels, cost, edges, col, cfg)
        np.testing.assert_allclose(got, want, rtol=1e-6)
        sp = Candidates.from_dense(cand, col)
        got_sp = energy(labels, cost[cand], edges, sp, cfg)  # (nnz,) costs with CSR colours
        np.testing.assert_allclose(got_sp, want, rtol=1e-6)
    # per-edge seam costs: symmetric under swapping the ends, 0 for equal labels
    lp = labels[edges[:, 0]]
    lq = labels[edges[:, 1]]
    v = smoothness_costs(edges, lp, lq, col, cfg, candidates=cand)
    v_sw = smoothness_costs(edges[:, ::-1], lq, lp, col, cfg, candidates=cand)
    np.testing.assert_allclose(v, v_sw, rtol=1e-6)
    assert np.all(v[(lp == lq) | (lp < 0) | (lq < 0)] == 0)
    assert np.all(v[(lp != lq) & (lp >= 0) & (lq >= 0)] >= 0.3 - 1e-6)
    # a label that is not a candidate has infinite energy
    bad = labels.copy()
    bad[0] = np.flatnonzero(~cand[0])[0] if (~cand[0]).any() else bad[0]
    if bad[0] != labels[0]:
        assert energy(bad, cost, edges, col, cfg)[0] == np.inf


# ---------------------------------------------------------------------------------------------
# solver
# ---------------------------------------------------------------------------------------------
def test_labels_are_candidates(scene, scene_result):
    pos, nrm, cand, col, cams = scene
    cfg, res = scene_result
    lab = res.labels
    assert lab.dtype == np.int32 and lab.shape == (len(pos),)
    has = cand.any(1)
    assert (~has).sum() >= 40                       # the back-facing patch
    assert np.all(lab[~has] == -1)
    assert np.all(lab[has] >= 0)
    assert cand[np.flatnonzero(has), lab[has]].all()  # 100 % of labels are candidates


def test_graph_cut_beats_wta_and_icm(scene, scene_result):
    pos, nrm, cand, col, cams = scene
    cfg, res = scene_result
    C, f = centers_focals(cams)
    data = data_costs(pos, nrm, C, f, cand, cfg)
    edges = knn_edges(pos, cfg.k_neighbors)
    assert res.n_edges == np.sum(cand.any(1)[edges].all(1))  # edges between labeled points
    e_gc = energy(res.labels, data, edges, col, cfg)
    # the solver's own bookkeeping agrees with the independent energy
    assert e_gc[0] == pytest.approx(res.energy_per_sweep[-1], rel=1e-5)
    assert e_gc[1] == pytest.approx(res.data_energy, rel=1e-5)
    assert e_gc[2] == pytest.approx(res.smooth_energy, rel=1e-5)
    wta = winner_take_all(data)
    assert np.all(wta[~cand.any(1)] == -1)
    e_wta = energy(wta, data, edges, col, cfg)[0]
    assert e_wta == pytest.approx(res.energy_per_sweep[0], rel=1e-5)
    lab_icm = icm(wta, data, edges, col, cfg)
    e_icm = energy(lab_icm, data, edges, col, cfg)[0]
    assert e_icm < e_wta
    assert e_gc[0] < e_icm < e_wta
    # energy never increases over sweeps
    assert np.all(np.diff(res.energy_per_sweep) <= 1e-9 * abs(res.energy_per_sweep[0]))
    assert len(res.seconds_per_sweep) == len(res.energy_per_sweep) - 1 >= 1
    # seams matter: the cut uses fewer label changes along edges than winner-take-all
    changes = lambda lab: np.sum(lab[edges[:, 0]] != lab[edges[:, 1]])
    assert changes(res.labels) < 0.7 * changes(wta)


def test_dense_and_sparse_inputs_agree(scene, scene_result):
    pos, nrm, cand, col, cams = scene
    cfg, res = scene_result
    sp = Candidates.from_dense(cand, col)
    res2 = label_points(pos, nrm, sp, cams, config=cfg, progress=True)
    assert np.array_equal(res2.labels, res.labels)
    # no spatial sort: same energy within the solver's tolerance, labels still candidates
    res3 = label_points(pos, nrm, sp, cams, config=LabelingConfig(spatial_sort=False),
                        progress=False)
    has = cand.any(1)
    assert cand[np.flatnonzero(has), res3.labels[has]].all()
    assert res3.energy_per_sweep[-1] == pytest.approx(res.energy_per_sweep[-1], rel=0.01)


@pytest.mark.parametrize("local_moves", [False, True])
@pytest.mark.parametrize("p_cand", [0.6, 0.2])
def test_every_move_decreases_energy(local_moves, p_cand):
    """Random colours and sparse candidates (many seam fallbacks, V far from a metric): every
    single move lowers the energy, every move's pair terms are submodular (the triangle-
    inequality argument of the module docstring), and the solver's cached per-edge costs stay
    equal to the independent energy."""
    cand, cost, col, edges = random_problem(300, 6, 900, seed=6, p_cand=p_cand, no_cand=(0, 1))
    cfg = LabelingConfig(smoothness_weight=2.0, label_change_cost=0.0, local_moves=local_moves)
    st = _Expansion(Candidates.from_dense(cand, col, cost), edges, cfg)
    e_prev = st.energy()[0]
    assert e_prev == pytest.approx(loop_energy(st.labels, cand, col, cost, edges, 2.0, 0.0)[0])
    n_changed = 0
    for sweep in range(4):
        for alpha in range(6):
            n_changed += max(st.expand(alpha, local_moves), 0)
            e = st.energy()[0]
            assert e <= e_prev + 1e-9
            assert e == pytest.approx(energy(st.labels, cost, edges, col, cfg)[0], rel=1e-5)
            e_prev = e
    assert n_changed > 0
    assert st.n_truncated == 0


def test_submodular_truncation():
    """The guard raises E01 and E10 (never lowers E00): an upper bound exact at (0, 0)."""
    rng = np.random.default_rng(11)
    E00, E01, E10 = (rng.random(1000).astype(np.float32) * s for s in (3, 1, 1))
    B, C, cap, n = _submodular(E00, E01, E10)
    viol = E00 > E01 + E10
    assert n == viol.sum() > 0
    assert np.all(B >= E01) and np.all(C >= E10) and np.all(cap >= 0)
    np.testing.assert_allclose((B + C)[viol], E00[viol], rtol=1e-6)
    assert np.array_equal(B[~viol], E01[~viol]) and np.array_equal(C[~viol], E10[~viol])
    np.testing.assert_allclose(cap[~viol], (E01 + E10 - E00)[~viol], rtol=1e-5, atol=1e-6)


def brute_force(cand, cost, col, edges, lam, lam0):
    n, m = cand.shape
    choices = [np.flatnonzero(r) if r.any() else np.array([-1]) for r in cand]
    best = np.inf
    for lab in itertools.product(*choices):
        best = min(best, loop_energy(np.array(lab), cand, col, cost, edges, lam, lam0)[0])
    return best


@pytest.mark.parametrize("seed", range(8))
def test_expansion_bound_on_tiny_problems(seed):
    """8 nodes, 3 labels, exhaustive optimum. Potts (colours equal in every photo, so
    V = λ0 per label change, a metric): alpha-expansion is within 2x the optimum. Non-metric
    random colours: no bound, but never below the optimum and never worse than WTA."""
    cfg = LabelingConfig(smoothness_weight=1.0, label_change_cost=0.8, local_moves=False,
                         max_sweeps=20, tolerance=0.0)
    for potts in (True, False):
        cand, cost, col, edges = random_problem(8, 3, 12, seed=seed, p_cand=0.7, potts=potts,
                                                no_cand=(5,) if seed % 2 else ())
        opt = brute_force(cand, cost, col, edges, 1.0, 0.8)
        res = alpha_expansion(cost, edges, col, cfg)
        e = loop_energy(res.labels, cand, col, cost, edges, 1.0, 0.8)[0]
        assert e == pytest.approx(res.energy_per_sweep[-1], rel=1e-5)
        assert e >= opt - 1e-6
        wta = winner_take_all(cost)
        assert e <= loop_energy(wta, cand, col, cost, edges, 1.0, 0.8)[0] + 1e-9
        if potts:
            assert e <= 2 * opt + 1e-6


def test_icm_is_a_local_minimum():
    cand, cost, col, edges = random_problem(80, 4, 200, seed=9)
    cfg = LabelingConfig()
    wta = winner_take_all(cost)
    lab = icm(wta, cost, edges, col, cfg)
    e = loop_energy(lab, cand, col, cost, edges, 1.0, 0.1)[0]
    assert e <= loop_energy(wta, cand, col, cost, edges, 1.0, 0.1)[0]
    for i in range(80):  # no single point can improve alone
        for a in np.flatnonzero(cand[i]):
            trial = lab.copy()
            trial[i] = a
            assert loop_energy(trial, cand, col, cost, edges, 1.0, 0.1)[0] >= e - 1e-6


def test_start_labels_and_degenerate_inputs():
    cand, cost, col, edges = random_problem(50, 4, 120, seed=10, no_cand=(2,))
    wta = winner_take_all(cost)
    res = alpha_expansion(cost, edges, col, LabelingConfig(), labels0=wta)
    assert res.energy_per_sweep[0] == pytest.approx(energy(wta, cost, edges, col)[0], rel=1e-6)
    bad = wta.copy()
    bad[0] = np.flatnonzero(~cand[0])[0] if (~cand[0]).any() else -1
    with pytest.raises(ValueError):
        alpha_expansion(cost, edges, col, LabelingConfig(), labels0=bad)
    # no candidates anywhere: everything -1, zero energy
    none = np.full((5, 3), np.inf, np.float32)
    res = alpha_expansion(none, np.array([[0, 1], [1, 2]]), np.zeros((5, 3, 3), np.float32))
    assert np.all(res.labels == -1) and res.energy_per_sweep[-1] == 0
    # no edges: the cut is winner-take-all
    res = alpha_expansion(cost, np.zeros((0, 2), np.int64), col)
    assert np.array_equal(res.labels, wta)
    # camera count must match the photos
    pos = np.random.default_rng(0).random((50, 3)).astype(np.float32)
    with pytest.raises(ValueError):
        label_points(pos, pos, cand, [Camera.look_at("c", [0, 0, 5], [0, 0, 0], 64, 48)], col,
                     progress=False)
