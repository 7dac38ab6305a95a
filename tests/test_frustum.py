"""Spatial buckets and their frustum test (dmrt.preprocess.frustum), against a per-point test."""

import numpy as np

from dmrt.camera import Camera
from dmrt.preprocess.frustum import Buckets


def test_buckets_keep_every_point_a_camera_sees():
    rng = np.random.default_rng(3)
    camera = Camera.look_at("c", eye=(0.0, 0.0, 1.5), target=(5.0, 0.0, 1.5), width=120, height=80)
    # a street of points 40 m each way, in a spatial order, radii up to 0.3 m
    p = np.stack([rng.uniform(-40, 40, 20_000), rng.uniform(-4, 4, 20_000), rng.uniform(0, 3, 20_000)], 1)
    p = p[np.argsort(p[:, 0])].astype(np.float32)
    r = rng.uniform(0.01, 0.3, len(p)).astype(np.float32)
    buckets = Buckets.of(p, r, 500, breaks=[1234, 7777])
    assert np.all(buckets.counts <= 500) and {1234, 7777} <= set(buckets.starts.tolist())
    assert buckets.starts[0] == 0 and buckets.n_points == len(p)
    rows = buckets.rows(buckets.visible(camera))
    first, count = buckets.runs(buckets.visible(camera))
    np.testing.assert_array_equal(rows, np.concatenate([np.arange(a, a + n) for a, n in zip(first, count)]))
    # every disc whose centre is in view is among the rows kept
    uv, z = camera.project(p)
    inside = (z > 0) & (uv[:, 0] >= 0) & (uv[:, 0] <= camera.width) & (uv[:, 1] >= 0) & (uv[:, 1] <= camera.height)
    assert inside.any() and np.isin(np.flatnonzero(inside), rows).all()
    assert 0.2 < len(rows) / len(p) < 0.7  # about the half of the street ahead, not all of it


def test_lines_keep_discs_through_the_camera_plane_and_nan_boxes():
    camera = Camera.look_at("c", eye=(0.0, 0.0, 0.0), target=(1.0, 0.0, 0.0), width=64, height=48)
    # 0: 5 m behind the camera: culled; 1: around the camera centre: kept; 2: a NaN position: kept
    p = np.array([[-5.0, 0.0, 0.0], [0.2, 0.0, 0.0], [np.nan, 0.0, 0.0]], np.float32)
    r = np.array([0.5, 0.5, 0.1], np.float32)
    buckets = Buckets.of(p, r, 1)
    assert buckets.visible(camera).tolist() == [False, True, True]
    # a bucket from 1 m behind the camera plane to 4 cm before it, 15 cm beside the axis: outside
    # the view (60 degrees wide: 2.3 cm beside the axis at 4 cm), inside the view mirrored through
    # the camera centre: a pixel's line (the grazing rule) may pass there
    q = np.array([[-1.0, -0.15, 0.0], [0.04, -0.15, 0.0]], np.float32)
    side = Buckets.of(q, np.full(2, 1e-3, np.float32), 2)
    assert side.visible(camera).tolist() == [False] and side.visible(camera, lines=True).tolist() == [True]
    # points (no radii) exactly: the one behind goes
    assert Buckets.of(p, None, 1).visible(camera).tolist() == [False, True, True]
    empty = Buckets.of(p[:0], None, 4)
    assert len(empty) == 0 and empty.visible(camera).shape == (0,) and len(empty.rows(empty.visible(camera))) == 0
