"""Image management (paper Section 5.2.2) and the texturing pass (5.2.3), the colours against the
numpy twin :func:`reference.twins.texturing_pass`.
"""

from __future__ import annotations

import numpy as np

from helpers import W
from reference.twins import texturing_pass


def test_image_cache_and_texturing(ctx, bundle):
    """Image management (paper 5.2.2) and texturing (5.2.3).

    * The most frequent labels of the frame (GPU histogram) get the full-resolution slots, and a
      steady view uploads nothing.
    * Streaming decodes on background threads and bounds the uploads per frame.
    * Colours against the numpy texturing of the same frame (:func:`reference.twins.texturing_pass`:
      each pixel's raytraced point projected into the full-resolution photo of its label, bilinear): with every photo cached, 99 % of the
      pixels are within 3 levels (8-bit filtering weights on the GPU); the low-resolution copies
      (half the resolution here) are at least 3 dB worse.
    """
    from dmrt.runtime.renderer import RenderConfig, Renderer
    from dmrt.runtime.texturing import ImageCache
    from reference.metrics import psnr

    cam = bundle.cameras[2].resized(W)
    slot_mb = max(c.width * c.height for c in bundle.cameras) * ImageCache.SLOT_TEXEL_BYTES / 2 ** 20
    sync = {"async_photos": False, "max_uploads_per_frame": 0}
    paper = {"photo_choice": "labels"}  # the cache holds exactly the labels' photos (the histogram's)
    low = Renderer(bundle, RenderConfig(layers=3, cache_mb=0, **paper), ctx)
    two = Renderer(bundle, RenderConfig(layers=3, cache_mb=2.5 * slot_mb, **sync, **paper), ctx)
    full = Renderer(bundle, RenderConfig(layers=3, **sync, **paper), ctx)
    streamed = Renderer(bundle, RenderConfig(layers=3, max_uploads_per_frame=1, **paper), ctx)  # asynchronous
    try:
        assert low.images.n_slots == 0 and two.images.n_slots == 2
        assert full.images.n_slots == len(bundle.cameras)  # the default 1 GB holds them all
        f_two = two.render(cam)
        counts = two.shading.read_label_counts().astype(np.int64)
        labelled = f_two["label"][f_two["label"] >= 0]
        np.testing.assert_array_equal(counts, np.bincount(labelled, minlength=len(bundle.cameras)))
        # a frame whose sides are no multiple of the histogram's 64 x 64 blocks: every pixel once
        odd = two.render(cam, 101, 70)["label"]
        np.testing.assert_array_equal(two.shading.read_label_counts(), np.bincount(odd[odd >= 0], minlength=len(bundle.cameras)))
        two.render(cam)
        assert set(np.flatnonzero(two.images.slot_of >= 0)) == set(np.argsort(-counts, kind="stable")[:2])
        uploads = two.images.uploads
        two.render(cam)
        assert two.images.uploads == uploads

        f_low, f_full = low.render(cam), full.render(cam)
        for key in ("depth", "label"):
            np.testing.assert_array_equal(f_low[key], f_full[key])
        expected = texturing_pass(cam, f_full["depth"], f_full["label"], bundle.cameras, bundle.image)
        hit = f_full["depth"] > 0
        err = np.abs(f_full["color"].astype(int) - expected.astype(int)).max(-1)[hit]
        p_low, p_full = psnr(f_low["color"], expected, hit), psnr(f_full["color"], expected, hit)
        print(f"texturing vs numpy: full-res {p_full:.2f} dB (99th pct error {np.percentile(err, 99):.0f}), "
              f"low-res {p_low:.2f} dB")
        assert np.percentile(err, 99) <= 3
        assert p_full > p_low + 3.0

        # streaming: the first frame waits for nothing (decodes run in the background), at most
        # one upload per frame, and once flushed the frame equals the synchronous one
        f0 = streamed.render(cam)
        assert streamed.images.uploads <= 1
        streamed.render(cam)
        assert streamed.images.uploads <= 2
        streamed.flush_photos()
        np.testing.assert_array_equal(streamed.render(cam)["color"], f_full["color"])
        assert (f0["depth"] == f_full["depth"]).all()
    finally:
        for r in (low, two, full, streamed):
            r.release()


