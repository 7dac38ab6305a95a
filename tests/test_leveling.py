"""Screen-space leveling (an addition to the paper): the gain solver on known gains, the GPU solve
against its numpy twin, and leveled frames against the synthetic generator's per-photo exposure
truth.
"""

from __future__ import annotations

import numpy as np
import pytest

from helpers import W

# How far the GPU solve's log gains may lie from solve_gains' (float64, direct). The shader runs
# float32 conjugate gradients until |r| <= TOLERANCE |rhs| = 1e-6 |rhs|; with the Jacobi-
# preconditioned matrix's condition number <= (2 + reg) / reg = 201 (the shader's header), the
# relative error of x is at most ~201 x 1e-6, i.e. <= 1.4e-4 for log gains within log(2) (the
# clamp); float32 rounding of the sums adds ~1e-7 x 201. 2e-4 is 0.02 % of a gain: 0.05 of an
# 8-bit level at white, a fifth of the seam sums' own fixed-point step (1 / LOG_SCALE). Measured on
# llvmpipe: at most 2.6e-5 (the chain of 60 photos below; 1.8e-5 for a chain of 300), ~1e-6 on
# random graphs (test_gpu_solve_matches_numpy_twin prints them).
LOG_GAIN_TOL = 2e-4


def seam_pairs(n: int, edges, log_gains: np.ndarray, rng, noise: float = 0.05) -> np.ndarray:
    """(n, n, 4) int32 seam sums as dmrt_leveling_seams.glsl adds them, for ``edges`` = (row a,
    column b, count) with per-photo ``log_gains`` (n, 3) and per-pair noise on the offsets."""
    from dmrt.runtime.leveling import LOG_SCALE

    pairs = np.zeros((n, n, 4), np.int32)
    for a, b, count in edges:
        offset = log_gains[a] - log_gains[b] + rng.normal(0, noise, 3)
        pairs[a, b, 0] += count
        pairs[a, b, 1:] += (np.round(offset * LOG_SCALE) * count).astype(np.int32)
    return pairs


def random_graph(members, rng, extra: int, min_samples: int = 16) -> list:
    """A connected random graph over ``members``: a random spanning tree plus ``extra`` edges, each
    as (smaller, larger, count >= min_samples) as the seam pass writes them."""
    members = list(members)
    edges = {tuple(sorted((members[i], members[int(rng.integers(0, i))]))) for i in range(1, len(members))}
    for _ in range(extra):
        edges.add(tuple(sorted(rng.choice(members, 2, replace=False).tolist())))
    return [(a, b, int(rng.integers(min_samples, 3000))) for a, b in sorted(edges)]


def _case(name: str):
    """(pairs, pixel counts) of one synthetic test case of the GPU solve."""
    rng = np.random.default_rng(sum(map(ord, name)))
    if name == "6 photos":  # connected, one pair below min_samples
        n = 6
        edges = random_graph(range(n), rng, 4) + [(1, 4, 15)]
    elif name == "40 photos":
        # 37 connected; photo 37 with only pairs below min_samples, 38 and 39 without any; some
        # pairs written as (larger, smaller), and one pair in both triangles (the twin's pairs are
        # the matrix's entries, whichever triangle; the seam pass writes the upper one only)
        n = 40
        edges = random_graph(range(37), rng, 60)
        edges += [(b, a, c) for a, b, c in edges[:5]] + [(edges[7][1], edges[7][0], 40)]
        edges += [(37, 3, 10), (5, 37, 15), (37, 20, 1)]
        edges = [e for i, e in enumerate(edges) if i not in range(5)]
    elif name == "clamped":  # exposures spread beyond the clamp (log 2 = 0.69)
        n = 12
        log_gains = rng.uniform(-1.5, 1.5, (n, 3))
        pairs = seam_pairs(n, random_graph(range(n), rng, 10), log_gains, rng)
        return pairs, rng.integers(100, 5000, n)
    elif name == "300 photos, 7 used":
        n = 300
        edges = random_graph(sorted(rng.choice(n, 7, replace=False).tolist()), rng, 4)
    elif name == "chain of 60":  # the slowest graph to converge: its smallest eigenvalues ~ reg
        n = 60
        edges = [(i, i + 1, int(rng.integers(16, 3000))) for i in range(n - 1)]
    elif name == "no seams":
        n = 5
        edges = [(0, 1, 15), (2, 3, 3)]
    pixels = rng.integers(0, 5000, n)
    if name == "6 photos":
        pixels[2] = 0  # a photo with seams but no pixels of its own weighs nothing in the mean
    return seam_pairs(n, edges, rng.uniform(-0.3, 0.3, (n, 3)), rng), pixels


