"""The tile-binned visibility path (``method="tiles"``, :mod:`dmrt.runtime.tiles`) against depth
peeling by compute passes (``method="compute"``), on Mesa llvmpipe.

Both evaluate the same ray-disc test (``splat_depth_at``) on the same discs in float32 and take
each layer as the same minimum (the smallest (depth bits, label) behind the layer before with
another label), so the layers must be equal bit for bit, whatever the tile's list holds.
"""

from __future__ import annotations

import numpy as np
import pytest

from dmrt.camera import Camera
from dmrt.gl.abi import EMPTY_BITS, EMPTY_LABEL

W = 192  # frame width (llvmpipe time); heights follow the photos' aspect
AGREE = 0.995  # whole frames (test_renderer_frames_match_compute): see there


def _novel(a: Camera, b: Camera, t: float = 0.5) -> Camera:
    """A camera between ``a`` and ``b``: centre interpolated linearly, rotation by slerp."""
    from scipy.spatial.transform import Rotation, Slerp

    R = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([a.R, b.R])))(t).as_matrix()
    c = (1 - t) * a.center + t * b.center
    return Camera(f"between_{a.name}_{b.name}", a.width, a.height, a.fx, a.fy, a.cx, a.cy, R, -R @ c)


def _uniforms(cam: Camera) -> dict:
    """Camera uniforms of the splat passes; ``cam`` in the proxies' (scene-origin-relative) frame."""
    return {"u_R": cam.R.T.ravel(), "u_t": cam.t, "u_K": (cam.fx, cam.fy, cam.cx, cam.cy),
            "u_size": (cam.width, cam.height)}


def _layers(ctx, stage, cam: Camera, k: int):
    """Run ``stage`` (VisibilityStage or TileVisibility) for ``cam``: (k, h, w) uint32 depth bits,
    (k, h, w) int32 labels."""
    w, h = cam.width, cam.height
    depth, label = ctx.buffer(reserve=4 * k * w * h), ctx.buffer(reserve=4 * k * w * h)
    try:
        stage.run(_uniforms(cam), (w, h), k, depth, label)
        return (np.frombuffer(depth.read(), np.uint32).reshape(k, h, w).copy(),
                np.frombuffer(label.read(), np.int32).reshape(k, h, w).copy())
    finally:
        depth.release()
        label.release()


def _assert_equal(peel, tiles, k: int, what: str) -> None:
    """The first k layers of both, depth bits and labels, equal."""
    (pd, pl), (td, tl) = peel, tiles
    for i in range(k):
        assert np.array_equal(pl[i], tl[i]), f"{what}, layer {i}: labels differ on {(pl[i] != tl[i]).sum()} pixels"
        assert np.array_equal(pd[i], td[i]), f"{what}, layer {i}: depths differ on {(pd[i] != td[i]).sum()} pixels"


@pytest.fixture(scope="module")
def bundle(tiny_bundle):
    """The preprocessed tiny scene (proxies labelled by the pipeline's graph cut)."""
    from dmrt.io.bundle import read_bundle

    return read_bundle(tiny_bundle)


@pytest.fixture(scope="module")
def splats(ctx, bundle):
    from dmrt.runtime.visibility import ProxySplats

    s = ProxySplats(ctx, bundle.proxy)
    yield s
    s.release()