def test_image_cache_replaces_the_least_recently_wanted(ctx, bundle):
    """A full cache puts a newly wanted photo into the slot of the photo wanted longest ago that
    the frame does not want (equal frames: the smaller slot), never into a wanted photo's slot."""
    from dmrt.runtime.texturing import ImageCache

    slot_mb = max(c.width * c.height for c in bundle.cameras) * ImageCache.SLOT_TEXEL_BYTES / 2 ** 20
    cache = ImageCache(ctx, bundle, cache_mb=3.5 * slot_mb)
    try:
        assert cache.n_slots == 3 and len(bundle.cameras) >= 5
        assert cache.update([0, 1, 2]) == 3
        assert list(cache.slot_of[:3]) == [0, 1, 2]  # empty slots in order
        assert cache.update([0, 3]) == 1  # photos 1 and 2 were last wanted together: the smaller slot
        assert cache.slot_of[3] == 1 and cache.slot_of[1] == -1
        assert cache.update([4, 0]) == 1  # photo 2 (frame 1) is older than photo 3 (frame 2)
        assert cache.slot_of[4] == 2 and cache.slot_of[2] == -1 and cache.slot_of[0] == 0
        assert cache.update([4, 0]) == 0  # nothing missing: nothing uploaded
        assert cache.uploads == 5
    finally:
        cache.release()