@pytest.mark.parametrize("p_in_shared", [None, False], ids=["shared", "buffer"])
@pytest.mark.parametrize("name", ["6 photos", "40 photos", "clamped", "300 photos, 7 used", "chain of 60",
                                  "no seams"])
def test_gpu_solve_matches_numpy_twin(ctx, name, p_in_shared):
    """shaders/dmrt_leveling_solve.glsl (ScreenLeveler.solve) on uploaded seam sums against
    solve_gains, its float64 numpy twin, within LOG_GAIN_TOL in log gain; photos without a pair of
    min_samples keep exactly 1. Both homes of the search direction: shared memory and, as for
    thousands of photos, the scratch buffer."""
    from dmrt.gl.kernels import Staging
    from dmrt.runtime.leveling import ScreenLeveler, solve_gains

    pairs, pixels = _case(name)
    n = len(pixels)
    twin = solve_gains(pairs, pixels, min_samples=16, max_gain=2.0)
    leveler = ScreenLeveler(ctx, n, min_samples=16, max_gain=2.0, p_in_shared=p_in_shared)
    counts = ctx.buffer(pixels.astype(np.uint32).tobytes())
    staging = Staging(ctx)
    try:
        leveler.pairs.write(pairs.tobytes())
        leveler.solve(counts)
        gains = leveler.read_gains(staging)
    finally:
        leveler.release()
        staging.release()
        counts.release()
    assert gains.shape == (n, 3) and gains.dtype == np.float32
    diff = np.abs(np.log(gains.astype(np.float64)) - np.log(twin.astype(np.float64))).max()
    print(f"{name} ({'shared' if p_in_shared is None else 'buffer'}): max |log gain - twin's| = {diff:.2e}")
    assert diff <= LOG_GAIN_TOL
    unused = (twin == 1).all(axis=1)
    assert (gains[unused] == 1).all()
    if name == "clamped":
        assert np.isclose(twin, 2.0).any() and np.isclose(twin, 0.5).any()
    if name == "no seams":
        assert unused.all()
    if name.endswith("used"):
        assert unused.sum() == n - 7
    if name == "40 photos":
        assert unused[37:].all() and not unused[:37].any()


def test_leveling_solver_recovers_known_gains():
    """dmrt.runtime.leveling.solve_gains on seam sums made from known per-photo gains: the solved gains undo
    them up to one common factor (to the 1/1024 fixed point of the sums), keep the frame's
    pixel-weighted mean log brightness, leave a photo without seams at 1 and ignore pairs with
    fewer than ``min_samples`` samples."""
    from dmrt.runtime.leveling import LOG_SCALE, solve_gains

    rng = np.random.default_rng(3)
    n = 6
    true = rng.uniform(-0.3, 0.3, (n, 3))  # log gains of the photos
    pairs = np.zeros((n, n, 4), np.int32)
    for a, b, count in [(0, 1, 400), (1, 2, 300), (2, 3, 50), (0, 3, 200), (3, 4, 120), (4, 5, 3)]:
        pairs[a, b, 0] = count
        pairs[a, b, 1:] = np.round((true[a] - true[b]) * LOG_SCALE) * count
    pixels = np.array([500, 400, 300, 200, 100, 50])
    gains = solve_gains(pairs, pixels, regularization=1e-6, min_samples=16)
    assert (gains[5] == 1).all()  # its only pair has 3 < 16 samples
    x = np.log(gains[:5].astype(np.float64))
    leveled = true[:5] + x
    np.testing.assert_allclose(leveled - leveled.mean(0), 0, atol=2e-3)
    np.testing.assert_allclose((pixels[:5, None] * x).sum(0), 0, atol=1e-3 * pixels.sum())


