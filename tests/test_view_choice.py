"""The view-dependent photo choice (``RenderConfig.photo_choice="view"``, dmrt/runtime/view_choice.py)
against its numpy twins (reference.twins.view_scores / view_choice) on the tiny scene, its
visibility test against a depth map that shows an occluder, and its blend along a slow walk."""

import shutil

import numpy as np
import pytest

from dmrt.io.bundle import read_bundle
from dmrt.io.exr import write_depth_exr
from dmrt.runtime.renderer import RenderConfig, Renderer
from dmrt.runtime.view_choice import quads, sample_grid
from helpers import novel_camera
from reference import twins

W, H = 96, 64
SYNC = {"async_photos": False, "max_uploads_per_frame": 0}


def _render(bundle, ctx, camera, **cfg):
    r = Renderer(bundle, RenderConfig(**SYNC, **cfg), ctx)
    try:
        frame = r.render(camera, camera.width, camera.height)
        extra = {}
        if r.view_choice is not None:
            extra["candidates"] = r.view_choice.read_candidates()
            extra["quads"] = quads(camera.fx, r.view_choice.map_focal)
            if r.config.view_blend > 1:
                extra["others"], extra["weights"] = r.view_choice.read_blend(camera.width, camera.height)
        return frame, extra
    finally:
        r.release()


def _local(bundle, cams):
    return [c.relative_to(bundle.origin) for c in cams]


@pytest.mark.parametrize("scale", [1, 5.5])  # 5.5: a frame pixel under half a texel, one choice per 2x2 quad
def test_view_choice_matches_numpy_twin(ctx, bundle, depthmaps, scale):
    cams = bundle.cameras
    view = novel_camera(cams[0], cams[3], 0.4).resized(int(W * scale), int(H * scale))
    cfg = {"view_blend": 3, "view_candidates": 4, "view_distance_weight": 0.3, "view_turn_weight": 0.5}
    paper, _ = _render(bundle, ctx, view, photo_choice="labels")  # the labels the choice starts from
    frame, extra = _render(bundle, ctx, view, photo_choice="view", **cfg)
    np.testing.assert_array_equal(frame["depth"], paper["depth"])  # the choice changes only labels
    local, photos = view.relative_to(bundle.origin), _local(bundle, cams)
    tol = RenderConfig().label_check_tolerance

    # the candidates: the 4 best-scored photos. float32 against float64 scores may differ by a unit
    # where 64 / penalty lies on an integer, so a candidate must score within 1 % of the 4th best.
    assert extra["quads"] == (scale > 1)
    stride, grid = sample_grid(view.width, view.height)
    scores = twins.view_scores(local, frame["depth"], photos, depthmaps, stride, grid, tol, 0.3, 0.5)
    assert len(extra["candidates"]) == min(4, int((scores > 0).sum())) >= 2
    fourth = np.sort(scores)[::-1][len(extra["candidates"]) - 1]
    assert (scores[extra["candidates"]] >= 0.99 * fourth).all(), (scores, extra["candidates"])

    best, weights = twins.view_choice(local, frame["depth"], paper["label"], photos, depthmaps,
                                      extra["candidates"], 3, tol, 0.3, 0.5, extra["quads"])
    hit = frame["depth"] > 0
    assert hit.mean() > 0.5
    # float32 angles on the GPU: a pixel whose two best penalties lie within rounding of each other
    # may order them the other way; such ties are rare (< 1 % of the pixels)
    same = frame["label"] == best[..., 0]
    assert same[hit].mean() > 0.99, same[hit].mean()
    gpu = np.concatenate([frame["label"][..., None], extra["others"][..., :2]], -1)
    both = hit & same & (gpu == best).all(-1)
    assert both[hit].mean() > 0.98
    # weights are stored in 8 bits each (1/255), and float32 penalties move them far less
    np.testing.assert_allclose(extra["weights"][both][:, :3], weights[both], atol=1.5 / 255)
    assert (extra["weights"][~hit] == 0).all() and (extra["others"][~hit] == -1).all()
    assert len(np.unique(frame["label"][hit])) >= 2  # the view really mixes photos here
    if extra["quads"]:  # where one choice per quad and per pixel differ, the GPU took the quad's
        _, alone = twins.view_choice(local, frame["depth"], paper["label"], photos, depthmaps,
                                     extra["candidates"], 3, tol, 0.3, 0.5, quads=False)
        moved = hit & same & (np.abs(alone - weights).max(-1) > 3 / 255)
        assert moved.sum() >= 100, moved.sum()  # measured 883: adjacent pixels' weights differ little
        followed = np.abs(extra["weights"][moved][:, :3] - weights[moved]).max(-1) <= 1.5 / 255
        assert followed.mean() > 0.95, followed.mean()


