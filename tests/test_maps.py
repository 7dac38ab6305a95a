"""The depth-map cache (dmrt/runtime/maps.py): with fewer slots than photos, frames equal those
rendered with every map resident, the misses loaded and the frame rendered again; a frame that
needs more maps than the cache holds says so."""

import numpy as np
import pytest

from dmrt.errors import ConfigError
from dmrt.runtime.renderer import RenderConfig, Renderer
from helpers import novel_camera

SYNC = {"async_photos": False, "max_uploads_per_frame": 0}


def _slot_mb(renderer, slots: float) -> float:
    """MiB of ``slots`` slots (a depth map and a low-resolution copy each)."""
    return slots * sum(renderer.maps.nbytes.values()) / renderer.maps.n_slots / 2 ** 20


@pytest.mark.parametrize("choice", ["labels", "view"])
def test_a_walk_with_fewer_slots_than_photos_renders_the_same_frames(ctx, bundle, choice):
    full = Renderer(bundle, RenderConfig(**SYNC, photo_choice=choice), ctx)
    assert not full.maps.partial and full.maps.n_slots == len(bundle.cameras) == 12
    # 8 slots: every view of this walk needs at most 7 maps (the labels, the label check's, the
    # view choice's candidates), so the cache can hold each frame's own
    small = Renderer(bundle, RenderConfig(**SYNC, photo_choice=choice, map_cache_mb=_slot_mb(full, 8.5)), ctx)
    try:
        assert small.maps.partial and small.maps.n_slots == 8 and small.maps.defines == {"MAP_SLOTS": 1}
        assert small.gpu_bytes["depthmaps"] == full.gpu_bytes["depthmaps"] * 8 // 12
        rerendered = 0
        for t in np.linspace(0.0, 1.0, 6):
            view = novel_camera(bundle.cameras[0], bundle.cameras[5], t).resized(96, 64)
            a, b = full.render(view), small.render(view)
            assert b["maps_missing"] == 0
            rerendered += bool(b.get("rerendered"))
            for key in ("depth", "label", "color"):
                np.testing.assert_array_equal(a[key], b[key], err_msg=f"{key} at t={t}")
        assert rerendered >= 1 and small.maps.loads >= 2  # the walk really went past the first fill
    finally:
        full.release()
        small.release()


def test_a_frame_that_needs_more_maps_than_the_cache_holds_says_so(ctx, bundle):
    full = Renderer(bundle, RenderConfig(**SYNC, photo_choice="labels"), ctx)
    small = Renderer(bundle, RenderConfig(**SYNC, photo_choice="labels", map_cache_mb=_slot_mb(full, 3.5)), ctx)
    try:
        view = novel_camera(bundle.cameras[0], bundle.cameras[5], 1.0).resized(96, 64)
        a, b = full.render(view), small.render(view)
        assert len(np.unique(a["label"][a["label"] >= 0])) > 3  # more photos than the 3 slots
        assert b["maps_missing"] > 0 and b["rerendered"]
    finally:
        full.release()
        small.release()
    with pytest.raises(ConfigError, match="--map-cache-mb: .* holds no photo"):
        Renderer(bundle, RenderConfig(map_cache_mb=0.001), ctx)


def test_frames_left_on_the_gpu_load_their_missing_maps_two_frames_late(ctx, bundle):
    """Without a read-back the renderer does not wait for a frame's flags: it reads those of the
    frame two before and loads what they name, so the third frame has its maps."""
    full = Renderer(bundle, RenderConfig(**SYNC, photo_choice="labels"), ctx)
    small = Renderer(bundle, RenderConfig(**SYNC, photo_choice="labels", map_cache_mb=_slot_mb(full, 8.5)), ctx)
    try:
        view = novel_camera(bundle.cameras[0], bundle.cameras[5], 1.0).resized(96, 64)
        a = full.render(view)
        assert not np.isin(np.unique(a["label"][a["label"] >= 0]), np.arange(8)).all()  # past the first fill
        loads = []
        for _ in range(3):
            small.render(view, readback=False)
            loads.append(small.maps.loads)
        assert loads[0] == loads[1] == 0 < loads[2]  # the first frame's flags, read by the third
        b = small.render(view)
        assert "rerendered" not in b and b["maps_missing"] == 0
        for key in ("depth", "label", "color"):
            np.testing.assert_array_equal(a[key], b[key])
    finally:
        full.release()
        small.release()