def test_photo_cache_budget_follows_the_free_gpu_memory(ctx, bundle):
    """cache_mb=None sizes the cache from the GPU memory free (a quarter, within [1 GiB, half]);
    where the driver does not say (Mesa's llvmpipe here), the paper's 1 GiB."""
    from dmrt.gl.context import free_memory_mb
    from dmrt.runtime.texturing import ImageCache, auto_cache_mb

    assert auto_cache_mb(None) == 1024.0
    assert auto_cache_mb(140_000.0) == 35_000.0  # an idle H200: a quarter
    assert auto_cache_mb(3_000.0) == 1024.0  # a quarter would be less than the paper's 1 GiB
    assert auto_cache_mb(1_000.0) == 500.0  # a small GPU: never more than half of what is free
    free = free_memory_mb(ctx)
    cache = ImageCache(ctx, bundle, cache_mb=None)
    try:
        assert cache.budget_mb == auto_cache_mb(free)
        slot_mb = max(c.width * c.height for c in bundle.cameras) * ImageCache.SLOT_TEXEL_BYTES / 2 ** 20
        assert cache.n_slots == min(len(bundle.cameras), int(cache.budget_mb // slot_mb))
    finally:
        cache.release()


def test_image_cache_preload(ctx, bundle):
    """preload makes the first n_slots of its photos resident at once (decoded in parallel, even in
    a streaming cache that uploads one photo a frame), the same bytes as an upload by update; a
    frame wanting them then uploads nothing."""
    from dmrt.runtime.texturing import ImageCache

    slot_mb = max(c.width * c.height for c in bundle.cameras) * ImageCache.SLOT_TEXEL_BYTES / 2 ** 20
    streamed = ImageCache(ctx, bundle, cache_mb=3.5 * slot_mb, max_uploads=1, asynchronous=True)
    synced = ImageCache(ctx, bundle, cache_mb=3.5 * slot_mb)
    try:
        assert streamed.preload([4, 2, 4, 0, 1]) == 3  # duplicates once; the slots hold three
        assert streamed.wanted == (4, 2, 0) and list(np.flatnonzero(streamed.slot_of >= 0)) == [0, 2, 4]
        assert streamed.pending == 0 and streamed.update([0, 2, 4]) == 0 and streamed.uploads == 3
        assert synced.update([4, 2, 0]) == 3
        a, b = streamed.high.read(), synced.high.read()  # every slot
        n = len(a) // streamed.n_slots
        for j in (4, 2, 0):
            sa, sb = streamed.slot_of[j], synced.slot_of[j]
            assert a[sa * n:(sa + 1) * n] == b[sb * n:(sb + 1) * n], j
        assert streamed.preload([3]) == 1 and streamed.slot_of[3] >= 0  # the least recently wanted slot
    finally:
        streamed.release()
        synced.release()


def test_streamed_decodes_no_frame_wants_any_more_end(ctx, bundle):
    """A streaming cache's background decodes of photos that a frame wanted and the next ones do
    not: once finished they join the decoded photos (CPU cache), so nothing stays pending, and a
    later frame wanting them uploads them without decoding again; and those of wanted photos are
    not dropped for them."""
    import time

    from dmrt.runtime.texturing import ImageCache

    slot_mb = max(c.width * c.height for c in bundle.cameras) * ImageCache.SLOT_TEXEL_BYTES / 2 ** 20
    cache = ImageCache(ctx, bundle, cache_mb=2.5 * slot_mb, max_uploads=1, asynchronous=True)
    try:
        cache.update([0, 1])  # decodes start for both (at most one uploaded, if ready at once)
        end = time.monotonic() + 30.0  # two small decodes on a loaded 2-core CI machine
        while time.monotonic() < end:
            cache.update([2])  # frames that want only photo 2
            if cache.pending == 0 and cache.slot_of[2] >= 0:
                break
            time.sleep(0.01)
        assert cache.pending == 0 and cache.slot_of[2] >= 0 and (cache.slot_of[[0, 1]] < 0).all()
        # decoded already: uploaded by this frame, not decoding (pending) for a later one
        assert cache.update([2, 1]) == 1 and cache.slot_of[1] >= 0 and cache.pending == 0
    finally:
        cache.release()
    # a CPU cache of one photo and a half: flush's decodes of wanted photos are uploaded, not
    # dropped from the CPU cache by each other and decoded again (the decodes counted)
    photo_mb = max(c.width * c.height for c in bundle.cameras) * 4 / 2 ** 20
    cache = ImageCache(ctx, bundle, cache_mb=4.5 * slot_mb, max_uploads=1, asynchronous=True,
                       cpu_cache_mb=1.5 * photo_mb)
    decoded, decode = [], cache._decode
    cache._decode = lambda j: decoded.append(j) or decode(j)  # the real decode, counted
    try:
        cache.update([0, 1, 2, 3])
        assert cache.flush() == 4 and sorted(decoded) == [0, 1, 2, 3]
    finally:
        cache.release()


def test_label_histogram_counts_labels_of_any_number_of_photos(ctx):
    """The histogram pass's per-workgroup hash table against np.bincount: long runs of one label,
    and blocks of more distinct labels (of 5,000 photos) than the table holds, which count globally."""
    from dmrt.gl import abi
    from dmrt.gl.kernels import groups
    from dmrt.gl.shaders import load_program, set_uniforms
    from dmrt.runtime.shading import HISTOGRAM_RUN

    w, h, n = 200, 70, 5000
    labels = np.random.default_rng(1).integers(-1, n, (h, w))
    labels[:, :90] = 7
    hits = np.zeros(h * w, abi.HIT_DTYPE)
    hits["depth"], hits["final_label"] = 1.0, labels.ravel()
    hits_buffer, counts = ctx.buffer(hits.tobytes()), ctx.buffer(np.zeros(n, np.uint32).tobytes())
    try:
        program = load_program(ctx, "dmrt_label_histogram", {"PIXELS_PER_THREAD": HISTOGRAM_RUN})
        hits_buffer.bind_to_storage_buffer(abi.B_HITS)
        counts.bind_to_storage_buffer(abi.B_COUNTS)
        set_uniforms(program, u_size=(w, h))
        program.run(groups(w, 64), groups(h, HISTOGRAM_RUN))
        np.testing.assert_array_equal(np.frombuffer(counts.read(), np.uint32),
                                      np.bincount(labels[labels >= 0], minlength=n))
    finally:
        hits_buffer.release()
        counts.release()
