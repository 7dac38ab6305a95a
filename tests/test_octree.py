"""Out-of-core levels of detail (dmrt.preprocess.octree): partition, nesting, evenness, out-of-core equivalence.

The truths here are independent of the implementation: a naive in-memory reference of the level
definition (per level, per cell, the free point closest to the cell centre, ties by x, y, z), the
input itself (every point once, attributes attached, positions rounded to float32), and set
identities for nesting/coverage. The octree stores float32 positions: it is the octree of the
input rounded to float32, so the references take the rounded input.
"""

from __future__ import annotations

import dataclasses
import filecmp
import json
import os
import tracemalloc

import numpy as np
import pytest

from dmrt.errors import InputError
from dmrt.io.pointcloud import PointCloud, PointWriter, point_range
from dmrt.morton import morton_encode
from dmrt.preprocess import octree as octree_module
from dmrt.preprocess.buckets import morton_columns
from dmrt.preprocess.octree import Octree, OctreeConfig, _best_of_runs, _block_cuts, _Grid, _Runs, _stable_order
from dmrt.preprocess.parallel import InProcess, ProcessPool

N_BIG = 2_000_000
CHUNK = 50_000


def surface_chunk(i: int, n: int = CHUNK, seed: int = 7):
    """Chunk ``i`` of a synthetic scanned scene: a 20x20 m ground, a 10 m wall and a sphere, 2 mm noise.
    Attributes: ``id`` (global input index) and ``colors`` (a function of ``id``)."""
    rng = np.random.default_rng([seed, i])
    u = rng.random((n, 2))
    kind = rng.integers(0, 3, n)
    p = np.empty((n, 3))
    p[:, 0], p[:, 1], p[:, 2] = u[:, 0] * 20, u[:, 1] * 20, 0.0
    m = kind == 1
    p[m, 2], p[m, 1] = u[m, 1] * 10, 5.0
    m = kind == 2
    th, ph = u[m, 0] * 2 * np.pi, np.arccos(1 - 2 * u[m, 1])
    p[m] = np.c_[np.sin(ph) * np.cos(th), np.sin(ph) * np.sin(th), np.cos(ph)] * 3 + [10, 10, 5]
    p += rng.normal(0, 0.002, p.shape)
    ids = np.arange(i * n, (i + 1) * n, dtype=np.int64)
    return p, {"id": ids, "colors": color_of(ids)}