def _replicated(bundle, root, copies: int):
    """``bundle`` with every photo ``copies`` times (the same files) and each proxy labelled with one
    of its photo's copies in turn: the frames equal the original's, from photos past 2048."""
    import json
    import shutil

    from dmrt.io.bundle import read_bundle

    shutil.copytree(bundle.root, root)
    meta = json.loads((root / "bundle.json").read_text())
    n = len(meta["cameras"])
    cams = [dict(c, name=f"{k}-{c['name']}") for k in range(copies) for c in meta["cameras"]]
    meta.update(cameras=cams, **{key: meta[key] * copies for key in ("images", "images_low", "depthmaps")})
    (root / "bundle.json").write_text(json.dumps(meta))
    proxy = dict(np.load(root / "proxy.npz"))
    proxy["labels"] = (proxy["labels"] + n * (np.arange(len(proxy["labels"])) % copies)).astype(np.int32)
    np.savez(root / "proxy.npz", **proxy)
    return read_bundle(root)


def test_more_photos_than_a_texture_array_holds(ctx, bundle, tmp_path):
    """2,100 photos (the tiny bundle's 12, 175 times each; proxies spread over the copies): more than
    GL_MAX_ARRAY_TEXTURE_LAYERS (2048 on Mesa and NVIDIA). DMRT renders the original's frames; DMT
    refuses with one line."""
    from baselines.dmt.renderer import DMTConfig, DMTRenderer
    from dmrt.errors import InputError

    many = _replicated(bundle, tmp_path / "many.bundle", 175)
    layers = ctx.info["GL_MAX_ARRAY_TEXTURE_LAYERS"]
    assert len(many.cameras) == 2100 > layers
    full = Renderer(bundle, RenderConfig(**SYNC, photo_choice="labels"), ctx)
    big = Renderer(many, RenderConfig(**SYNC, photo_choice="labels"), ctx)
    try:
        assert big.maps.partial and big.maps.n_slots == layers
        for t in (0.0, 0.5, 1.0):
            view = novel_camera(bundle.cameras[0], bundle.cameras[5], t).resized(96, 64)
            a, b = full.render(view), big.render(view)
            assert b["maps_missing"] == 0 and (b["label"][b["label"] >= 0] >= layers).any()
            # the same photos, but the passes break exact depth ties by label index, which the copies
            # change: measured 6 of 6144 pixels at one view
            same = (b["label"] % 12 == a["label"] % 12) & (b["label_raw"] % 12 == a["label_raw"] % 12)
            assert same.mean() > 0.995, same.mean()
            # and a tie-broken layer may start the search from another disc at the same depth, which
            # converges on the same surface within the refinement's stopping tolerance (measured at
            # most 2.3e-5 m on 8 pixels of 6134; 0.1 mm is far below the maps' centimetre texels)
            np.testing.assert_allclose(a["depth"][same], b["depth"][same], rtol=0, atol=1e-4)
            assert (np.abs(a["color"][same].astype(int) - b["color"][same]) <= 1).all()
    finally:
        full.release()
        big.release()
    with pytest.raises(InputError, match="2100 photos: DMT holds every depth map in one texture array"):
        DMTRenderer(many, DMTConfig(progress=False), ctx)