def _views(bundle) -> list[Camera]:
    """Two photo cameras of different rooms and one novel view between two photos, in the proxies' frame."""
    cams = bundle.cameras
    views = [cams[0], cams[len(cams) // 2 + 1], _novel(cams[1], cams[2])]
    return [c.resized(W).relative_to(bundle.origin) for c in views]


def test_tiles_match_peeling(ctx, bundle, splats):
    """1, 3 and 5 layers at photo cameras and a novel one. Peeling's first k layers do not depend
    on how many follow, so one 5-layer peel is the reference of all three."""
    from dmrt.runtime.visibility import VisibilityStage

    peel = VisibilityStage(ctx, splats, "compute")
    tiles = VisibilityStage(ctx, splats, "tiles")
    try:
        for cam in _views(bundle):
            splats.begin_frame()
            ref = _layers(ctx, peel, cam, 5)
            assert (ref[1][0] != EMPTY_LABEL).mean() > 0.5 and (ref[1][2] != EMPTY_LABEL).mean() > 0.05
            for k in (1, 3, 5):
                got = _layers(ctx, tiles, cam, k)
                _assert_equal(ref, got, k, f"{cam.name}, {k} layers")
                stats = tiles.tiles.stats()
                assert not stats["dropped"] and stats["entries"] > 0 and tiles.read_overflow() == 0
        assert tiles.nbytes >= 4 * tiles.tiles.capacity
    finally:
        peel.release()
        tiles.release()


@pytest.mark.parametrize("tile, batch, top, blocks, walk", [
    (8, 256, 16, False, "linear"), (16, 512, 4, False, "linear"), (16, 64, 8, False, "linear"),
    (16, 512, 16, False, "linear"), (8, 256, 8, True, "linear"), (16, 288, 12, True, "sparse"),
    (8, 256, 4, False, "sparse"), (16, 64, 8, True, "sparse")])
def test_other_tile_settings_match_peeling(ctx, bundle, splats, tile, batch, top, blocks, walk):
    """8 x 8 tiles (64 invocations a workgroup, no hit masks: they need 256 pixels a tile), fewer
    nearest hits kept (more pixels walk again), short batches, warps of two pixel rows instead of
    8 x 4 blocks, and either walk (every disc in turn, or only those whose box holds the pixel): 5
    layers equal peeling's at the photo and novel cameras (the settings bench_visibility
    --tile-sweep times)."""
    from dmrt.runtime.tiles import TileVisibility
    from dmrt.runtime.visibility import VisibilityStage

    peel = VisibilityStage(ctx, splats, "compute")
    tiles = TileVisibility(ctx, splats, tile=tile, batch=batch, top=top, warp_blocks=blocks, walk=walk)
    try:
        assert tiles.hit_masks == (tile == 16)
        for cam in _views(bundle):
            splats.begin_frame()
            _assert_equal(_layers(ctx, peel, cam, 5), _layers(ctx, tiles, cam, 5), 5,
                          f"{cam.name}, tile {tile}, batch {batch}, top {top}, blocks {blocks}")
    finally:
        peel.release()
        tiles.release()


def _crowded_tile(n: int, seed: int = 1):
    """``n`` small discs (1-2 px) at depths 2-10 m, all inside pixel tile (1, 1) of a 64 x 48 frame
    (pixels 16-31), tilted up to ~30 degrees from facing the camera, 4 labels: one tile's list
    longer than the raster pass remembers per pixel (64) and, for n = 4000, ~100 hits per pixel."""
    rng = np.random.default_rng(seed)
    cam = Camera("crowd", 64, 48, 64.0, 64.0, 32.0, 24.0, np.eye(3), np.zeros(3))
    z = rng.uniform(2.0, 10.0, n)
    u, v = rng.uniform(18.0, 30.0, n), rng.uniform(18.0, 30.0, n)
    pos = np.stack([(u - cam.cx) / cam.fx * z, (v - cam.cy) / cam.fy * z, z], 1)
    normals = np.array([0.0, 0.0, -1.0]) + rng.uniform(-0.3, 0.3, (n, 3))
    proxy = {"positions": pos.astype(np.float32), "normals": normals.astype(np.float32),
             "radii": (z * rng.uniform(1.0, 2.0, n) / cam.fx).astype(np.float32),
             "labels": rng.integers(0, 4, n).astype(np.int32)}
    return cam, proxy


@pytest.mark.parametrize("discs, batch", [(300, 512), (4000, 512), (300, 64)])
def test_long_tile_lists(ctx, discs, batch):
    """One tile with 300 or 4000 discs: held in shared memory with the first 64 remembered per
    pixel (300, 512), or walked in batches loaded again for each layer (4000 or batch 64); the
    layers equal peeling's. (Mesa llvmpipe ends any shader loop nest after 65535 iterations: 4000
    discs x 5 layers stay below.)"""
    from dmrt.runtime.tiles import TileVisibility
    from dmrt.runtime.visibility import ProxySplats, VisibilityStage

    cam, proxy = _crowded_tile(discs)
    splats = ProxySplats(ctx, proxy)
    peel = VisibilityStage(ctx, splats, "compute")
    tiles = TileVisibility(ctx, splats, batch=batch)
    try:
        splats.begin_frame()
        ref = _layers(ctx, peel, cam, 5)
        assert (ref[1][2][16:32, 16:32] != EMPTY_LABEL).mean() > 0.5  # most of the tile has 3+ layers
        _assert_equal(ref, _layers(ctx, tiles, cam, 5), 5, f"{discs} discs, batch {batch}")
        stats = tiles.stats()
        assert stats["entries"] == discs and stats["longest"] == discs  # every disc in the one tile
        # the labeling pass on the same lists (with 300 discs and batch 512 the first 256 through
        # the raster's hit masks, the rest tested) against the splatted one, at the first layer
        first = ref[0][0].view(np.float32) * (ref[0][0] != EMPTY_BITS)
        np.testing.assert_array_equal(_tile_labels(ctx, tiles, splats, cam, first),
                                      _tile_labels(ctx, None, splats, cam, first))
        if discs == 300 and batch == 512:
            # the crowd moved 11 px left: tile (1, 1) keeps 1-128 discs, a list whose masks' second
            # half the raster does not write (its pixels' still hold the last frame's bits): layers
            # and labels as before. (That the labeling pass leaves those bits alone holds by
            # construction, masks_second_half; a read of them would visit shared-memory slots past
            # the list, which llvmpipe leaves empty: no label would show it here.)
            moved = Camera("moved", 64, 48, 64.0, 64.0, 21.0, 24.0, np.eye(3), np.zeros(3))
            splats.begin_frame()
            ref = _layers(ctx, peel, moved, 5)
            _assert_equal(ref, _layers(ctx, tiles, moved, 5), 5, "the crowd moved")
            offsets = np.frombuffer(tiles.offsets.read(), np.uint32)
            assert 0 < offsets[6] - offsets[5] <= 128  # tile (1, 1) of the 4 x 3 tiles
            first = ref[0][0].view(np.float32) * (ref[0][0] != EMPTY_BITS)
            np.testing.assert_array_equal(_tile_labels(ctx, tiles, splats, moved, first),
                                          _tile_labels(ctx, None, splats, moved, first))
    finally:
        for obj in (tiles, peel, splats):
            obj.release()


@pytest.mark.parametrize("discs, batch, split_min", [(4000, 288, 1152), (300, 64, 100)])
def test_long_lists_split_over_workgroups(ctx, discs, batch, split_min):
    """A tile whose list is longer than split_min is walked by a workgroup per batch of discs
    (dmrt_tiles_split.glsl: a pass per slice, then one merging each tile's slices): the layers
    equal peeling's, bit for bit, and so do the labeling pass's labels (its SPLIT_PASS 1 and 2),
    twice over (the split buffer reused). 4000 discs in 14 slices of 288; 300 in 5 of 64 (the
    last one short)."""
    from dmrt.runtime.tiles import TileVisibility
    from dmrt.runtime.visibility import ProxySplats, VisibilityStage

    cam, proxy = _crowded_tile(discs)
    splats = ProxySplats(ctx, proxy)
    peel = VisibilityStage(ctx, splats, "compute")
    tiles = TileVisibility(ctx, splats, batch=batch, split_min=split_min)
    try:
        splats.begin_frame()
        ref = _layers(ctx, peel, cam, 5)
        first = ref[0][0].view(np.float32) * (ref[0][0] != EMPTY_BITS)
        want = _tile_labels(ctx, None, splats, cam, first)
        for frame in range(2):
            _assert_equal(ref, _layers(ctx, tiles, cam, 5), 5, f"{discs} discs, batch {batch}, frame {frame}")
            np.testing.assert_array_equal(_tile_labels(ctx, tiles, splats, cam, first), want)
            stats = tiles.stats()  # the one tile out of the lists, in slices
            assert (stats["entries"], stats["longest"]) == (0, 0)
            assert (stats["split_tiles"], stats["split_slices"], stats["split_discs"]) == (1, -(-discs // batch), discs)
    finally:
        for obj in (tiles, peel, splats):
            obj.release()


def test_split_only_while_frames_have_long_lists(ctx):
    """The scan counts the long lists into the frame's status record, and a frame splits only while
    one of the last split_hold frames read back had one: looking away from the crowded tile, the
    split stops after split_hold frames; the first frame back walks the long list with the raster
    alone (and counts it), the next splits again. Every frame's layers and labels equal peeling's,
    bit for bit, split or not."""
    from dmrt.runtime.tiles import TileVisibility
    from dmrt.runtime.visibility import ProxySplats, VisibilityStage

    discs = 300
    cam, proxy = _crowded_tile(discs)
    turned = np.diag([-1.0, 1.0, -1.0])  # half a turn about y: the discs (z > 0) behind the camera
    away = Camera("away", cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy, turned, np.zeros(3))
    splats = ProxySplats(ctx, proxy)
    peel = VisibilityStage(ctx, splats, "compute")
    tiles = TileVisibility(ctx, splats, batch=64, split_min=100, split_hold=2)
    try:
        splats.begin_frame()
        ref = {c.name: _layers(ctx, peel, c, 5) for c in (cam, away)}
        first = ref[cam.name][0][0].view(np.float32) * (ref[cam.name][0][0] != EMPTY_BITS)
        want = _tile_labels(ctx, None, splats, cam, first)
        # frames 0-3 split their long list (each record counts the tile the plan took out), 4 and
        # 5 still split (hold 2), 6 not; 7 looks back unsplit, and its record makes 8 split
        views = [cam] * 4 + [away] * 3 + [cam] * 2
        splits = [True] * 6 + [False, False, True]
        for frame, (c, split) in enumerate(zip(views, splits)):
            _assert_equal(ref[c.name], _layers(ctx, tiles, c, 5), 5, f"frame {frame} ({c.name})")
            stats = tiles.stats()
            assert (stats["split_tiles"] > 0) == (split and c is cam), f"frame {frame}: {stats}"
            assert tiles.split_frames == sum(splits[:frame + 1]), f"frame {frame}"
            if c is cam:
                np.testing.assert_array_equal(_tile_labels(ctx, tiles, splats, cam, first), want)
                assert stats["longest"] == (0 if split else discs), f"frame {frame}: {stats}"
    finally:
        for obj in (tiles, peel, splats):
            obj.release()


def test_list_passes_timed_apart(ctx, bundle, splats):
    """GpuTimer.passes: each dispatch of the tile lists timed as a part of its own, in place of the
    one ``visibility:tile_lists`` section; the layers are the same either way."""
    from dmrt.gl.timer import GpuTimer
    from dmrt.runtime.tiles import TileVisibility

    cam, k = _views(bundle)[0], 5
    w, h = cam.width, cam.height
    tiles = TileVisibility(ctx, splats)
    depth, label = ctx.buffer(reserve=4 * k * w * h), ctx.buffer(reserve=4 * k * w * h)
    try:
        layers, names = [], []
        for passes in (False, True):
            timer = GpuTimer(ctx)
            timer.passes = passes
            splats.begin_frame()
            tiles.run(_uniforms(cam), (w, h), k, depth, label, timer=timer)
            layers.append((depth.read(), label.read()))
            names.append(set(timer.part_ms))
        assert layers[0] == layers[1]
        lists = {f"visibility:lists_{p}" for p in ("clear", "count", "count_large", "scan", "scatter", "scatter_large")}
        assert names[0] == {"visibility:tile_lists", "visibility:tile_raster"}
        assert names[1] == lists | {"visibility:tile_raster"}
    finally:
        for obj in (depth, label, tiles):
            obj.release()


def test_scan_against_numpy(ctx):
    """The tile counts' exclusive prefix sum (dmrt_tiles_scan.glsl, one workgroup reading and writing
    four words at a time, 4096 tiles a round, 1 or 8 rounds a sweep) against numpy's: counts that are
    not a multiple of four, one sweep exactly, and several sweeps; the total in the status word and
    after the last offset, and the lists longer than u_split_min in the status record's third word.
    Buffers as TileVisibility allocates them (padded to four words)."""
    from dmrt.gl import abi
    from dmrt.gl.shaders import load_program, set_uniforms
    from dmrt.runtime.tiles import _padded

    rng = np.random.default_rng(7)
    for rounds, tiles in [(r, n) for r in (1, 8) for n in (1, 3, 4, 5, 3600, 32400, 32768, 32771, 70001)]:
        program = load_program(ctx, "dmrt_tiles_scan", {"ROUNDS": rounds})
        counts = rng.integers(0, 300, tiles).astype(np.uint32)
        padded = np.zeros(_padded(tiles), np.uint32)
        padded[:tiles] = counts
        bufs = {abi.B_TILE_COUNTS: ctx.buffer(padded.tobytes()),
                abi.B_TILE_OFFSETS: ctx.buffer(reserve=4 * (_padded(tiles) + 4)),
                abi.B_FRAME_STATUS: ctx.buffer(reserve=16)}
        try:
            for point, buf in bufs.items():
                buf.bind_to_storage_buffer(point)
            set_uniforms(program, u_tile_count=tiles, u_split_min=250, u_planned=0)
            program.run(1)
            offsets = np.frombuffer(bufs[abi.B_TILE_OFFSETS].read(), np.uint32)[:tiles + 1]
            want = np.concatenate([[0], np.cumsum(counts, dtype=np.uint64)]).astype(np.uint32)
            np.testing.assert_array_equal(offsets, want, err_msg=f"{tiles} tiles, {rounds} rounds")
            total, _, long_tiles = np.frombuffer(bufs[abi.B_FRAME_STATUS].read(12), np.uint32)
            assert (total, long_tiles) == (want[-1], (counts > 250).sum()), f"{tiles} tiles, {rounds} rounds"
        finally:
            for buf in bufs.values():
                buf.release()


@pytest.mark.parametrize("max_thread_tiles", [1, 2])
def test_large_discs_share_tiles_with_small_ones(ctx, bundle, splats, max_thread_tiles):
    """Discs over more than max_thread_tiles tiles are binned by a workgroup each (the large list,
    dispatch-indirect), the others by a thread each: with 1 or 2 tiles a thread, many tiles hold
    both kinds, and their slices must still get every disc once (the layers equal peeling's)."""
    from dmrt.runtime.tiles import TileVisibility
    from dmrt.runtime.visibility import VisibilityStage

    peel = VisibilityStage(ctx, splats, "compute")
    tiles = TileVisibility(ctx, splats, max_thread_tiles=max_thread_tiles)
    try:
        for cam in _views(bundle):
            splats.begin_frame()
            ref = _layers(ctx, peel, cam, 5)
            got = _layers(ctx, tiles, cam, 5)
            n_large = tiles.stats()["large"]
            assert 0 < n_large < splats.n // 2, cam.name  # both kinds, in numbers
            _assert_equal(ref, got, 5, f"{cam.name}, {max_thread_tiles} tiles a thread")
    finally:
        peel.release()
        tiles.release()


def test_walk_per_frame_bench(bundle):
    """bench_visibility --walk-frames: per frame both walks' raster times, the list's discs a tile
    (its length over the tiles) and the share of a tile a disc's box covers (a box of the 16 x 16
    tile's pixels: between one pixel and the whole tile)."""
    from bench.bench_visibility import walk_per_frame

    cams = [c.resized(W) for c in bundle.cameras[:2]]  # world frame, as a walkthrough's
    rows = walk_per_frame(bundle, cams, 3)
    assert [r["frame"] for r in rows] == [0, 1]
    for r in rows:
        # a time, or NaN where none was measured (a software rasterizer: dmrt.gl.timer)
        assert not (r["linear_ms"] < 0.0 or r["sparse_ms"] < 0.0) and r["N"] > 1.0
        assert 1 / 256 <= r["cover"] <= 1.0


def test_auto_walk_turns_sparse_on_long_lists(ctx):
    """walk="auto": the first frame walks every disc in turn (no list length known yet), the next
    one, after a list of 1300 discs over 12 tiles (108 a tile, above SPARSE_MIN), only the discs
    whose box holds the pixel; a view with no disc in front turns it back. Every frame's layers
    equal peeling's, with batches of 768 and 288 discs."""
    from dmrt.runtime.tiles import SPARSE_MIN, TileVisibility
    from dmrt.runtime.visibility import ProxySplats, VisibilityStage

    cam, proxy = _crowded_tile(1300)
    assert 1300 > SPARSE_MIN * 12
    splats = ProxySplats(ctx, proxy)
    peel = VisibilityStage(ctx, splats, "compute")
    stages = [TileVisibility(ctx, splats, batch=batch) for batch in (768, 288)]
    away = Camera("away", 64, 48, 64.0, 64.0, 32.0, 24.0, np.diag([-1.0, 1.0, -1.0]), np.zeros(3))
    try:
        for stage in stages:
            for frame, (view, sparse) in enumerate([(cam, False), (cam, True), (away, True), (cam, False)]):
                splats.begin_frame()
                assert stage._sparse() == sparse, f"batch {stage.batch}, frame {frame}"
                _assert_equal(_layers(ctx, peel, view, 5), _layers(ctx, stage, view, 5), 5,
                              f"batch {stage.batch}, frame {frame}, sparse {sparse}")
    finally:
        for obj in (*stages, peel, splats):
            obj.release()


def test_equal_depths_take_the_smaller_label(ctx):
    """Every disc twice, the copy with another label: each hit has a twin of bit-equal depth, and
    peeling takes the smaller label (the order of (depth bits, label)); the tiles path the same,
    both with lists held in shared memory and walked in batches."""
    from dmrt.runtime.tiles import TileVisibility
    from dmrt.runtime.visibility import ProxySplats, VisibilityStage

    cam, proxy = _crowded_tile(200)
    twin = {k: np.concatenate([v, v]) for k, v in proxy.items()}
    twin["labels"][200:] = (twin["labels"][200:] + 1 + np.arange(200) % 3) % 4  # another label
    splats = ProxySplats(ctx, twin)
    peel = VisibilityStage(ctx, splats, "compute")
    stages = [TileVisibility(ctx, splats, batch=batch) for batch in (512, 64)]
    try:
        splats.begin_frame()
        ref = _layers(ctx, peel, cam, 5)
        assert (ref[1][2][16:32, 16:32] != EMPTY_LABEL).mean() > 0.5  # most of the tile has 3+ layers
        for stage, batch in zip(stages, (512, 64)):
            _assert_equal(ref, _layers(ctx, stage, cam, 5), 5, f"twin discs, batch {batch}")
    finally:
        for obj in (*stages, peel, splats):
            obj.release()


def _tile_labels(ctx, tiles, splats, cam: Camera, depth: np.ndarray) -> np.ndarray:
    """(h, w) labels of the labeling pass for raytraced camera z ``depth`` (0 = none): on ``tiles``'
    lists of the last frame (dmrt_tiles_labeling.glsl), or with None by splatting the proxies
    again (dmrt_labeling.glsl, portable layout)."""
    from dmrt.gl import abi
    from dmrt.gl.kernels import fill_u32

    h, w = depth.shape
    hits = np.zeros(h * w, abi.HIT_DTYPE)
    hits["depth"] = depth.ravel()
    bufs = {abi.B_HITS: ctx.buffer(hits.tobytes()), abi.B_KEY: ctx.buffer(reserve=4 * h * w),
            abi.B_VLABEL: ctx.buffer(reserve=4 * h * w)}
    try:
        if tiles is not None:
            tiles.label_pass(_uniforms(cam), bufs[abi.B_HITS], bufs[abi.B_KEY], bufs[abi.B_VLABEL], packed=False)
        else:
            fill_u32(ctx, bufs[abi.B_KEY], EMPTY_BITS, h * w)
            fill_u32(ctx, bufs[abi.B_VLABEL], EMPTY_LABEL, h * w)
            ctx.memory_barrier()
            for resolve in (0, 1):
                splats.run("dmrt_labeling", {"RESOLVE": resolve}, _uniforms(cam), bufs)
        label = np.frombuffer(bufs[abi.B_VLABEL].read(), np.int32).reshape(h, w).copy()
        assert (label[depth > 0] != EMPTY_LABEL).all()  # a pixel with a point is covered by its disc
        return label
    finally:
        for b in bufs.values():
            b.release()


def test_tiles_match_peeling_with_splat_overlap(ctx, bundle):
    """Radii x 2.5 (the paper's worst case, Section 6.4): many more discs over each pixel, the same
    layers as peeling."""
    from dmrt.runtime.tiles import TileVisibility
    from dmrt.runtime.visibility import ProxySplats, VisibilityStage

    proxy = {**bundle.proxy, "radii": np.asarray(bundle.proxy["radii"]) * 2.5}
    splats = ProxySplats(ctx, proxy)
    peel = VisibilityStage(ctx, splats, "compute")
    tiles = TileVisibility(ctx, splats)
    cam = _views(bundle)[0]
    try:
        splats.begin_frame()
        _assert_equal(_layers(ctx, peel, cam, 3), _layers(ctx, tiles, cam, 3), 3, "radii x 2.5")
    finally:
        for obj in (tiles, peel, splats):
            obj.release()


def test_renderer_frames_match_compute(ctx, bundle):
    """Whole frames with ``method="tiles"`` against ``method="compute"``: the raytracing pass starts
    from the same layers (test_tiles_match_peeling), so the frames are the same computation; depths
    within 1e-6 relative on >= 99.5 % of the pixels (float results of one program on other
    dispatch shapes; measured: all). The
    labeling pass of the tiles path walks the tile lists (dmrt_tiles_labeling.glsl) instead of
    splatting the proxies again: the same discs, the same cover test and distance, so the final
    labels are the same wherever the depths are (ties: the smallest label in both). The tile
    raster's options (RenderConfig.tile_batch, tile_hits, tile_split) change its speed, not its
    frames: with 64 discs a batch, 4 kept hits and every list of more than 32 discs split over
    workgroups, the frame is bit-equal to the default's."""
    from dmrt.runtime.renderer import RenderConfig, Renderer

    cfg = {"layers": 3, "async_photos": False, "max_uploads_per_frame": 0}
    tiles = Renderer(bundle, RenderConfig(method="tiles", **cfg), ctx)
    peel = Renderer(bundle, RenderConfig(method="compute", **cfg), ctx)
    other = Renderer(bundle, RenderConfig(method="tiles", tile_batch=64, tile_hits=4, tile_split=32, **cfg), ctx)
    try:
        for cam in (bundle.cameras[3], _novel(bundle.cameras[1], bundle.cameras[2])):
            a, b = peel.render(cam, W), tiles.render(cam, W)
            assert (a["depth"] > 0).mean() > 0.5
            close = np.abs(a["depth"] - b["depth"]) <= 1e-6 * np.maximum(a["depth"], 1e-3)
            assert close.mean() >= AGREE
            assert (a["label"] == b["label"]).mean() >= AGREE
            assert (a["label"] == b["label"])[close].all()
            assert (a["label_raw"] != a["label"]).any()  # the labeling pass did relabel pixels
            la, lb = peel.layers(), tiles.layers()
            assert np.array_equal(la["label"], lb["label"])
            assert (other.visibility.tiles.batch, other.visibility.tiles.top) == (64, 4)
            c = other.render(cam, W)
            assert np.array_equal(b["depth"], c["depth"]) and np.array_equal(b["label"], c["label"])
        assert other.visibility.tiles.stats()["split_tiles"] > 0  # the last frame split lists
        assert tiles.visibility.nbytes > 0
    finally:
        for r in (tiles, peel, other):
            r.release()


def test_tile_labeling_packed_layout(ctx, bundle):
    """The tiles labeling pass writes the 64-bit (label, distance bits) keys of the NVIDIA path the
    same as the portable pair of buffers (dmrt_label_finalize.glsl reads either; the renderer's
    own frames take the final labels from the pass directly)."""
    from dmrt.runtime.renderer import RenderConfig, Renderer

    r = Renderer(bundle, RenderConfig(method="tiles", layers=3, async_photos=False), ctx)
    try:
        cam = bundle.cameras[3].resized(W)
        r.render(cam)
        npix = cam.width * cam.height
        key, vlabel = ctx.buffer(reserve=8 * npix), ctx.buffer(reserve=4 * npix)
        local = cam.relative_to(r.origin)
        uniforms = {"u_R": local.R.T.ravel(), "u_t": local.t, "u_K": (local.fx, local.fy, local.cx, local.cy),
                    "u_size": (cam.width, cam.height)}
        r.visibility.tiles.label_pass(uniforms, r._buffers["hits"], key, vlabel, packed=False)
        bits = np.frombuffer(key.read(), np.uint32)[:npix].copy()
        label = np.frombuffer(vlabel.read(), np.int32)[:npix].copy()
        assert (label >= 0).mean() > 0.5
        r.visibility.tiles.label_pass(uniforms, r._buffers["hits"], key, vlabel, packed=True)
        packed = np.frombuffer(key.read(), np.uint32)[:2 * npix].reshape(npix, 2)
        np.testing.assert_array_equal(packed[:, 0].view(np.int32), label)
        np.testing.assert_array_equal(packed[:, 1], bits)
        key.release()
        vlabel.release()
    finally:
        r.release()


def test_no_hit_masks_without_the_labeling_pass(ctx, bundle):
    """A renderer without the labeling pass has its tiles raster write no hit masks (no buffer, no
    32-byte writes a pixel): the same layers and the same frame as with them."""
    from dmrt.runtime.renderer import RenderConfig, Renderer

    cfg = {"layers": 3, "async_photos": False, "max_uploads_per_frame": 0, "labeling": False}
    without = Renderer(bundle, RenderConfig(method="tiles", **cfg), ctx)
    peel = Renderer(bundle, RenderConfig(method="compute", **cfg), ctx)
    try:
        cam = _novel(bundle.cameras[1], bundle.cameras[2])
        a, b = peel.render(cam, W), without.render(cam, W)
        assert without.visibility.tiles.masks is None and not without.visibility.tiles.hit_masks
        assert np.array_equal(peel.layers()["label"], without.layers()["label"])
        np.testing.assert_array_equal(a["label"], b["label"])
    finally:
        without.release()
        peel.release()
