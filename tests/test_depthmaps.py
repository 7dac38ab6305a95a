"""Depth maps from oriented circular splats (paper Section 4.1), on a real GL context.

Both GPU paths (compute, raster) are checked against analytic planes and against
:func:`reference.twins.splat_depth_map`, an independent brute-force float64 implementation of the
same primitive written in world space (every pixel against every disc, no bounding boxes).
"""

import threading

import numpy as np
import pytest

from dmrt.camera import Camera
from dmrt.io.exr import read_depth_exr, write_depth_exr
from dmrt.preprocess.depthmaps import DepthMapConfig, DepthMapRenderer, depth_map_size
from dmrt.errors import InputError
from dmrt.gl import GpuTimer
from reference.twins import splat_depth_map

W, H = 96, 64  # depth-map size used throughout: small enough for llvmpipe and the numpy reference

# (method, renderer tweak): the default paths, plus settings that push most discs through the
# second programs (workgroup-per-disc compute pass; geometry-shader quads in the raster path)
VARIANTS = {
    "compute": ("compute", {}),
    "compute-large": ("compute", {"max_thread_pixels": 4}),
    "raster": ("raster", {}),
    "raster-quads": ("raster", {"max_point_size": 8.0}),
}


def _render(ctx, variant, camera, chunks, **config):
    method, tweak = VARIANTS[variant]
    cfg = DepthMapConfig(width=W, method=method, **config)
    if "max_thread_pixels" in tweak:
        cfg.max_thread_pixels = tweak["max_thread_pixels"]
    renderer = DepthMapRenderer(ctx, cfg)
    if "max_point_size" in tweak:
        renderer.max_point_size = tweak["max_point_size"]
    try:
        return renderer.render(camera, chunks)
    finally:
        renderer.release()


def _plane_grid(origin, normal, half, spacing):
    """Points on a square grid of the plane through ``origin`` with ``normal``; returns p, n, r."""
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    a = np.cross(normal, [0.0, 1.0, 0.0])
    a /= np.linalg.norm(a)
    b = np.cross(normal, a)
    g = np.arange(-half, half + 1e-9, spacing)
    u, v = (x.ravel() for x in np.meshgrid(g, g))
    p = np.asarray(origin) + u[:, None] * a + v[:, None] * b
    n = np.tile(normal, (len(p), 1))
    # 0.75 spacing > half the cell diagonal (0.707): the discs leave no gaps
    r = np.full(len(p), 0.75 * spacing)
    return p.astype(np.float32), n.astype(np.float32), r.astype(np.float32), (a, b)


def _analytic_plane_depth(camera, origin, normal, axes, half):
    """Exact camera z of the plane per pixel, and the pixels well inside the grid."""
    cam = camera.scaled(W, H)
    dirs, c = cam.pixel_rays()
    normal = np.asarray(normal, float) / np.linalg.norm(normal)
    s = ((np.asarray(origin) - c) @ normal) / (dirs @ normal)
    hit = c + s[:, None] * dirs - origin
    inside = (np.abs(hit @ axes[0]) < half - 0.1) & (np.abs(hit @ axes[1]) < half - 0.1) & (s > 0)
    return s.reshape(H, W), inside.reshape(H, W)


PHOTO = dict(width=960, height=640)  # the renderer scales the photo camera to W x H


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("tilt", ["frontal", "tilted"])
def test_plane_depth_is_exact(ctx, variant, tilt):
    camera = Camera.look_at("plane", eye=(0.2, -0.1, 0.0), target=(0.0, 0.0, 3.0), **PHOTO)
    origin = np.array([0.0, 0.0, 3.0])
    normal = (0.0, 0.0, 1.0) if tilt == "frontal" else (np.sin(0.7), 0.3, np.cos(0.7))
    p, n, r, axes = _plane_grid(origin, normal, half=2.4, spacing=0.04)
    truth, inside = _analytic_plane_depth(camera, origin, normal, axes, half=2.4)
    assert inside.mean() > 0.5
    depth = _render(ctx, variant, camera, [(p, n, r)])
    assert depth.shape == (H, W) and depth.dtype == np.float32
    # a disc lies in the plane, so every covered pixel gets the plane's depth up to float32 rounding
    # (3 m x 1e-7); 1e-4 m is the contract
    assert (depth[inside] > 0).all()
    assert np.abs(depth[inside] - truth[inside]).max() < 1e-4
    if tilt == "tilted":
        # discs facing the camera instead (zero normals) are off the plane by up to r sin(tilt):
        # orientation is what makes the depth exact
        flat = _render(ctx, variant, camera, [(p, np.zeros_like(n), r)])
        assert np.abs(flat[inside] - truth[inside]).max() > 1e-3


