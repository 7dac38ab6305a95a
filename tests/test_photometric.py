"""The global photometric adjustment (dmrt.preprocess.photometric): the gain solve on known gains,
the gains preprocessing stores against the synthetic generator's exposures, and the texturing pass
applying them (DMRT and DMT share it) against numpy."""

from __future__ import annotations

import json

import numpy as np
import pytest

from reference.twins import texturing_pass


def _observations(truth, points: int, per_point: int, seed: int = 0, noise: float = 0.0, outliers: float = 0.0,
                  photos=None):
    """CSR candidates of ``points`` points of random albedo, each seen by ``per_point`` of ``photos``
    (default all); photo j records albedo / truth[j] (times log-normal noise; a share ``outliers``
    of the samples replaced by random colours)."""
    rng = np.random.default_rng(seed)
    photos = np.arange(len(truth)) if photos is None else np.asarray(photos)
    albedo = rng.uniform(0.1, 0.7, (points, 3))
    pts = np.repeat(np.arange(points), per_point)
    phs = np.concatenate([np.sort(rng.choice(photos, per_point, replace=False)) for _ in range(points)])
    colors = albedo[pts] / truth[phs] * np.exp(rng.normal(0, noise, (len(pts), 3)))
    bad = rng.random(len(pts)) < outliers
    colors[bad] = rng.uniform(0.05, 0.95, (int(bad.sum()), 3))
    indptr = np.concatenate([[0], np.cumsum(np.bincount(pts, minlength=points))])
    return indptr, phs, colors


def _centred(log_gains):
    return log_gains - log_gains.mean(axis=0)


def test_solver_recovers_known_gains():
    """Photos that record albedo / g_j: the solved gains are g_j up to a common scale, with the mean log
    gain 0; exact without noise and prior, within 0.02 in log with noise and 10 % outliers (the Huber
    weights), and a photo that shares fewer than min_shared points keeps gain 1."""
    from dmrt.preprocess.photometric import PhotometricConfig, solve_photo_gains

    truth = np.random.default_rng(1).uniform(0.7, 1.4, (6, 3))
    ip, ph, col = _observations(truth, 400, 3)
    r = solve_photo_gains(ip, ph, col, 6, PhotometricConfig(prior_observations=0.0))
    np.testing.assert_allclose(_centred(np.log(r.gains)), _centred(np.log(truth)), atol=1e-5)
    np.testing.assert_allclose(np.log(r.gains).mean(axis=0), 0.0, atol=1e-6)
    assert r.photos_adjusted == 6 and r.groups == 1 and r.rms_after < 1e-5 < r.rms_before

    ip, ph, col = _observations(truth, 600, 3, noise=0.02, outliers=0.1)
    r = solve_photo_gains(ip, ph, col, 6)
    err = _centred(np.log(r.gains)) - _centred(np.log(truth))
    print(f"log-gain error with noise and outliers: max {np.abs(err).max():.4f}")
    assert np.abs(err).max() < 0.02

    # photo 6 shares 5 points with the others: no evidence, gain 1; the others as before
    truth7 = np.concatenate([truth, [[1.3, 1.3, 1.3]]])
    ip2, ph2, col2 = _observations(truth7, 5, 2, seed=3, photos=[0, 6])
    r = solve_photo_gains(np.concatenate([ip, ip2[1:] + ip[-1]]), np.concatenate([ph, ph2]),
                          np.concatenate([col, col2]), 7)
    assert r.gains[6].tolist() == [1.0, 1.0, 1.0] and r.group_of[6] == -1 and r.photos_adjusted == 6


def test_two_groups_get_their_own_scale():
    """Photos 0-2 and 3-5 share no point: each group's mean log gain is 0 (the gauge is per group)."""
    from dmrt.preprocess.photometric import PhotometricConfig, solve_photo_gains

    truth = np.random.default_rng(2).uniform(0.7, 1.4, (6, 3))
    a = _observations(truth, 200, 2, seed=0, photos=[0, 1, 2])
    b = _observations(truth, 200, 2, seed=1, photos=[3, 4, 5])
    r = solve_photo_gains(np.concatenate([a[0], b[0][1:] + a[0][-1]]), np.concatenate([a[1], b[1]]),
                          np.concatenate([a[2], b[2]]), 6, PhotometricConfig(prior_observations=0.0))
    assert r.groups == 2 and len(set(r.group_of[:3])) == 1 and r.group_of[0] != r.group_of[3]
    for g in (slice(0, 3), slice(3, 6)):
        np.testing.assert_allclose(_centred(np.log(r.gains[g])), _centred(np.log(truth[g])), atol=1e-5)
        np.testing.assert_allclose(np.log(r.gains[g]).mean(axis=0), 0.0, atol=1e-6)


