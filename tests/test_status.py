"""The frame's one status read-back (:mod:`dmrt.runtime.status`): the photo choice on the GPU
against its numpy twin, and how many records a frame reads on each visibility path.
"""

from __future__ import annotations

import numpy as np
import pytest

from dmrt.gl import abi
from dmrt.runtime.texturing import ImageCache, choose_photos

from helpers import W


def _choice_cases(n_photos: int, rng) -> list:
    """Counts the choice must rank: a frame's few hundred photos among the scene's (labels come in
    few sizes: many ties), none at all, and, where the photos are few, most or all of them counted
    (many ties and zeros; all distinct)."""
    seen = rng.choice(n_photos, min(n_photos, 300), replace=False)
    sparse = np.zeros(n_photos, np.int64)
    sparse[seen] = rng.integers(1, 6, seen.size) * rng.integers(1, 3, seen.size)
    cases = [sparse, np.zeros(n_photos, np.int64)]
    if n_photos <= 1000:  # all photos counted: m^2 comparisons, slow on llvmpipe at 10,240
        cases += [rng.integers(0, 4, n_photos) * rng.integers(0, 3, n_photos), rng.permutation(n_photos) + 1]
    return cases


# 10,240 photos (the `many` scene) with ~300 counted: slots fewer and more than the counted photos
@pytest.mark.parametrize("n_photos, n_slots", [(1, 1), (7, 3), (192, 480), (1000, 64), (10_240, 64),
                                               (10_240, 480)])
def test_photo_choice_matches_numpy(ctx, n_photos, n_slots):
    """The photo choice on the GPU (:class:`dmrt.runtime.ranking.PhotoRanking`, as the renderer runs
    it) writes exactly :func:`choose_photos`'s list (same photos, same order, ties to the smaller
    index) into the record, whatever it held before, and leaves the record's tile total alone. One
    ranking serves every case in turn: its list must start empty each time."""
    from dmrt.runtime.ranking import PhotoRanking
    from dmrt.runtime.status import FrameStatus

    rng = np.random.default_rng(n_photos)
    ranking = PhotoRanking(ctx, n_photos)
    status = FrameStatus(ctx, n_slots)
    counts_buf = ctx.buffer(reserve=4 * n_photos)
    try:
        for counts in _choice_cases(n_photos, rng):
            status.begin()
            record = status.record(-1)
            stale = np.full(abi.STATUS_HEADER_WORDS + n_slots, 7, np.uint32)  # what a reused record holds
            stale[0] = 12345
            record.write(stale.tobytes())
            counts_buf.write(counts.astype(np.uint32).tobytes())
            ranking.run(counts_buf, record, n_slots)
            ctx.finish()
            total, wanted = status.read(-1)
            np.testing.assert_array_equal(wanted, choose_photos(counts, n_slots))
            assert total == 12345
    finally:
        for obj in (counts_buf, status, ranking):
            obj.release()


def test_choose_photos():
    """The twin itself, on a case worked by hand."""
    np.testing.assert_array_equal(choose_photos([0, 5, 2, 5, 0, 1], 3), [1, 3, 2])
    np.testing.assert_array_equal(choose_photos([0, 0, 1], 5), [2])
    assert choose_photos([3, 1], 0).size == 0


# Records read in each of five frames of one view, with streamed photos and with synchronous ones:
# the tiles path reads its list length right after its raster on a size's first frame, and that of
# two frames back when lagged (from the third frame); the photo cache takes its choice from the
# frame's read, or reads this frame's record (which also gives the frame check its length), or with
# synchronous photos reads its own choice (and the frame check then reads this frame's record).
@pytest.mark.parametrize("method, check, streamed, synchronous", [
    ("tiles", "frame", [1, 1, 1, 1, 1], [2, 2, 2, 2, 2]),
    ("tiles", "lagged", [1, 1, 1, 1, 1], [2, 1, 2, 2, 2]),
    ("compute", "frame", [1, 1, 1, 1, 1], [1, 1, 1, 1, 1])])
def test_one_read_back_a_frame(ctx, bundle, method, check, streamed, synchronous):
    """With streamed photos (the default) a frame reads one status record on every path, and the cache follows the GPU's choice: after a flush
    it holds exactly the photos :func:`choose_photos` picks from the last frame's histogram."""
    from dmrt.runtime.renderer import RenderConfig, Renderer

    cam = bundle.cameras[1].resized(W)
    slot_mb = max(c.width * c.height for c in bundle.cameras) * ImageCache.SLOT_TEXEL_BYTES / 2 ** 20
    for sync, expected in ((False, streamed), (True, synchronous)):
        r = Renderer(bundle, RenderConfig(layers=2, method=method, tile_check=check, cache_mb=2.5 * slot_mb,
                                          async_photos=not sync), ctx)
        try:
            reads = []
            for _ in range(5):
                before = r.shading.status.reads
                r.render(cam, readback=False)
                reads.append(r.shading.status.reads - before)
            assert reads == expected, (sync, reads)
            counts = r.shading.read_label_counts()
            r.flush_photos()
            resident = set(np.flatnonzero(r.images.slot_of >= 0))
            assert resident == set(choose_photos(counts, r.images.n_slots)) and len(resident) == 2
        finally:
            r.release()


def test_a_frame_that_outgrows_its_tile_list_is_rendered_again(ctx, bundle):
    """``tile_check="frame"`` in a renderer checks the list length late in the frame (from the
    record read for the photo cache): a frame whose list outgrew the buffer is rendered again with a
    larger one, and equals the frame of a renderer whose list was large enough."""
    from dmrt.runtime.renderer import RenderConfig, Renderer

    cam = bundle.cameras[2].resized(W)
    cfg = RenderConfig(layers=3, async_photos=False, max_uploads_per_frame=0)
    small, ok = Renderer(bundle, cfg, ctx), Renderer(bundle, cfg, ctx)
    try:
        tiles = small.visibility.tiles
        small.render(cam)  # the size's first frame, which the stage checks itself
        tiles.entries.release()  # a list buffer of 16 entries: the frame loses its discs past them
        tiles.capacity, tiles.entries, tiles._grow_to = 16, ctx.buffer(reserve=64), 0
        got, want = small.render(cam), ok.render(cam)
        assert got.get("rerendered") and "rerendered" not in want
        assert tiles.dropped_frames == 1 and tiles.capacity >= tiles.stats()["entries"] > 16
        for key in ("depth", "label", "color"):
            np.testing.assert_array_equal(got[key], want[key])
    finally:
        small.release()
        ok.release()