def _random_scene(seed=0, n=1500):
    rng = np.random.default_rng(seed)
    camera = Camera.look_at("rand", eye=(0.0, -5.0, 1.5), target=(0.0, 0.0, 1.0), **PHOTO)
    p = rng.uniform([-3, -2, 0], [3, 2, 2.5], (n, 3))
    r = rng.uniform(0.03, 0.25, n)
    c = camera.center
    fwd = camera.R[2]
    # a few discs near the camera, two of them reaching behind its plane (whole-image pixel boxes,
    # but off to the side so that they cover only part of the map), discs behind the camera, and
    # discs just outside the view whose radii reach in across the image border
    near = c + fwd * rng.uniform(0.3, 0.6, (4, 1)) + rng.normal(0, 0.1, (4, 3))
    crossing = c + camera.R[0] * np.array([[0.25], [-0.3]]) + camera.R[1] * 0.1 + fwd * 0.05
    behind = c - fwd * rng.uniform(0.8, 2.0, (20, 1)) + rng.normal(0, 0.2, (20, 3))
    side = c + fwd * 4.0 + camera.R[0] * rng.choice([-2.5, 2.5], (30, 1)) + rng.normal(0, 0.2, (30, 3))
    p = np.concatenate([p, near, crossing, behind, side])
    r = np.concatenate([r, rng.uniform(0.03, 0.08, 4), [0.45, 0.5], rng.uniform(0.1, 0.4, 20),
                        rng.uniform(0.3, 0.6, 30)])
    nrm = rng.normal(size=p.shape)
    nrm[n + 4:n + 6] = camera.R[0] + 0.2 * camera.R[2]  # the crossing discs reach into the view
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    return camera, p.astype(np.float32), nrm.astype(np.float32), r.astype(np.float32)


@pytest.fixture(scope="module")
def random_scene():
    camera, p, n, r = _random_scene()
    ref, ambiguous = splat_depth_map(camera, p, n, r, W, H)
    return camera, p, n, r, ref, ambiguous


@pytest.fixture(scope="module")
def random_depths(ctx, random_scene):
    camera, p, n, r, _ref, _amb = random_scene
    return {v: _render(ctx, v, camera, [(p, n, r)]) for v in VARIANTS}


def _mismatch(a, b, rel):
    return np.abs(a.astype(np.float64) - b) > rel * np.maximum(np.abs(a), np.abs(b))


@pytest.mark.parametrize("variant", VARIANTS)
def test_random_splats_match_numpy_reference(random_scene, random_depths, variant):
    _camera, _p, _n, _r, ref, ambiguous = random_scene
    depth = random_depths[variant]
    covered = (depth > 0) | (ref > 0)
    assert covered.mean() > 0.5  # the scene fills most of the map
    bad = _mismatch(depth, ref, 1e-4) & covered
    assert bad.sum() <= 0.01 * covered.sum()
    # and every mismatch is one float32 rounding can explain (a disc rim through the pixel centre)
    assert not (bad & ~ambiguous).any(), np.argwhere(bad & ~ambiguous)[:10]


@pytest.mark.parametrize("variant", ["compute-large", "raster", "raster-quads"])
def test_gpu_paths_agree(random_scene, random_depths, variant):
    ambiguous = random_scene[5]
    a, b = random_depths["compute"], random_depths[variant]
    covered = (a > 0) | (b > 0)
    bad = _mismatch(a, b, 1e-5) & covered
    assert bad.sum() <= 0.01 * covered.sum()
    assert not (bad & ~ambiguous).any()


@pytest.mark.parametrize("method", ["compute", "raster"])
def test_chunked_input_equals_one_chunk(ctx, random_scene, random_depths, method):
    camera, p, n, r = random_scene[:4]
    chunks = [(p[a:b], n[a:b], r[a:b]) for a, b in [(0, 100), (100, 130), (130, 900), (900, len(p))]]
    chunks.insert(2, (p[:0], n[:0], r[:0]))  # an empty chunk is fine
    # chunk_points=256 also splits the big chunks into several GPU batches
    depth = _render(ctx, method, camera, iter(chunks), chunk_points=256)
    # nearest-wins is order-independent (atomicMin / MIN blend): bit-identical
    np.testing.assert_array_equal(depth, random_depths[method])