def test_a_tie_no_cycle_confirms_is_not_trusted():
    """Photos 0-1-2-3 overlapping in a chain (a camera rig's narrow strips): every tie is a bridge, no
    second chain of overlaps confirms its offset, so every gain stays 1; close the ring (3-0) and
    the gains are recovered. With ``cycles`` off the chain is trusted."""
    from dmrt.preprocess.photometric import PhotometricConfig, solve_photo_gains

    truth = np.random.default_rng(4).uniform(0.7, 1.4, (4, 3))

    def pairs(edges):
        parts = [_observations(truth, 100, 2, seed=k, photos=e) for k, e in enumerate(edges)]
        ip = [parts[0][0]]
        for pt in parts[1:]:
            ip.append(pt[0][1:] + ip[-1][-1])
        return np.concatenate(ip), np.concatenate([pt[1] for pt in parts]), np.concatenate([pt[2] for pt in parts])

    chain = [[0, 1], [1, 2], [2, 3]]
    r = solve_photo_gains(*pairs(chain), 4)
    assert (r.gains == 1).all() and r.photos_adjusted == 0 and (r.group_of == -1).all()
    r = solve_photo_gains(*pairs(chain), 4, PhotometricConfig(cycles=False, prior_observations=0.0))
    np.testing.assert_allclose(_centred(np.log(r.gains)), _centred(np.log(truth)), atol=1e-5)
    r = solve_photo_gains(*pairs(chain + [[0, 3]]), 4, PhotometricConfig(prior_observations=0.0))
    assert r.photos_adjusted == 4
    np.testing.assert_allclose(_centred(np.log(r.gains)), _centred(np.log(truth)), atol=1e-5)


def test_preprocessing_gains_recover_the_synthetic_exposures(tiny_bundle, tiny_scene):
    """The tiny scene's photos carry known exposure x white-balance gains (synthetic.json): the gains
    preprocessing solves undo them up to the common scale of each group of tied photos. Its two
    rooms share almost no proxy (a doorway), so they form two groups, each with its own scale.
    Measured: the spread of the true log gains within the groups 0.153 / 0.095, of the corrected
    ones (true + solved) 0.012 / 0.011; the solve takes well under a second."""
    from dmrt.io.bundle import read_bundle

    b = read_bundle(tiny_bundle)
    truth = np.log(np.array(json.loads((tiny_scene / "synthetic.json").read_text())["photo_gains"]))
    meta = b.meta["photometric"]
    assert b.photo_gains.shape == (len(b.cameras), 3) and "photometric_s" in b.meta["timings"]
    groups = np.array(meta["photo_groups"])
    assert len(groups) == len(b.cameras) and meta["photos_adjusted"] >= len(b.cameras) - 2
    assert (b.photo_gains[groups < 0] == 1).all()
    corrected = truth + np.log(b.photo_gains)
    for g in np.unique(groups):
        members = groups == g
        if members.sum() < 3:
            continue
        before, after = truth[members].std(axis=0).mean(), corrected[members].std(axis=0).mean()
        print(f"group {g} ({members.sum()} photos): log-gain spread {before:.3f} -> {after:.3f}")
        assert before > 0.05 and after < 0.3 * before and after < 0.035
        np.testing.assert_allclose(np.log(b.photo_gains[members]).mean(axis=0), 0.0, atol=1e-5)