def test_leveling_balances_photo_exposures(ctx, renderers, bundle, tiny_scene):
    """Screen-space leveling against the generator's truth: the synthetic photos differ by known
    per-photo exposure x white-balance gains (``synthetic.json``; shading does not depend on the
    view), so a leveled frame's photos should carry equal effective gains. Over six photo
    cameras, the spread (std of log gain over the photos covering >= 1 % of the frame) must at
    least halve; measured 0.13 -> 0.03 on the real preprocessing's bundle. Also the apply pass:
    leveled colours = unleveled x gain of the pixel's photo, to 8-bit rounding; the gains solved on
    the GPU = solve_gains (the numpy twin) of the frame's seam sums and label counts, within
    LOG_GAIN_TOL; and a frame left on the GPU (timing) reads no gains back."""
    import json

    from dmrt.runtime.leveling import solve_gains
    from dmrt.runtime.renderer import RenderConfig, Renderer

    truth = np.log(np.array(json.loads((tiny_scene / "synthetic.json").read_text())["photo_gains"]))
    config = RenderConfig(layers=3, leveling=True, async_photos=False, max_uploads_per_frame=0,
                          photo_choice="labels")  # the fixed labels: a photo a region
    leveler = Renderer(bundle, config, ctx)
    n = len(bundle.cameras)
    before, after, twin_diff = [], [], []
    try:
        for j in range(0, 12, 2):
            cam = bundle.cameras[j].resized(W)
            frame, plain = leveler.render(cam), renderers[3].render(cam)
            gains = frame["leveling_gains"]
            pairs = np.frombuffer(leveler.leveler.pairs.read(), np.int32).reshape(n, n, 4)
            pixels = np.bincount(frame["label"][frame["label"] >= 0], minlength=n)
            twin = solve_gains(pairs, pixels, min_samples=config.leveling_min_samples,
                               max_gain=config.leveling_max_gain)
            twin_diff.append(np.abs(np.log(gains.astype(np.float64)) - np.log(twin.astype(np.float64))).max())
            assert twin_diff[-1] <= LOG_GAIN_TOL
            labels, counts = np.unique(frame["label"][frame["label"] >= 0], return_counts=True)
            big = labels[counts >= 0.01 * frame["label"].size]
            if len(big) < 2:
                continue
            before.append(truth[big].std(axis=0).mean())
            after.append((truth[big] + np.log(gains[big])).std(axis=0).mean())
            hit = frame["label"] >= 0
            expected = np.clip(plain["color"][hit] * gains[frame["label"][hit]], 0, 255)
            assert np.abs(frame["color"][hit] - expected).max() <= 1.0
        print(f"log-gain spread before {np.mean(before):.3f}, after leveling {np.mean(after):.3f}; "
              f"GPU gains vs numpy twin: max |log difference| {max(twin_diff):.2e}")
        assert len(before) >= 3
        assert np.mean(after) <= 0.5 * np.mean(before)
        # a time, or NaN where none was measured (a software rasterizer: dmrt.gl.timer)
        assert not frame["timings"]["leveling"] < 0 and "leveling" in frame["cpu_ms"]
        assert {"leveling:seams", "leveling:solve", "leveling:apply"} <= set(frame["part_timings"])
        kept = leveler.render(bundle.cameras[1].resized(W), readback=False)
        assert "leveling_gains" not in kept and "leveling" in kept["cpu_ms"]
    finally:
        leveler.release()


def test_apply_reaches_every_pixel_of_a_4k_frame(ctx):
    """GL guarantees 65535 workgroups of the apply pass's 64 invocations, 4.19M pixels, fewer than
    a 3840x2160 frame's 8.29M: the pass strides, so the last pixel is leveled as the first. The
    grey 128 times gain 0.5 is 64 to 8-bit rounding (unpackUnorm / packUnorm round to nearest)."""
    from dmrt.gl.abi import HIT_DTYPE
    from dmrt.runtime.leveling import ScreenLeveler

    n = 3840 * 2160
    records = np.zeros(n, HIT_DTYPE)
    records["depth"], records["final_label"] = 1.0, 1
    records["final_label"][::7] = -1  # no photo: left alone
    leveler = ScreenLeveler(ctx, 2)
    hits = ctx.buffer(records.tobytes())
    colors = ctx.buffer(np.full(n, 0xFF808080, np.uint32).tobytes())
    try:
        leveler.gains_buffer.write(np.array([[1, 1, 1, 1], [0.5, 0.5, 0.5, 1]], np.float32).tobytes())
        leveler.apply(hits, colors, n)
        out = np.frombuffer(colors.read(), np.uint32)
        expected = np.where(records["final_label"] == 1, 0xFF404040, 0xFF808080).astype(np.uint32)
        assert np.array_equal(out, expected), f"{(out != expected).sum()} pixels wrong, first at {np.argmax(out != expected)}"
    finally:
        for obj in (hits, colors, leveler):
            obj.release()