def test_renderer_reuse_timer_and_size(ctx, random_scene):
    camera, p, n, r = random_scene[:4]
    timer = GpuTimer(ctx)
    renderer = DepthMapRenderer(ctx, DepthMapConfig(width=W), timer=timer)
    first = renderer.render(camera, [(p, n, r)])
    again = renderer.render(camera.scaled(W, H), [(p, n, r)])  # any camera resolution, same map
    np.testing.assert_array_equal(first, again)
    # timed twice; a time where the driver measures one (a software rasterizer's read as NaN)
    assert timer.counts["depthmap"] == 2 and not timer.ms["depthmap"] <= 0
    small = renderer.render(camera, [(p[:0], n[:0], r[:0])])
    assert (small == 0).all()
    renderer.release()
    assert depth_map_size(Camera("c", 1000, 667, 1, 1, 0, 0), 100) == (100, 67)
    with pytest.raises(ValueError, match="method"):
        DepthMapRenderer(ctx, DepthMapConfig(method="ray"))
    with pytest.raises(ValueError, match=r"\(n, 3\)"):
        DepthMapRenderer(ctx, DepthMapConfig(width=W)).render(camera, [(p, n[:5], r)])


def _camera_plane_scene():
    """Discs whose bounding sphere reaches the camera plane (z <= r) have no bounded projection, but
    those beside the optical axis (|x| > r or |y| > r) reach into the view from one side only.
    Every wall and floor of a room scan has such discs near each camera. Returns camera, p, n, r."""
    rng = np.random.default_rng(5)
    camera = Camera.look_at("plane", eye=(0.0, 0.0, 0.0), target=(0.0, 1.0, 0.0), **PHOTO)
    n = 80
    r = rng.uniform(0.2, 0.6, n)
    z = rng.uniform(-0.5, 1.0, n) * r
    half = np.array([0.5, 0.5 * PHOTO["height"] / PHOTO["width"]])  # tan of the half fields of view
    # one coordinate beside the axis by r plus up to 1.2x the view's half extent at depth z + r, the
    # other anywhere within that extent
    xy = rng.uniform(-1, 1, (n, 2)) * half * (z + r)[:, None]
    k = rng.integers(2, size=n)
    xy[np.arange(n), k] = rng.choice([-1, 1], n) * (r + rng.uniform(0, 1.2, n) * half[k] * (z + r))
    p = np.column_stack([xy, z]) @ camera.R + camera.center  # camera -> world
    nrm = rng.normal(size=(n, 3))
    # a back wall, 6 m away
    g = np.arange(-4.0, 4.0 + 1e-9, 0.2)
    u, v = (x.ravel() for x in np.meshgrid(g, g))
    wall = np.stack([u, np.full_like(u, 6.0), v], axis=1)
    p = np.concatenate([p, wall]).astype(np.float32)
    nrm = np.concatenate([nrm, np.tile([0.0, 1.0, 0.0], (len(u), 1))]).astype(np.float32)
    r = np.concatenate([r, np.full(len(u), 0.15)]).astype(np.float32)
    return camera, p, nrm, r


@pytest.mark.parametrize("variant", VARIANTS)
def test_discs_through_the_camera_plane_match_reference(ctx, variant):
    camera, p, nrm, r = _camera_plane_scene()
    ref, ambiguous = splat_depth_map(camera, p, nrm, r, W, H)
    near = (ref > 0) & (ref < 1.0)
    assert 0.2 < near.mean() < 0.8  # the camera-plane discs cover part of the map, not all of it
    depth = _render(ctx, variant, camera, [(p, nrm, r)])
    covered = (depth > 0) | (ref > 0)
    bad = _mismatch(depth, ref, 1e-4) & covered
    assert bad.sum() <= 0.01 * covered.sum()
    assert not (bad & ~ambiguous).any(), np.argwhere(bad & ~ambiguous)[:10]


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("scene", ["random", "camera-plane"])
def test_frustum_culling_is_exact(ctx, variant, scene):
    # one disc per bucket: each disc's own box against the frustum, the closest the culling gets
    # (discs behind the camera, beside the view reaching in, through the camera plane)
    camera, p, n, r = (_random_scene() if scene == "random" else _camera_plane_scene())
    whole = _render(ctx, variant, camera, [(p, n, r)], cull_points=0)
    method, tweak = VARIANTS[variant]
    renderer = DepthMapRenderer(ctx, DepthMapConfig(width=W, method=method, cull_points=1, **{
        k: v for k, v in tweak.items() if k != "max_point_size"}))
    renderer.max_point_size = tweak.get("max_point_size", getattr(renderer, "max_point_size", None))
    try:
        (_, culled), = renderer.render_many([camera], lambda: iter([(p, n, r)]))
        stats = renderer.last_stats
        again = renderer.render(camera, [(p, n, r)])  # render() culls on the CPU before the upload
    finally:
        renderer.release()
    np.testing.assert_array_equal(culled, whole)
    np.testing.assert_array_equal(again, whole)
    assert stats["splats_all"] == len(p) and stats["splats"] < 0.95 * len(p)  # it did cull