def test_bundle_gains_default_and_errors(tiny_bundle, tmp_path):
    """A bundle without photo_gains (made before them) has gains 1; a malformed field is an InputError
    naming bundle.json."""
    import shutil

    from dmrt.errors import InputError
    from dmrt.io.bundle import read_bundle

    copy = tmp_path / "b"
    shutil.copytree(tiny_bundle, copy)
    meta = json.loads((copy / "bundle.json").read_text())
    n = len(meta["cameras"])
    del meta["photo_gains"]
    (copy / "bundle.json").write_text(json.dumps(meta))
    np.testing.assert_array_equal(read_bundle(copy).photo_gains, np.ones((n, 3), np.float32))
    meta["photo_gains"] = [[1.0, 1.0]] * n
    (copy / "bundle.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="photo_gains"):
        read_bundle(copy).photo_gains


@pytest.mark.gpu
def test_texturing_multiplies_by_the_gains(ctx, tiny_bundle):
    """RenderConfig/DMTConfig.photometric: each pixel's colour is its photo's colour times that photo's
    gain (the GPU frame with gains equals the one without times the gains, to the rounding of 8 bits),
    against the numpy texturing twin times the gains too (99 % within 3 levels, as test_texturing);
    off, the frame is the photos' own colours. The leveling seams then see the corrected colours: a
    leveled frame is the plain one times the leveling gains."""
    from baselines.dmt import DMTConfig, DMTRenderer
    from dmrt.io.bundle import read_bundle
    from dmrt.runtime.renderer import RenderConfig, Renderer

    b = read_bundle(tiny_bundle)
    gains = b.photo_gains
    assert np.abs(np.log(gains)).max() > 0.05  # the tiny scene's photos do differ
    cam = b.cameras[3].resized(160)
    sync = {"async_photos": False, "max_uploads_per_frame": 0}
    frames = {}
    # the fixed labels: each pixel's colour one photo's, times that photo's gain
    for name, make in (("dmrt", lambda ph, lev=False: Renderer(b, RenderConfig(layers=3, photometric=ph, leveling=lev,
                                                                               photo_choice="labels", **sync), ctx)),
                       ("dmt", lambda ph, lev=False: DMTRenderer(b, DMTConfig(photometric=ph, leveling=lev,
                                                                              labeler="wta", progress=False,
                                                                              **sync), ctx))):
        for key, args in (("off", (False,)), ("on", (True,)), ("leveled", (True, True))):
            r = make(*args)
            try:
                frames[name, key] = r.render(cam)
            finally:
                r.release()
        off, on = frames[name, "off"], frames[name, "on"]
        np.testing.assert_array_equal(off["label"], on["label"])
        hit = on["label"] >= 0
        want = np.clip(off["color"][hit] * gains[on["label"][hit]], 0, 255)
        assert np.abs(on["color"][hit] - want).max() <= 1.0, name
        twin = texturing_pass(cam, on["depth"], on["label"], b.cameras, b.image)
        twin = np.clip(np.rint(twin[hit] * gains[on["label"][hit]]), 0, 255)
        err = np.abs(on["color"][hit].astype(int) - twin).max(axis=-1)
        print(f"{name}: with gains vs numpy twin x gains: 99th pct error {np.percentile(err, 99):.0f}")
        assert np.percentile(err, 99) <= 3, name
        lev = frames[name, "leveled"]
        lg = lev["leveling_gains"]
        expected = np.clip(on["color"][hit] * lg[on["label"][hit]], 0, 255)
        assert np.abs(lev["color"][hit] - expected).max() <= 1.0, name


def test_patch_colors_average_the_disc_box_exactly():
    """A disc facing the camera projects to a square box of whole pixels here; its colour is the plain
    mean of those pixels (numpy twin), and a box off the photo is NaN. The summed-area table's sums
    are exact integers, so the only error is float32 rounding of the result."""
    from dmrt.camera import Camera
    from dmrt.preprocess.photometric import patch_colors

    rng = np.random.default_rng(3)
    img = rng.integers(0, 256, (90, 120, 3), dtype=np.uint8)
    # camera at the origin looking down +z; 100 px focal, principal point at pixel corner (50, 40)
    cam = Camera("c", 120, 90, 100.0, 100.0, 50.0, 40.0, np.eye(3), np.zeros(3))
    # discs at z = 10 m: a 0.5 m radius spans 5 px each way; the second lies far off the photo
    pos = np.array([[0.0, 0.0, 10.0], [0.3, -0.1, 10.0], [100.0, 0.0, 10.0]])
    nrm = np.tile([0.0, 0.0, -1.0], (3, 1))
    radii = np.array([0.5, 0.2, 0.5])
    got = patch_colors(pos, nrm, radii, np.arange(3), np.zeros(3, np.int64), [cam], lambda j: img)
    expect0 = img[35:45, 45:55].reshape(-1, 3).mean(axis=0) / 255.0  # rows 40 +- 5, columns 50 +- 5
    expect1 = img[37:41, 51:55].reshape(-1, 3).mean(axis=0) / 255.0  # centre (53, 39), 2 px each way
    np.testing.assert_allclose(got[0], expect0, rtol=1e-6)
    np.testing.assert_allclose(got[1], expect1, rtol=1e-6)
    assert np.isnan(got[2]).all()
