"""Screen-space leveling (an addition to the paper): the gain solver on known gains, and leveled
frames against the synthetic generator's per-photo exposure truth.
"""

from __future__ import annotations

import numpy as np

from helpers import W


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
    leveled colours = unleveled x gain of the pixel's photo, to 8-bit rounding."""
    import json

    from dmrt.runtime.renderer import RenderConfig, Renderer

    truth = np.log(np.array(json.loads((tiny_scene / "synthetic.json").read_text())["photo_gains"]))
    leveler = Renderer(bundle, RenderConfig(layers=3, leveling=True, async_photos=False, max_uploads_per_frame=0), ctx)
    before, after = [], []
    try:
        for j in range(0, 12, 2):
            cam = bundle.cameras[j].resized(W)
            frame, plain = leveler.render(cam), renderers[3].render(cam)
            gains = frame["leveling_gains"]
            labels, counts = np.unique(frame["label"][frame["label"] >= 0], return_counts=True)
            big = labels[counts >= 0.01 * frame["label"].size]
            if len(big) < 2:
                continue
            before.append(truth[big].std(axis=0).mean())
            after.append((truth[big] + np.log(gains[big])).std(axis=0).mean())
            hit = frame["label"] >= 0
            expected = np.clip(plain["color"][hit] * gains[frame["label"][hit]], 0, 255)
            assert np.abs(frame["color"][hit] - expected).max() <= 1.0
        print(f"log-gain spread before {np.mean(before):.3f}, after leveling {np.mean(after):.3f}")
        assert len(before) >= 3
        assert np.mean(after) <= 0.5 * np.mean(before)
        assert frame["timings"]["leveling"] >= 0 and "leveling" in frame["cpu_ms"]
    finally:
        leveler.release()