# -- many cameras, one upload ------------------------------------------------------------------
@pytest.fixture(scope="module")
def many_scene():
    """Two cameras of different sizes and a cloud of ~6300 discs (four random scenes' discs)."""
    cams = [_random_scene(0)[0],
            Camera.look_at("side", eye=(4.0, -3.0, 2.0), target=(0.0, 0.0, 1.0), width=800, height=600)]
    parts = [_random_scene(seed)[1:] for seed in range(4)]
    p, n, r = (np.concatenate(a) for a in zip(*parts))
    # irregular chunks, an empty one among them: render_many re-cuts them into batches
    cuts = [0, 700, 701, 701, 2900, 3000, len(p)]
    chunks = [(p[a:b], n[a:b], r[a:b]) for a, b in zip(cuts[:-1], cuts[1:])]
    return cams, chunks


# "threads": the GPU batches packed, bucketed and culled on three feed threads (compute and
# raster: on one), which every mode drops half read at some point (the first upload that exceeds
# the budget, an early stop)
@pytest.mark.parametrize("method", ["compute", "raster", "threads"])
@pytest.mark.parametrize("mode", ["overlapped", "resident", "grouped", "camera-groups", "streamed"])
def test_render_many_equals_render(ctx, many_scene, method, mode):
    cams, chunks = many_scene
    chunk_points = 256
    timer = GpuTimer(ctx)
    threads = threading.active_count()
    config = DepthMapConfig(width=W, method=method.replace("threads", "compute"), chunk_points=chunk_points,
                            feed_threads=3 if method == "threads" else 1, overlap=mode == "overlapped")
    renderer = DepthMapRenderer(ctx, config, timer=timer)
    try:
        expected = [renderer.render(c, iter(chunks)) for c in cams]
        maps = sum(renderer.map_bytes(c) for c in cams)
        assert maps == W * (H + 72) * (8 if method == "raster" else 4)
        batch = chunk_points * 7 * 4
        cloud = sum(len(c[0]) for c in chunks) * 7 * 4
        # overlapped: the maps and two batches; resident: the whole cloud; grouped: the maps and
        # three batches; camera-groups: one map and three batches (a group per camera); streamed:
        # not even one map and a batch
        one = max(renderer.map_bytes(c) for c in cams)
        budget = {"overlapped": maps + 2 * batch, "resident": cloud, "grouped": maps + 3 * batch,
                  "camera-groups": one + 3 * batch, "streamed": one + batch - 1}[mode]
        assert budget < cloud or mode == "resident"
        calls = []

        def chunks_fn():
            calls.append(1)
            return iter(chunks)

        timer.reset()
        got = list(renderer.render_many(cams, chunks_fn, resident_mb=budget / 2**20))
        stats = renderer.last_stats
        assert stats["mode"] == mode.replace("camera-groups", "grouped")
        assert [i for i, _ in got] == list(range(len(cams)))
        for (_, depth), want in zip(got, expected):
            assert depth.dtype == np.float32 and depth.shape == want.shape
            np.testing.assert_array_equal(depth, want)  # nearest-wins in any order: bit-identical
        if mode == "overlapped":  # one upload and one timed section of every camera's splats per batch
            assert len(calls) == 1 and stats["groups"] == -(-cloud // batch) and stats["camera_groups"] == 1
            assert timer.counts["depthmap"] == timer.counts["depthmap_upload"] == stats["groups"]
        elif mode == "resident":
            assert len(calls) == 1 and stats["groups"] == 1
            assert timer.counts["depthmap"] == len(cams)  # one section per camera
            assert timer.counts["depthmap_upload"] == -(-cloud // batch)  # every batch once
        elif mode == "grouped":
            # the first try uploads up to the budget, then the source is read once more
            assert len(calls) == 2 and stats["groups"] == -(-cloud // (3 * batch))
            assert timer.counts["depthmap_upload"] < 2 * -(-cloud // batch)
        elif mode == "camera-groups":  # the first group reads the rest of the cloud, the second all of it
            assert stats["camera_groups"] == 2 and len(calls) == 3
        else:
            assert len(calls) == 1 + len(cams)
        if mode != "streamed":
            assert stats["points"] == cloud // 28
        # frustum culling: every point counted once per camera, the splats sent among them
        assert stats["splats_all"] == len(cams) * (cloud // 28) and 0 < stats["splats"] <= stats["splats_all"]
        assert timer.counts["depthmap_readback"] == len(cams)
        # stopping early is fine: the generator frees what it holds
        first = renderer.render_many(cams, chunks_fn, resident_mb=budget / 2**20)
        np.testing.assert_array_equal(next(first)[1], expected[0])
        first.close()
        assert threading.active_count() == threads  # no batch producer left behind
        # a bad chunk fails the call, and leaves no feed thread behind either
        p, n, r = chunks[0]
        with pytest.raises(ValueError, match="depth-map chunk"):
            list(renderer.render_many(cams, lambda: iter([*chunks, (p, n, r[:-1])]), resident_mb=budget / 2**20))
        assert threading.active_count() == threads
        # no points at all: empty maps
        empty = list(renderer.render_many(cams, lambda: iter([])))
        assert all((d == 0).all() for _, d in empty)
        assert renderer.last_stats["mode"] == ("overlapped" if config.overlap else "resident")
    finally:
        renderer.release()
        renderer.release()  # twice is fine


# -- OpenEXR ------------------------------------------------------------------------------------
def test_exr_round_trip(tmp_path):
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.5, 80.0, (37, 53)).astype(np.float32)
    depth[rng.random(depth.shape) < 0.2] = 0.0
    path = tmp_path / "IMG_0001.exr"
    write_depth_exr(path, depth)
    back = read_depth_exr(path)
    assert back.dtype == np.float32
    np.testing.assert_array_equal(back, depth)
    write_depth_exr(path, depth * 2)  # overwriting replaces atomically, leaving no temp files
    np.testing.assert_array_equal(read_depth_exr(path), depth * 2)
    assert [f.name for f in tmp_path.iterdir()] == ["IMG_0001.exr"]


def test_exr_errors_name_the_file(tmp_path):
    import OpenEXR

    missing = tmp_path / "missing.exr"
    with pytest.raises(InputError, match="missing.exr.*not found"):
        read_depth_exr(missing)
    garbage = tmp_path / "garbage.exr"
    garbage.write_bytes(b"not an exr file at all")
    with pytest.raises(InputError, match="garbage.exr.*OpenEXR"):
        read_depth_exr(garbage)
    other = tmp_path / "other.exr"
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"R": np.ones((4, 4), np.float32)}).write(str(other))
    with pytest.raises(InputError, match=r"other.exr.*no 'Z' channel.*R"):
        read_depth_exr(other)
    negative = tmp_path / "negative.exr"
    write_depth_exr(negative, -np.ones((4, 4), np.float32))
    with pytest.raises(InputError, match="negative.exr.*negative"):
        read_depth_exr(negative)
    with pytest.raises(ValueError):
        write_depth_exr(tmp_path / "bad.exr", np.ones((2, 2, 2), np.float32))


# -- the tiny scene: phase 3 of preprocessing with and without the frustum culling --------------
def test_culled_depth_maps_of_the_tiny_scene_equal_the_whole_ones(tiny_scene, tmp_path):
    from dataclasses import replace

    from dmrt.io.scene import load_scene
    from dmrt.preprocess.config import PreprocessConfig
    from dmrt.preprocess.pipeline import normals_radii_phase, octree_phase, render_depth_maps

    config = PreprocessConfig(depthmap_width=128, chunk_points=50_000)
    scene = load_scene(tiny_scene, chunk_size=config.chunk_points)
    work = tmp_path / "work"
    octree = octree_phase(scene, work, config)
    cams = [c.relative_to(scene.origin) for c in scene.cameras]
    _, has_normals = normals_radii_phase(octree, cams, work, config)
    # four photos, two per room; culled: in camera groups of two maps (1.5 MB = one 1.4 MB batch of
    # 50k points and two 128 x 85 maps), the octree read once per group
    cams, names = cams[:4], [c.name for c in cams[:4]]
    runs = {"whole": replace(config, cull_points=0),
            "culled": replace(config, cull_points=1024, resident_mb=1.5)}
    maps, walls = {}, {}
    for name, cfg in runs.items():
        walls[name] = {}
        rels, _, _, _ = render_depth_maps(cams, names, work, tmp_path / name, has_normals,
                                          cfg, wall=walls[name])
        maps[name] = [read_depth_exr(tmp_path / name / rel) for rel in rels]
    for whole, culled in zip(maps["whole"], maps["culled"]):
        assert (whole > 0).mean() > 0.9
        np.testing.assert_array_equal(culled, whole)
    whole, culled = walls["whole"], walls["culled"]
    assert whole["mode"] == "overlapped" and whole["splats"] == whole["splats_all"] == 4 * octree.n_points
    assert culled["mode"] == "grouped" and culled["camera_groups"] == 2
    # each photo sees about one of the two rooms; buckets of 1024 points (a level's Morton order)
    # keep a margin around that: 62 % of the splats were sent
    assert culled["splats_all"] == 4 * octree.n_points and culled["splats"] < 0.7 * culled["splats_all"]


def test_batch_buckets_equal_those_of_the_whole_batch():
    """Batches hold the chunks' values as float32 rows, and their culling buckets, reduced chunk
    piece by chunk piece (over the chunks' own arrays where they are float32), are Buckets.of the
    batch's rows cut where a chunk begins; packed on several threads, the same batches in order,
    with each camera's runs those of its visible buckets."""
    from dmrt.preprocess.depthmaps import _batches
    from dmrt.preprocess.frustum import Buckets

    rng = np.random.default_rng(3)
    sizes = [5, 0, 700, 1, 333, 1200, 64]
    chunks = [(rng.normal(size=(m, 3)).astype(np.float32 if k % 2 else np.float64), rng.normal(size=(m, 3)),
               rng.random(m).astype(np.float32 if k % 3 else np.float64)) for k, m in enumerate(sizes)]
    chunks[2][0][7] = np.nan  # a NaN point spoils nothing but its box
    starts = np.cumsum([0] + sizes)[:-1]
    # two cameras looking at the points, one looking away from them all
    cams = [Camera.look_at(f"c{k}", eye=eye, target=target, width=W, height=H)
            for k, (eye, target) in enumerate([((0, -3, 0.5), (0, 0, 0)), ((0, 0, 10), (0, 10, 14)),
                                                ((2.5, 0, 0.2), (0, 0, 0))])]
    batches = list(_batches(iter(chunks), 500, cull=64))
    threaded = list(_batches(iter(chunks), 500, cull=64, cameras=cams, threads=3))
    assert [len(rows) for rows, _, _ in batches] == [500] * 4 + [sum(sizes) - 2000]
    # the rows: each value cast to float32 (float64 chunks) or copied bit for bit (float32 ones)
    want = np.concatenate([np.column_stack(c).astype(np.float32) for c in chunks if len(c[0])])
    np.testing.assert_array_equal(np.concatenate([rows for rows, _, _ in batches]).view(np.uint32),
                                  want.view(np.uint32))
    sent = np.zeros(len(cams), np.int64)
    for b, ((rows, got, _), (rows3, got3, runs)) in enumerate(zip(batches, threaded, strict=True)):
        np.testing.assert_array_equal(rows3.view(np.uint32), rows.view(np.uint32))
        breaks = [s - 500 * b for s, m in zip(starts, sizes) if m and 0 < s - 500 * b < len(rows)]
        want = Buckets.of(rows[:, 0:3], rows[:, 6], 64, breaks)
        for k in ("starts", "counts", "lo", "hi"):
            np.testing.assert_array_equal(getattr(got, k), getattr(want, k))
            np.testing.assert_array_equal(getattr(got3, k), getattr(want, k))
        for i, cam in enumerate(cams):  # all cameras culled at once as each one alone
            for x, y in zip(runs[i], want.runs(want.visible(cam, lines=True)), strict=True):
                np.testing.assert_array_equal(x, y)
            sent[i] += runs[i][1].sum()
    # the camera looking away splats only the bucket of the NaN point (kept by every camera)
    assert sent[0] > 1000 and sent[2] > 1000 and sent[1] <= 64
    assert all(buckets is None and runs is None for _, buckets, runs in _batches(iter(chunks), 500))