def test_the_maps_a_frame_reads_become_the_most_recently_used(ctx, bundle):
    """The cache evicts the least recently used maps: a map the search or the label check reads
    counts as used even when no final label names it (else a map every frame reads would be
    evicted and loaded again, frame after frame)."""
    full = Renderer(bundle, RenderConfig(**SYNC, photo_choice="labels"), ctx)
    # no full-resolution photo cache: the frame's wanted photos (its final labels) are none, so only
    # the passes' own flags can make a map recently used
    small = Renderer(bundle, RenderConfig(**SYNC, photo_choice="labels", cache_mb=0,
                                          map_cache_mb=_slot_mb(full, 8.5)), ctx)
    try:
        views = [novel_camera(bundle.cameras[0], bundle.cameras[5], t).resized(96, 64) for t in (1.0, 0.0)]
        for view in (*views, views[0]):
            f = small.render(view)
        read = np.unique(f["label_raw"][f["label_raw"] >= 0])  # the maps the search hit
        maps = small.maps
        assert small.images.wanted == () and len(read) >= 2
        np.testing.assert_array_equal(maps._last_used[maps.slot_of[read]], maps._frame)
    finally:
        full.release()
        small.release()


def test_frames_left_on_the_gpu_do_not_wait_for_the_maps_they_miss(ctx, bundle):
    """With async_photos a frame left on the GPU starts the reads of its missing maps and goes on;
    later frames upload them, at most max_map_loads_per_frame each, and the frame is then the one
    rendered with every map resident."""
    full = Renderer(bundle, RenderConfig(**SYNC, photo_choice="labels"), ctx)
    small = Renderer(bundle, RenderConfig(photo_choice="labels", max_uploads_per_frame=0, max_map_loads_per_frame=1,
                                          map_cache_mb=_slot_mb(full, 8.5)), ctx)
    try:
        view = novel_camera(bundle.cameras[0], bundle.cameras[5], 1.0).resized(96, 64)
        a = full.render(view)
        loads, pending = [0], []
        for _ in range(12):
            small.render(view, readback=False)
            loads.append(small.maps.loads)
            pending.append(small.maps.pending)
            small.ctx.finish()
        steps = np.diff(loads)
        assert max(pending) >= 1 and steps.max() == 1 and steps.sum() >= 2  # one upload a frame, several frames
        small.flush_photos()
        b = small.render(view)
        assert "rerendered" not in b and b["maps_missing"] == 0 and small.maps.pending == 0
        for key in ("depth", "label"):
            np.testing.assert_array_equal(a[key], b[key])
    finally:
        full.release()
        small.release()


def test_with_a_partial_cache_the_view_choice_scores_a_short_list(ctx, bundle):
    """With a partial map cache the view choice scores the renderer's short list (the photos
    nearest the camera and those the last frame wanted), not every photo: where the list holds the
    photo the full scoring makes the candidate, the frame is the one rendered with every map
    resident. One candidate: the list (4 nearest, the last frame's first 4 wanted) is at most 8 of
    the 12 photos."""
    cfg = {**SYNC, "photo_choice": "view", "view_candidates": 1}
    full = Renderer(bundle, RenderConfig(**cfg), ctx)
    small = Renderer(bundle, RenderConfig(**cfg, map_cache_mb=_slot_mb(full, 8.5)), ctx)
    try:
        covered = 0
        for t in np.linspace(0.0, 1.0, 6):
            view = novel_camera(bundle.cameras[0], bundle.cameras[5], t).resized(96, 64)
            a, b = full.render(view), small.render(view)
            listed = small.view_choice.listed
            assert full.view_choice.listed is None and 4 <= len(listed) == len(np.unique(listed)) <= 8
            if np.isin(full.view_choice.read_candidates(), listed).all():
                covered += 1
                for key in ("depth", "label", "color"):
                    np.testing.assert_array_equal(a[key], b[key], err_msg=f"{key} at t={t}")
        # measured 5 of 6: at t=0.4 the full scoring's candidate was the last frame's 5th wanted
        assert covered >= 5
    finally:
        full.release()
        small.release()