def test_view_choice_rejects_a_photo_whose_depth_map_shows_an_occluder(ctx, bundle, depthmaps, tmp_path):
    """At photo j's own pose, j is the best photo wherever it sees the point (penalty ~0). Put an
    occluder into j's depth map (half the depth in a square): where the surface comes from another
    photo's map (the raytraced layer's label is not j), j must then never be chosen."""
    ys, xs = np.mgrid[0:H, 0:W]
    # the square in frame pixels, shrunk by a pixel on each side (the map's texel quads straddle its edge)
    inner = (ys >= H / 3 + 1) & (ys < 2 * H / 3 - 1) & (xs >= W / 3 + 1) & (xs < 2 * W / 3 - 1)
    outer = (ys < H / 3 - 1) | (ys >= 2 * H / 3 + 1) | (xs < W / 3 - 1) | (xs >= 2 * W / 3 + 1)
    cfg = {"photo_choice": "view", "view_blend": 1, "view_candidates": 16}
    for j in range(len(bundle.cameras)):  # a photo whose pose sees much surface raytraced from other maps
        view = bundle.cameras[j].resized(W, H)
        clear, _ = _render(bundle, ctx, view, **cfg)
        # pixels where j is chosen though their surface came from another photo's map
        other = inner & (clear["depth"] > 0) & (clear["label_raw"] != j) & (clear["label"] == j)
        if other.sum() >= 50:
            break
    else:
        pytest.fail("no photo pose of the test scene has 50 pixels raytraced from other photos' "
                    "maps and textured from its own photo")
    copy = tmp_path / "occluded.bundle"
    shutil.copytree(bundle.root, copy)
    D = depthmaps[j].copy()
    h, w = D.shape
    D[h // 3:2 * h // 3, w // 3:2 * w // 3] *= 0.5
    write_depth_exr(copy / bundle.meta["depthmaps"][j], D)
    frame, _ = _render(read_bundle(copy), ctx, view, **cfg)
    other &= (frame["depth"] > 0) & (frame["label_raw"] != j)
    assert other.sum() >= 50
    assert (frame["label"][other] != j).all()
    np.testing.assert_array_equal(frame["label"][outer], clear["label"][outer])


def _dense_weights(frame, extra, n):
    """(h*w, n) float: each photo's weight at each pixel (the final label alone without a blend)."""
    label = frame["label"].ravel()
    out = np.zeros((label.size, n))
    rows = np.arange(label.size)
    if "weights" not in extra:
        out[rows[label >= 0], label[label >= 0]] = 1.0
        return out
    photos = np.concatenate([label[:, None], extra["others"].reshape(-1, 3)], 1)
    wts = extra["weights"].reshape(-1, 4)
    for k in range(4):
        m = photos[:, k] >= 0
        np.add.at(out, (rows[m], photos[m, k]), wts[m, k])
    return out / np.maximum(out.sum(1, keepdims=True), 1e-9)


def test_view_blend_changes_smoothly_along_a_slow_walk(ctx, bundle):
    """Along a slow walk, each surface point's photo weights (the frame before's pixel projected
    into the next frame) change little from frame to frame with the blend; with the best photo alone
    they jump (0 to 1) wherever the best photo changes: popping seams."""
    a, b = bundle.cameras[0], bundle.cameras[3]
    steps = [novel_camera(a, b, t).resized(W, H) for t in np.linspace(0.2, 0.35, 16)]
    n = len(bundle.cameras)
    jumps = {}
    for blend in (1, 3):
        r = Renderer(bundle, RenderConfig(photo_choice="view", view_blend=blend, **SYNC), ctx)
        frames = []
        for c in steps:
            f = r.render(c, W, H)
            extra = {} if blend == 1 else dict(zip(("others", "weights"), r.view_choice.read_blend(W, H)))
            frames.append((c, f, _dense_weights(f, extra, n)))
        r.release()
        change = []
        for (c0, f0, w0), (c1, f1, w1) in zip(frames, frames[1:]):
            pts = twins.pixel_points(c0, f0["depth"])
            uv, z = c1.project(pts)
            col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
            ok = (f0["depth"].ravel() > 0) & (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
            col, row = np.where(ok, col, 0), np.where(ok, row, 0)
            # the same surface point: its pixel in the next frame holds its depth (2 cm: well under a
            # texel footprint's worth of depth slope at these distances, far under the rooms' depth steps)
            ok &= np.abs(f1["depth"][row, col] - z) < 0.02
            change.append(np.abs(w1[row * W + col] - w0)[ok].sum(1))
        jumps[blend] = np.concatenate(change)
    pops = {k: (v > 1.5).mean() for k, v in jumps.items()}  # weight moved wholesale to another photo
    # best alone: ~1.6 % of the points pop a frame here (the seams sweeping over the surface); with
    # the blend the weights slide, and what still jumps lies where a photo's visibility ends (an
    # occluding edge: a real change), ~0.4 %; 90 % of the points move less than a tenth of their
    # weight (measured 0.02) and 99 % less than three quarters (0.67), where best alone moves all (2)
    assert pops[3] < 0.005 and pops[1] > 2 * pops[3], pops
    assert np.percentile(jumps[3], 90) < 0.1 and np.percentile(jumps[3], 99) < 0.75
    assert np.percentile(jumps[1], 99) == 2.0


def test_a_photo_list_scores_only_the_listed_photos(ctx, bundle):
    """``ViewChoice.run(photo_list=...)`` (a partial map cache's path) scores the listed photos
    exactly as the full scoring does (integer atomics: order-free) and leaves every other photo at
    0, so no unlisted photo becomes a candidate."""
    from dmrt.runtime.shading import camera_uniforms

    view = novel_camera(bundle.cameras[0], bundle.cameras[3], 0.4).resized(W, H)
    r = Renderer(bundle, RenderConfig(**SYNC, photo_choice="view", view_candidates=4), ctx)
    try:
        r.render(view, W, H)
        choice = r.view_choice
        assert choice.listed is None  # every map resident: every photo scored
        every = np.frombuffer(choice.scores.read(), np.uint32).copy()
        seen = np.flatnonzero(every > 0)
        assert len(seen) >= 3
        unseen = np.flatnonzero(every == 0)[:1]
        listed = np.concatenate([seen[:0:-1], unseen])  # reversed: row r scores listed[r], not photo r
        uniforms = camera_uniforms(view.relative_to(bundle.origin))
        choice.run(r.timer, r._buffers["hits"], r.photos, r.depthmaps, uniforms, photo_list=listed)
        some = np.frombuffer(choice.scores.read(), np.uint32)
        np.testing.assert_array_equal(choice.listed, listed)
        np.testing.assert_array_equal(some[listed], every[listed])
        assert some[seen[0]] == 0 and (np.delete(some, listed) == 0).all()
        assert set(choice.read_candidates()) <= set(listed[every[listed] > 0])
    finally:
        r.release()