def color_of(ids):
    return np.stack([ids % 251, (ids // 251) % 253, (ids * 7) % 255], axis=1).astype(np.uint8)


def cell_codes(pos, origin, root, levels, level):
    """Integer code of each point's level-``level`` cell, from the finest grid's integer coordinates
    shifted down (the definition of the nested grids)."""
    finest = levels - 2
    q = np.floor((pos - origin) / (root / 2.0 ** finest)).astype(np.int64) >> (finest - level)
    assert q.min() >= 0 and q.max() < 2 ** 21
    return (q[:, 0] << 42) | (q[:, 1] << 21) | q[:, 2]


def unique(a):
    """Sorted unique values (sort-based; NumPy 2.4's hash-based np.unique is slow on large arrays)."""
    s = np.sort(a)
    return s[np.r_[True, s[1:] != s[:-1]]] if len(s) else s


def reference_levels(pos, origin, root, levels):
    """Naive in-memory reference: (n,) level of each point."""
    finest = levels - 2
    q = np.floor((pos - origin) / (root / 2.0 ** finest)).astype(np.int64)
    level = np.full(len(pos), -1)
    for lvl in range(levels - 1):
        free = np.flatnonzero(level < 0)
        ql = q[free] >> (finest - lvl)
        p = pos[free]
        d = p - (origin + (ql + 0.5) * (root / 2.0 ** lvl))
        d2 = d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1] + d[:, 2] * d[:, 2]
        o = np.lexsort((free, p[:, 2], p[:, 1], p[:, 0], d2, ql[:, 2], ql[:, 1], ql[:, 0]))
        qs = ql[o]
        first = np.r_[True, np.any(qs[1:] != qs[:-1], axis=1)]
        level[free[o[first]]] = lvl
    level[level < 0] = levels - 1
    return level


def rounded(pos):
    """The input positions as the octree stores them: rounded to float32 (nearest), (n, 3) float32."""
    return np.asarray(pos, np.float64).astype(np.float32)


def ids_per_level(tree):
    return [np.sort(tree.read_level(lvl)["id"]) for lvl in range(tree.levels)]


def assert_same_files(a, b):
    """The two octrees' level files are byte-identical."""
    assert a.level_counts == b.level_counts and a.fields == b.fields
    for lvl in range(a.levels):
        for k in a.fields:
            fa, fb = a.path / f"level_{lvl:02d}" / f"{k}.bin", b.path / f"level_{lvl:02d}" / f"{k}.bin"
            assert fa.exists() == fb.exists(), f"level {lvl} {k}"
            if fa.exists():
                assert filecmp.cmp(fa, fb, shallow=False), f"level {lvl} field {k} differs"


# ---------------------------------------------------------------------------------------------
# a 2M-point cloud (48 MB of float64 positions, 83 MB with attributes) built with an 8 MB limit
# ---------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def big(tmp_path_factory):
    """The octree of 2M float64 points (their exact float64 bbox given) and the input positions
    rounded to float32, (n, 3) float32."""
    out = tmp_path_factory.mktemp("oct") / "big"
    # the test keeps the input in RAM only to check the result; the build sees 50k-point chunks
    data = [surface_chunk(i) for i in range(N_BIG // CHUNK)]
    pos = np.concatenate([p for p, _ in data])
    cfg = OctreeConfig(levels=8, memory_limit_mb=8)
    tree = Octree.build(lambda: iter(data), out, cfg, bbox=(pos.min(0), pos.max(0)), progress=False)
    return tree, rounded(pos)


def test_partition_every_point_once_with_attributes(big):
    tree, pos = big
    assert tree.n_points == N_BIG and sum(tree.level_counts) == N_BIG
    ids, got_pos = [], []
    for lvl in range(tree.levels):
        d = tree.read_level(lvl)
        assert d["positions"].dtype == np.float32 and d["positions"].shape == (tree.level_counts[lvl], 3)
        assert d["colors"].dtype == np.uint8 and d["id"].dtype == np.int64
        np.testing.assert_array_equal(d["colors"], color_of(d["id"]))  # attributes travel with points
        ids.append(d["id"])
        got_pos.append(d["positions"])
    ids = np.concatenate(ids)
    np.testing.assert_array_equal(np.sort(ids), np.arange(N_BIG))  # each input point exactly once
    np.testing.assert_array_equal(np.concatenate(got_pos), pos[ids])  # bit-exact float32 roundings
    # and, independent of the ids, the sorted coordinate arrays agree
    a = np.concatenate(got_pos)
    for axis in range(3):
        np.testing.assert_array_equal(np.sort(a[:, axis]), np.sort(pos[:, axis]))


def test_levels_even_nested_and_covering(big):
    tree, pos = big
    origin, root, L = tree.bbox[0], tree.meta["root_cell"], tree.levels
    # the given float64 box, rounded as the points are: the box of the rounded points
    np.testing.assert_array_equal(tree.bbox[0], pos.min(0))
    np.testing.assert_array_equal(tree.bbox[1], pos.max(0))
    assert tree.meta["points_outside_bbox"] == 0
    lod = np.zeros((0, 3), np.float32)
    for lvl in range(L - 1):
        p = tree.read_level(lvl)["positions"]
        # spatially even: no two points of level l share a level-l cell
        codes = cell_codes(p, origin, root, L, lvl)
        assert len(unique(codes)) == len(codes), f"level {lvl} has two points in one cell"
        lod = np.concatenate([lod, p])
        # LOD l+1 (levels 0..l) covers every occupied level-l cell of the whole cloud, and only those
        want = unique(cell_codes(pos, origin, root, L, lvl))
        have = unique(cell_codes(lod, origin, root, L, lvl))
        np.testing.assert_array_equal(have, want)


def test_subsampling_factors(big):
    tree, _ = big
    f = tree.subsampling_factors()
    assert len(f) == tree.levels and f[-1] == 1.0
    assert all(a > b for a, b in zip(f, f[1:]) if b > 1.0)  # strictly decreasing until all points are in
    assert all(a >= b for a, b in zip(f, f[1:]))
    # surfaces: each grid level multiplies the LOD size by about 4 while the cloud is dense enough
    lods = tree.lod_counts()
    assert 3.0 < lods[1] / lods[0] < 5.0 and 3.0 < lods[2] / lods[1] < 5.0
    assert tree.lod_for_factor(f[2]) == 3


def test_reopen_gives_same_data(big):
    tree, _ = big
    again = Octree.open(tree.path)
    assert again.level_counts == tree.level_counts and again.fields == tree.fields
    meta = json.loads((tree.path / "octree.json").read_text())
    assert meta["level_counts"] == tree.level_counts and meta["format"] == "dmrt-octree"
    for lvl in (0, 3, tree.levels - 1):
        a, b = tree.read_level(lvl), again.read_level(lvl)
        for k in a:
            np.testing.assert_array_equal(a[k], b[k])
        chunks = list(again.iter_level_chunks(lvl, chunk_size=10_007))
        assert all(len(c["positions"]) <= 10_007 for c in chunks)
        for k in a:
            np.testing.assert_array_equal(np.concatenate([c[k] for c in chunks]), a[k])
    streamed = list(again.iter_levels(range(3), chunk_size=5000))
    lod = again.read_lod(3)
    np.testing.assert_array_equal(np.concatenate([c["id"] for c in streamed]), lod["id"])
    ranged = list(again.point_range(range(3), chunk_size=5000)())
    np.testing.assert_array_equal(np.concatenate([c["positions"] for c in ranged]), lod["positions"])
    for c in chunks + streamed + ranged + [lod]:
        assert c["positions"].dtype == np.float32 and c["positions"].shape[1:] == (3,)
    assert again.meta["n_buckets"] > 10  # the 8 MB limit really split the cloud


def test_deal_interleaves_the_chunks(big):
    """OctreeRange.deal: the range's own chunks (never across a level), dealt round-robin, each
    share reading every level it reaches; the shares together are the range, point for point."""
    tree, _ = big
    whole = tree.point_range(chunk_size=7_000)
    chunks = list(whole())
    shares = whole.deal(3)
    assert len(shares) == 3 and [len(s) for s in shares] == [len(range(p, len(chunks), 3)) for p in range(3)]
    for p, share in enumerate(shares):
        for piece, chunk in zip(share, chunks[p::3], strict=True):
            (read,) = list(piece())  # one chunk, the one at its place in the whole range's order
            assert len(piece) == len(chunk["positions"])
            for k in chunk:
                np.testing.assert_array_equal(read[k], chunk[k])
    # every share has points of every level of at least 3 chunks (split's thirds would not)
    bounds = np.cumsum([0] + tree.level_counts)
    big_levels = [(a, b) for a, b in zip(bounds, bounds[1:]) if b - a >= 3 * 7_000]
    assert len(big_levels) >= 3
    assert all(any(a <= r.start < b for r in s) for s in shares for a, b in big_levels)
    assert whole.deal(10**9) == [[c] for c in whole.deal(1)[0]]  # at most one share per chunk


# ---------------------------------------------------------------------------------------------
# exactness against the naive reference, on a small cloud with every hard case:
# coarse levels spanning buckets, an over-full bucket, exact distance ties, duplicate points
# ---------------------------------------------------------------------------------------------
def tricky_cloud(seed=3):
    rng = np.random.default_rng(seed)
    parts = [surface_chunk(0, n=20_000, seed=seed)[0]]
    g = np.stack(np.meshgrid(np.arange(40), np.arange(40), indexing="ij"), -1).reshape(-1, 2) * 0.05
    parts.append(np.c_[g + 2.0, np.full(len(g), 0.5)])  # exact grid: many exact distance ties
    parts.append(np.repeat(parts[0][:300], 3, axis=0))  # exact duplicates
    parts.append(rng.normal([15.0, 15.0, 1.0], 1e-4, (4000, 3)))  # a dense cluster: over-full cell
    pos = np.concatenate(parts)
    ids = np.arange(len(pos), dtype=np.int64)
    return pos, ids


def chunked(pos, ids, size, order=None):
    starts = list(range(0, len(pos), size))
    if order is not None:
        starts = [starts[i] for i in order]
    return lambda: ((pos[s:s + size], {"id": ids[s:s + size]}) for s in starts)


def test_matches_naive_reference_out_of_core(tmp_path, monkeypatch):
    pos, ids = tricky_cloud()
    lo, hi = pos.min(0), pos.max(0)
    root = float(np.linalg.norm(hi - lo)) / 3  # huge level-0 cells: coarse levels span many buckets
    cfg = OctreeConfig(levels=9, root_cell=root, memory_limit_mb=0.05)  # ~1000-point buckets
    tree = Octree.build(chunked(pos, ids, 3001), tmp_path / "a", cfg, bbox=(lo, hi), progress=False)
    assert tree.meta["bucket_level"] > 0, "the coarse-candidate path was not exercised"
    assert tree.meta["max_bucket_points"] > tree.meta["bucket_capacity"], "no over-full bucket"
    # the reference on the rounded points, whose box's minimum is the rounded minimum
    r = rounded(pos)
    ref = reference_levels(r.astype(np.float64), r.min(0).astype(np.float64), root, cfg.levels)
    got = ids_per_level(tree)
    for lvl in range(cfg.levels):
        np.testing.assert_array_equal(got[lvl], np.flatnonzero(ref == lvl), err_msg=f"level {lvl}")

    # the same octree in memory (one bucket), with shuffled chunks and without a given bbox
    order = np.random.default_rng(0).permutation(len(range(0, len(pos), 3001)))
    cfg2 = OctreeConfig(levels=9, root_cell=root, memory_limit_mb=512)
    tree2 = Octree.build(chunked(pos, ids, 3001, order), tmp_path / "b", cfg2, progress=False)
    assert tree2.meta["n_buckets"] == 1
    for lvl in range(cfg.levels):
        # compare positions: which of several exact duplicates lands in which level follows the
        # input order, which the shuffle changed
        a, b = r[got[lvl]], tree2.read_level(lvl)["positions"]
        np.testing.assert_array_equal(a[np.lexsort(a.T)], b[np.lexsort(b.T)], err_msg=f"level {lvl}")

    # in the same chunk order, the in-memory build writes the same bytes as the out-of-core one
    # (whose over-full bucket took the streaming path): the level files do not depend on the buckets
    tree3 = Octree.build(chunked(pos, ids, 3001), tmp_path / "c", cfg2, bbox=(lo, hi), progress=False)
    assert_same_files(tree, tree3)
    # and so does it selecting in blocks of a few level-0 cells (~27 cells: the blocks are cells)
    monkeypatch.setattr(octree_module, "SELECT_BLOCK", 257)
    tree4 = Octree.build(chunked(pos, ids, 3001), tmp_path / "e", cfg2, bbox=(lo, hi), progress=False)
    assert_same_files(tree, tree4)


def test_streamed_bucket_whose_first_slice_the_levels_take_whole(tmp_path):
    """An over-full bucket whose first 1100 points (a slice and more) each sit alone in a finest
    cell, so the grid levels take them all, before a dense blob (the remainder): the streamed
    remainder skips the empty slice and writes the in-memory build's bytes."""
    rng = np.random.default_rng(0)
    grid_pts = (np.stack(np.meshgrid(*[np.arange(11)] * 3, indexing="ij"), -1).reshape(-1, 3)[:1100] + 0.5) * 0.09
    blob = 0.5 + rng.normal(0, 0.0005, (5000, 3))
    background = rng.random((20000, 3)) * 16 + [2, 0, 0]  # many cells: the count table coarsens
    pos = np.concatenate([grid_pts, blob, background])
    chunks = [(pos[s:s + 5000], {}) for s in range(0, len(pos), 5000)]
    box = (np.zeros(3), np.full(3, 18.0))
    streamed = Octree.build(chunks, tmp_path / "s", OctreeConfig(levels=8, root_cell=1.0, memory_limit_mb=0.1),
                            bbox=box, progress=False)
    assert streamed.meta["max_bucket_points"] > streamed.meta["bucket_capacity"]
    in_memory = Octree.build(chunks, tmp_path / "m", OctreeConfig(levels=8, root_cell=1.0, memory_limit_mb=512),
                             bbox=box, progress=False)
    assert in_memory.meta["n_buckets"] == 1
    assert_same_files(streamed, in_memory)


def test_default_root_and_single_level(tmp_path):
    pos, ids = tricky_cloud(seed=5)
    tree = Octree.build(chunked(pos, ids, 5000), tmp_path / "d", OctreeConfig(levels=6), progress=False)
    r = rounded(pos).astype(np.float64)
    diag = float(np.linalg.norm(r.max(0) - r.min(0)))  # of the rounded points' box
    assert tree.meta["root_cell"] == diag / 64
    ref = reference_levels(r, r.min(0), diag / 64, 6)
    for lvl, got in enumerate(ids_per_level(tree)):
        np.testing.assert_array_equal(got, np.flatnonzero(ref == lvl))
    # no grid level: the rounded input, in input order
    one = Octree.build(chunked(pos, ids, 5000), tmp_path / "e", OctreeConfig(levels=1), progress=False)
    assert one.level_counts == [len(pos)] and one.subsampling_factors() == [1.0]
    np.testing.assert_array_equal(one.read_level(0)["positions"], rounded(pos))


# ---------------------------------------------------------------------------------------------
# float32 positions: the octree of the input rounded to float32
# ---------------------------------------------------------------------------------------------
def test_levels_hold_the_float32_rounding_of_the_input(tmp_path):
    """The levels hold exactly the input rounded to float32 (as a multiset of rows), and the build
    of float64 input is the build of that input rounded beforehand, byte for byte: every pass
    (bbox, cells, coarse candidates, over-full buckets' streaming) sees the rounded values."""
    pos, ids = tricky_cloud()
    r = rounded(pos)
    assert np.count_nonzero(r != pos) > len(pos)  # rounding moved most coordinates
    root = float(np.linalg.norm(pos.max(0) - pos.min(0))) / 3
    cfg = OctreeConfig(levels=9, root_cell=root, memory_limit_mb=0.05)  # ~1000-point buckets
    f64 = Octree.build(chunked(pos, ids, 3001), tmp_path / "a", cfg, progress=False)
    assert f64.meta["bucket_level"] > 0 and f64.meta["max_bucket_points"] > f64.meta["bucket_capacity"]
    assert f64.fields["positions"] == ("float32", (3,))
    got = f64.read_lod(f64.levels)["positions"]
    assert got.dtype == np.float32
    np.testing.assert_array_equal(got[np.lexsort(got.T)], r[np.lexsort(r.T)])
    assert f64.meta["bbox"] == [r.min(0).astype(np.float64).tolist(), r.max(0).astype(np.float64).tolist()]

    f32 = Octree.build(chunked(r, ids, 3001), tmp_path / "b", cfg, progress=False)
    assert f32.meta["bbox"] == f64.meta["bbox"]
    assert_same_files(f64, f32)


def test_given_bbox_is_rounded_as_the_points(tmp_path):
    """Points on the faces of the exact float64 box of the input, which rounding to float32 moves
    just outside it: the given box is rounded too, so they stay inside, are not counted outside,
    and the octree is the one built without a bbox. A point really outside is still counted."""
    v = 8 * (1 + 2.0 ** -23 - 2.0 ** -30)  # rounds up to 8 (1 + 2**-23), away from the box
    rng = np.random.default_rng(1)
    pos = np.concatenate([rng.uniform(-7, 7, (5000, 3)), [[v, v, v], [-v, -v, -v]]])
    ids = np.arange(len(pos), dtype=np.int64)
    lo, hi = pos.min(0), pos.max(0)
    r = rounded(pos)
    assert np.all(r.max(0) > hi) and np.all(r.min(0) < lo)  # rounded, they leave the given box
    cfg = OctreeConfig(levels=5, memory_limit_mb=0.05)
    given = Octree.build(chunked(pos, ids, 1000), tmp_path / "g", cfg, bbox=(lo, hi), progress=False)
    assert given.meta["points_outside_bbox"] == 0
    np.testing.assert_array_equal(given.bbox[0], r.min(0))
    np.testing.assert_array_equal(given.bbox[1], r.max(0))
    computed = Octree.build(chunked(pos, ids, 1000), tmp_path / "c", cfg, progress=False)
    assert computed.meta["bbox"] == given.meta["bbox"]
    assert_same_files(given, computed)

    box = (lo, hi - 3.0)
    short = Octree.build(chunked(pos, ids, 1000), tmp_path / "s", cfg, bbox=box, progress=False)
    outside = int(np.count_nonzero(np.any(r > rounded(box[1]), axis=1)))
    assert outside > 100 and short.meta["points_outside_bbox"] == outside
    np.testing.assert_array_equal(np.sort(np.concatenate(ids_per_level(short))), ids)


def test_level_files_are_spatially_coherent(big):
    """Level files are written in Morton order (per bucket, and buckets in Morton order), which lets
    later stages stream a level as spatially compact chunks."""
    tree, _ = big
    lvl = 4
    p = tree.read_level(lvl)["positions"]
    finest = tree.levels - 2
    q = np.floor((p - tree.bbox[0]) / (tree.meta["root_cell"] / 2.0 ** finest)).astype(np.int64)
    k = morton_encode(q >> (finest - lvl))
    assert np.all(np.diff(k) > 0)


# ---------------------------------------------------------------------------------------------
# robustness
# ---------------------------------------------------------------------------------------------
def test_interrupted_build_leaves_nothing(tmp_path):
    pos, ids = tricky_cloud()
    calls = {"n": 0}

    def chunks_fn():
        calls["n"] += 1
        this_call = calls["n"]
        for k, s in enumerate(range(0, len(pos), 2000)):
            if this_call == 4 and k == 4:  # 4th call (schema, bbox, count, distribute): mid-way
                raise KeyboardInterrupt("simulated interruption")
            yield pos[s:s + 2000], {"id": ids[s:s + 2000]}

    with pytest.raises(KeyboardInterrupt):
        Octree.build(chunks_fn, tmp_path / "oct", OctreeConfig(levels=6, memory_limit_mb=0.05), progress=False)
    assert calls["n"] == 4
    assert not (tmp_path / "oct").exists()
    assert os.listdir(tmp_path) == []  # no temporary folder left behind either
    with pytest.raises(InputError, match="octree.json"):
        Octree.open(tmp_path)


def test_replaces_old_octree_but_not_foreign_folders(tmp_path):
    pos, ids = tricky_cloud()
    out = tmp_path / "oct"
    Octree.build(chunked(pos[:5000], ids[:5000], 1000), out, OctreeConfig(levels=4), progress=False)
    t = Octree.build(chunked(pos, ids, 7000), out, OctreeConfig(levels=5), progress=False)
    assert Octree.open(out).level_counts == t.level_counts and t.n_points == len(pos)
    assert sorted(os.listdir(tmp_path)) == ["oct"]
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("keep")
    with pytest.raises(InputError, match="not an octree"):
        Octree.build(chunked(pos, ids, 7000), foreign, OctreeConfig(levels=4), progress=False)
    assert (foreign / "notes.txt").read_text() == "keep"


def test_open_rejects_bad_metadata(tmp_path):
    pos, ids = tricky_cloud()
    t = Octree.build(chunked(pos, ids, 7000), tmp_path / "o", OctreeConfig(levels=4), progress=False)
    meta = json.loads((t.path / "octree.json").read_text())
    assert meta["version"] == 2 and meta["fields"]["positions"] == {"dtype": "float32", "shape": [3]}
    for old in (99, 1):  # 1: an octree of float64 positions
        meta["version"] = old
        (t.path / "octree.json").write_text(json.dumps(meta))
        with pytest.raises(InputError, match=f"field 'version' is {old}, this reader knows 2"):
            Octree.open(t.path)
    meta["version"] = 2
    meta["level_counts"][0] += 1
    (t.path / "octree.json").write_text(json.dumps(meta))
    with pytest.raises(InputError, match="level_counts"):
        Octree.open(t.path)


def test_inconsistent_chunks_are_rejected(tmp_path):
    pos, ids = tricky_cloud()

    def bad():
        yield pos[:100], {"id": ids[:100]}
        yield pos[100:200], {"id": ids[100:200].astype(np.int32)}

    with pytest.raises(ValueError, match="differ"):
        Octree.build(bad, tmp_path / "x", OctreeConfig(levels=4), progress=False)
    assert not (tmp_path / "x").exists()
    with pytest.raises(TypeError, match="callable"):
        Octree.build(iter([(pos, {})]), tmp_path / "y", OctreeConfig(levels=4), progress=False)


@pytest.mark.filterwarnings("ignore:overflow encountered in cast")  # 1e39 to float32, on purpose
@pytest.mark.parametrize("bad", [np.nan, np.inf, -np.inf, 1e39])  # 1e39: beyond float32, inf once rounded
def test_non_finite_coordinates_are_rejected(tmp_path, bad):
    pos, ids = tricky_cloud()
    pos = pos.copy()
    pos[150, 1] = bad
    box = (np.zeros(3), np.full(3, 100.0))  # a given box: the count pass is the first to see the points
    with pytest.raises(ValueError, match="non-finite"):
        Octree.build(chunked(pos, ids, 100), tmp_path / "x", OctreeConfig(levels=4), bbox=box, progress=False)


def test_memory_stays_near_the_limit(tmp_path):
    """Python-heap peak (numpy buffers are traced) of a build of a 600k-point cloud (19 MB of data)
    under a 4 MB limit. The chunk generator's own ~1 MB peak is included; allow 2x for slack."""
    n, ch, limit = 600_000, 10_000, 4
    chunks = lambda: (surface_chunk(i, n=ch, seed=11)[0:1] + ({"id": np.arange(i * ch, (i + 1) * ch)},)
                      for i in range(n // ch))
    tracemalloc.start()
    try:
        tracemalloc.reset_peak()
        tree = Octree.build(chunks, tmp_path / "m", OctreeConfig(levels=8, memory_limit_mb=limit),
                            progress=False)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert tree.n_points == n
    assert tree.meta["n_buckets"] > 10
    assert peak < 2 * limit * 2 ** 20, f"peak {peak / 2**20:.1f} MB for a {limit} MB limit"


# ---------------------------------------------------------------------------------------------
# the bucket passes in worker processes
# ---------------------------------------------------------------------------------------------
def parallel_cloud(seed=13):
    """~212k points: the surface scene, a cluster inside one finest cell and a dense blob over
    several (over-full buckets, whose remainder runs are one cell and several cells), an exact grid
    (distance ties) and exact duplicates."""
    rng = np.random.default_rng(seed)
    parts = [surface_chunk(i, seed=seed)[0] for i in range(4)]
    parts.append(rng.normal([15.0, 15.0, 1.0], 1e-4, (3000, 3)))
    parts.append(rng.normal([4.0, 16.0, 2.0], 0.1, (6000, 3)))
    g = np.stack(np.meshgrid(np.arange(40), np.arange(40), indexing="ij"), -1).reshape(-1, 2) * 0.05
    parts.append(np.c_[g + 2.0, np.full(len(g), 0.5)])
    parts.append(np.repeat(parts[0][:500], 2, axis=0))
    pos = np.concatenate(parts)
    return pos, np.arange(len(pos), dtype=np.int64)


@pytest.fixture(scope="module")
def pool():
    p = ProcessPool(2)
    yield p
    p.close()


def test_process_pool_build_is_byte_identical(tmp_path, pool):
    """Candidates and select as tasks in 2 spawned processes (each with half the buckets'
    capacity, so other buckets): the same level files as the serial build, byte for byte."""
    pos, ids = parallel_cloud()
    lo, hi = pos.min(0), pos.max(0)
    root = float(np.linalg.norm(hi - lo)) / 3  # coarse levels span buckets: candidates run as tasks
    cfg = OctreeConfig(levels=8, root_cell=root, memory_limit_mb=1.5)
    serial = Octree.build(chunked(pos, ids, 20_000), tmp_path / "s", cfg, bbox=(lo, hi), progress=False)
    par = Octree.build(chunked(pos, ids, 20_000), tmp_path / "p", cfg, bbox=(lo, hi), progress=False,
                       executor=pool)
    for t, workers in ((serial, 1), (par, 2)):
        m = t.meta
        assert m["workers"] == workers
        assert m["bucket_level"] > 0 and m["n_buckets"] > 20
        assert m["max_bucket_points"] > m["bucket_capacity"], "no over-full bucket: streaming path not run"
    assert par.meta["bucket_capacity"] < serial.meta["bucket_capacity"]  # the budget split over 2 workers
    assert_same_files(serial, par)
    assert not (tmp_path / "p.partial").exists()
    assert sorted(os.listdir(par.path)) == sorted(os.listdir(serial.path))  # no spill or select folders left
    # an in-process executor is the serial path
    again = Octree.build(chunked(pos, ids, 20_000), tmp_path / "i", cfg, bbox=(lo, hi), progress=False,
                         executor=InProcess())
    assert again.meta["workers"] == 1 and again.meta["n_buckets"] == serial.meta["n_buckets"]
    assert_same_files(serial, again)


# ---------------------------------------------------------------------------------------------
# the input passes (bbox, count, distribute) in worker processes, over parts of a split source
# ---------------------------------------------------------------------------------------------
@dataclasses.dataclass
class SplitChunks:
    """A splittable, picklable chunk source over arrays: chunks ``[start, stop)`` of ``size`` points
    each, ``(positions, {"id", "colors"})``; :meth:`split` cuts the chunks into consecutive ranges as
    :class:`~dmrt.io.pointcloud.PointRange` cuts records. ``bad_chunk``: that chunk's ids come as
    int32 (a schema mismatch); ``whole``: :meth:`split` returns ``[self]`` (an input that cannot
    seek)."""

    pos: np.ndarray
    ids: np.ndarray
    size: int
    start: int = 0
    stop: int | None = None
    bad_chunk: int = -1
    whole: bool = False

    def __call__(self):
        stop = -(-len(self.pos) // self.size) if self.stop is None else self.stop
        for c in range(self.start, stop):
            ids = self.ids[c * self.size:(c + 1) * self.size]
            yield (self.pos[c * self.size:(c + 1) * self.size],
                   {"id": ids.astype(np.int32) if c == self.bad_chunk else ids, "colors": color_of(ids)})

    def split(self, parts: int) -> list["SplitChunks"]:
        stop = -(-len(self.pos) // self.size) if self.stop is None else self.stop
        parts = max(1, min(parts, stop - self.start))
        if self.whole or parts == 1:
            return [self]
        cuts = [self.start + (stop - self.start) * i // parts for i in range(parts + 1)]
        return [dataclasses.replace(self, start=a, stop=b) for a, b in zip(cuts, cuts[1:])]


def test_split_ply_input_in_workers_is_byte_identical(tmp_path, pool):
    """A binary PLY read through point_range in 2 parts: bbox, count and distribute run as tasks (each
    part spills to its own files per bucket); the level files are the serial build's, byte for byte,
    over-full buckets (streaming path) included."""
    pos, ids = parallel_cloud()
    ply = tmp_path / "cloud.ply"
    with PointWriter(ply, normals=False, colors=True) as w:
        w.write(PointCloud(pos, colors=color_of(ids)))
    src = point_range(ply, 20_000)
    lo, hi = pos.min(0), pos.max(0)
    root = float(np.linalg.norm(hi - lo)) / 3
    cfg = OctreeConfig(levels=8, root_cell=root, memory_limit_mb=1.5)
    serial = Octree.build(src, tmp_path / "s", cfg, bbox=(lo, hi), progress=False)
    par = Octree.build(src, tmp_path / "p", cfg, progress=False, executor=pool)  # bbox in the workers too
    assert serial.meta["input_parts"] == 1 and par.meta["input_parts"] == 2
    r = rounded(pos).astype(np.float64)  # the given box, rounded = the box of the rounded points
    assert serial.meta["bbox"] == par.meta["bbox"] == [r.min(0).tolist(), r.max(0).tolist()]
    for t in (serial, par):
        assert t.meta["max_bucket_points"] > t.meta["bucket_capacity"], "no over-full bucket: streaming path not run"
        assert t.meta["points_outside_bbox"] == 0
    assert_same_files(serial, par)
    assert sorted(os.listdir(par.path)) == sorted(os.listdir(serial.path))  # no spill folders left
    assert not (tmp_path / "p.partial").exists()


def test_split_input_outside_bbox_one_part_and_errors(tmp_path, pool):
    pos, ids = tricky_cloud()
    lo, hi = pos.min(0), pos.max(0)
    root = float(np.linalg.norm(hi - lo)) / 3
    cfg = OctreeConfig(levels=9, root_cell=root, memory_limit_mb=0.05)  # ~1000-point buckets, over-full ones
    # a given bbox that leaves points out: they are clipped into the boundary cells and counted
    box = (lo, hi - [2.0, 2.0, 0.5])
    src = SplitChunks(pos, ids, 3001)
    serial = Octree.build(src, tmp_path / "s", cfg, bbox=box, progress=False)
    par = Octree.build(src, tmp_path / "p", cfg, bbox=box, progress=False, executor=pool)
    assert par.meta["input_parts"] == 2
    outside = int(np.count_nonzero(np.any(rounded(pos) > rounded(box[1]), axis=1)))
    assert outside > 0 and serial.meta["points_outside_bbox"] == par.meta["points_outside_bbox"] == outside
    assert par.meta["max_bucket_points"] > par.meta["bucket_capacity"]
    assert_same_files(serial, par)
    np.testing.assert_array_equal(np.sort(np.concatenate(ids_per_level(par))), ids)

    # a source whose split returns one part is read here, as without split
    one = Octree.build(dataclasses.replace(src, whole=True), tmp_path / "o", cfg, bbox=box, progress=False,
                       executor=pool)
    assert one.meta["input_parts"] == 1 and one.meta["workers"] == 2
    assert_same_files(serial, one)

    # a schema mismatch in the second part, found by a task, reaches the caller; nothing is left
    bad = dataclasses.replace(src, bad_chunk=7)
    with pytest.raises(ValueError, match="input part 2 of 2, chunk 3: attributes .* differ"):
        Octree.build(bad, tmp_path / "x", cfg, bbox=box, progress=False, executor=pool)
    assert not (tmp_path / "x").exists() and not (tmp_path / "x.partial").exists()


# ---------------------------------------------------------------------------------------------
# the select's helpers against plain numpy twins
# ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("span", [1 << 20, 1 << 61])  # packed into one int64 / too wide: argsort
def test_stable_order_is_a_stable_argsort(span):
    keys = np.random.default_rng(1).integers(0, 50, 5000) * (span // 50) + 7  # many equal keys
    o, srt = _stable_order(keys)
    np.testing.assert_array_equal(o, np.argsort(keys, kind="stable"))
    np.testing.assert_array_equal(srt, keys[o])


@pytest.mark.parametrize("spread", ["repeat", "run index"])
def test_best_of_runs_matches_a_per_run_loop(spread):
    """Exact distance ties (resolved by x, y, z, then index), runs of taken points (d2 = inf); the
    runs' values spread by np.repeat (long runs) and by a gather through each point's run index
    (short runs)."""
    rng = np.random.default_rng(2)
    n = 3000
    cols = [rng.integers(0, 3, n).astype(np.float32) for _ in range(3)]  # few values: position ties
    d2 = rng.integers(0, 4, n).astype(np.float64)  # few values: distance ties
    d2[rng.random(n) < 0.3] = np.inf
    start = np.r_[0, np.sort(rng.choice(np.arange(1, n), 900, replace=False))]
    want = []
    for a, b in zip(start, np.r_[start[1:], n]):
        i = np.arange(a, b)[np.isfinite(d2[a:b])]
        if len(i):
            want.append(i[np.lexsort((i, cols[2][i], cols[1][i], cols[0][i], d2[i]))[0]])
    assert len(want) < len(start), "no run of taken points"
    breaks = np.zeros(n - 1, bool)
    breaks[start[1:] - 1] = True
    runs = _Runs.from_breaks(breaks)
    assert runs.rid is not None  # 900 runs of 3000 points: short runs, spread through the run index
    np.testing.assert_array_equal(runs.start, start)
    if spread == "repeat":
        runs.rid = None
    else:
        np.testing.assert_array_equal(runs.rid, np.repeat(np.arange(len(start)), np.diff(np.r_[start, n])))
    np.testing.assert_array_equal(_best_of_runs(runs, d2, cols), want)


def test_cell_columns_and_keys_equal_coords_and_morton_encode():
    rng = np.random.default_rng(4)
    g = _Grid(np.array([-3.1, 0.7, 12.9]), 0.37, 8, 14)  # 14 + 7 = 21 bits a coordinate: every table bit
    pos = (rng.random((5000, 3)) * 0.37 * 2 ** 14 * 1.1 + g.origin - 1).astype(np.float32)  # some clipped
    q = g.coords(pos)
    qc = g.coord_columns(pos)
    assert all(a.dtype == np.int32 for a in qc)
    np.testing.assert_array_equal(np.stack(qc, 1), q)
    assert q.min() == 0 and q.max() == 2 ** 21 - 1
    np.testing.assert_array_equal(morton_columns(qc), morton_encode(q))


def test_run_distances_equal_the_formula_bit_for_bit():
    rng = np.random.default_rng(3)
    g = _Grid(np.array([-3.1, 0.7, 12.9]), 0.37, 6, 5)
    pos = (rng.random((4000, 3)) * 11.8 + g.origin).astype(np.float32)
    pos = pos[np.argsort(morton_encode(g.coords(pos)), kind="stable")]  # cells of every level: runs
    q = g.coords(pos)
    kf = morton_encode(q)
    for lvl in range(g.n_grid):
        shift = g.finest - lvl
        ql = q >> shift
        want = g.d2(pos[:, 0], pos[:, 1], pos[:, 2], ql[:, 0], ql[:, 1], ql[:, 2], lvl)
        breaks = (kf[1:] >> 3 * shift) != (kf[:-1] >> 3 * shift)
        runs = _Runs.from_breaks(breaks)
        for rid in (np.cumsum(np.r_[0, breaks]), None):  # both spreads, whichever the run lengths chose
            runs.rid = rid
            got = g.d2_runs([pos[:, j].copy() for j in range(3)], [q[:, j].astype(np.int32) for j in range(3)],
                            runs, shift, lvl)
            assert got.tobytes() == want.tobytes(), f"level {lvl}"


@pytest.mark.parametrize("size", [1, 7, 100, 10_000])
def test_block_cuts_are_the_first_run_starts_past_each_multiple(size):
    rng = np.random.default_rng(5)
    breaks = rng.random(999) < 0.05  # 1000 points in runs of ~20
    cuts = _block_cuts(breaks, size)
    start = [0] + [i + 1 for i in np.flatnonzero(breaks)]
    want = [0]
    for m in range(size, 1000, size):
        nxt = [s for s in start if s >= m]
        if nxt and nxt[0] > want[-1]:
            want.append(nxt[0])
    want.append(1000)
    np.testing.assert_array_equal(cuts, want)
