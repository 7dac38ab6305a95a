"""Out-of-core buckets (dmrt.preprocess.buckets, dmrt.preprocess.spill) against plain-numpy twins:
partition, halos, spill round trips and count merging."""

from __future__ import annotations

import numpy as np
import pytest

from dmrt.morton import morton_encode
from dmrt.preprocess.buckets import (Buckets, CellCounts, FineGrid, InputPart, coarsen, count_input, distribute,
                                     halo_schema, in_sorted, merge_counts, unique_counts)
from dmrt.preprocess.parallel import InProcess
from dmrt.preprocess import spill as spill_module
from dmrt.preprocess.spill import Spill


def clustered(n, seed=0):
    """(n, 3) float64 points: dense blobs on a sparse background (uneven cells, uneven buckets)."""
    rng = np.random.default_rng(seed)
    centres = rng.random((5, 3)) * 8
    blobs = centres[rng.integers(0, 5, n // 2)] + rng.normal(0, 0.3, (n // 2, 3))
    return np.concatenate([blobs, rng.random((n - n // 2, 3)) * 10])


def parts_of(p, cuts, attrs=None):
    """The input ``p`` cut at ``cuts`` into consecutive parts, each a source of 2 chunks."""
    out = []
    for i, (a, b) in enumerate(zip(cuts, cuts[1:])):
        def src(a=a, b=b):
            for s, e in ((a, (a + b) // 2), ((a + b) // 2, b)):
                yield p[s:e], {k: v[s:e] for k, v in (attrs or {}).items()}
        out.append(InputPart(i, len(cuts) - 1, src))
    return out


def partition(p, shift, capacity, halos=False):
    """Buckets of ``p`` at ``shift`` doublings of a fine grid over its box, cut at ``capacity``."""
    lo, hi = p.min(0), p.max(0)
    grid = FineGrid(lo, float(np.max(hi - lo)) / ((1 << 20) - 1))
    q = grid.coords(p) >> shift
    keys, counts = unique_counts(morton_encode(q))
    return Buckets.cut(grid, shift, keys, counts, capacity, halos=halos), q


def test_each_point_lands_in_exactly_one_bucket_whose_cell_range_holds_it(tmp_path):
    p = clustered(6000)
    buckets, q = partition(p, shift=16, capacity=400)
    assert 10 < len(buckets) < len(p)
    idx = np.arange(len(p))
    spill = Spill(str(tmp_path / "spill"), {"positions": ("float64", (3,)), "idx": ("int64", ())}, parts=3)
    spill.create(len(buckets))
    written = 0
    for part in parts_of(p, [0, 1000, 3500, len(p)], {"idx": idx}):
        # a small buffer: many flushes, each bucket's file appended to many times
        n, per_bucket = distribute(part, buckets, spill, 300, 4096, schema=spill.schema)
        written += per_bucket
    seen = np.zeros(len(p), np.int64)
    keys = morton_encode(q)
    ends = np.r_[buckets.starts[1:], np.iinfo(np.int64).max]
    for b in range(len(buckets)):
        rec = spill.read(b)
        seen[rec["idx"]] += 1
        assert np.all(np.diff(rec["idx"]) > 0)  # input order, across the parts
        np.testing.assert_array_equal(rec["positions"], p[rec["idx"]])
        k = keys[rec["idx"]]
        assert np.all((buckets.starts[b] <= k) & (k < ends[b]))  # its cell range holds it
        # a bucket over the capacity is a single cell
        assert len(rec["idx"]) == buckets.counts[b] == written[b]
        assert buckets.counts[b] <= 400 or len(np.unique(k)) == 1
    np.testing.assert_array_equal(seen, 1)
    # the twin: a point's bucket is the last whose first key is <= its key
    twin = (keys[:, None] >= buckets.starts[None, :]).sum(1) - 1
    np.testing.assert_array_equal(buckets.of(p), twin)


def test_a_halo_holds_exactly_the_points_whose_margin_box_overlaps_an_occupied_cell(tmp_path):
    p = clustered(3000, seed=1)
    margin = 0.3
    buckets, q = partition(p, shift=17, capacity=200, halos=True)
    cell = buckets.grid.cell * 2.0 ** buckets.shift
    assert cell > 2 * margin and len(buckets) > 5
    spill = Spill(str(tmp_path / "spill"), halo_schema("float64"), parts=2)
    spill.create(len(buckets))
    firsts = [0, 1700]
    for part in parts_of(p, [0, 1700, len(p)]):
        n, _ = distribute(part, buckets, spill, 500, 1 << 16, margin=margin, firsts=firsts)
        assert n == [1700, 1300][part.index]
    # the twin, geometrically: the box [p - m, p + m] overlaps the occupied cell [lo + Q c, lo + (Q+1) c)
    own = buckets.of(p)
    cells, first = np.unique(q, axis=0, return_index=True)
    cell_bucket = own[first]
    lo_c = buckets.grid.lo + cells * cell
    overlap = np.all((p[:, None, :] + margin >= lo_c[None]) & (p[:, None, :] - margin < lo_c[None] + cell), axis=2)
    # every point within the margin (per axis) of a bucket's own point is there, core or halo
    near = np.all(np.abs(p[:, None, :] - p[None, :, :]) <= margin, axis=2)
    halos = 0
    for b in range(len(buckets)):
        rec = spill.read(b)
        core = rec["core"].astype(bool)
        np.testing.assert_array_equal(rec["gidx"][core], np.flatnonzero(own == b))
        halo = np.flatnonzero(overlap[:, cell_bucket == b].any(1) & (own != b))
        np.testing.assert_array_equal(np.sort(rec["gidx"][~core]), halo)
        np.testing.assert_array_equal(rec["positions"], p[rec["gidx"]])
        assert set(np.flatnonzero(near[own == b].any(0))) <= set(rec["gidx"].tolist())
        halos += len(halo)
    assert halos > 100


@pytest.mark.parametrize("runs", [False, True])  # buckets at random (sorted first) / in runs (buffered as they come)
@pytest.mark.parametrize("buffer_bytes", [1, 1 << 20])
def test_spill_files_round_trip_their_records(tmp_path, buffer_bytes, runs, monkeypatch):
    rng = np.random.default_rng(2)
    monkeypatch.setattr(spill_module, "RUN_POINTS", 4)  # runs of 10 points average more
    schema = {"positions": ("float32", (3,)), "id": ("int64", ()), "rgb": ("uint8", (3,))}
    spill = Spill(str(tmp_path / "s"), schema, parts=2)
    nb = 7
    spill.create(nb)
    parts = []  # per part: (bucket, records) of each add
    for part in range(2):
        w = spill.writer(part, nb, buffer_bytes)
        adds = []
        for _ in range(4):
            m = int(rng.integers(0, 50))
            rec = {"positions": rng.random((m, 3)).astype(np.float32), "id": rng.integers(0, 1 << 40, m),
                   "rgb": rng.integers(0, 256, (m, 3)).astype(np.uint8), "extra": np.zeros(m)}
            bucket = rng.integers(0, nb - 1, m)  # unsorted; the last bucket stays empty
            if runs:
                bucket = np.repeat(bucket, 10)[:m]
            w.add(bucket, rec)
            adds.append((bucket, rec))
        counts = w.close()
        np.testing.assert_array_equal(counts, np.bincount(np.concatenate([b for b, _ in adds]), minlength=nb))
        parts.append(adds)
    for b in range(nb):
        # the twin: each part's records of bucket b in the order added, part after part
        want = {k: np.concatenate([r[k][bk == b] for adds in parts for bk, r in adds]) for k in schema}
        got = spill.read(b)
        assert set(got) == set(schema)
        for k in schema:
            assert got[k].dtype == np.dtype(schema[k][0])
            np.testing.assert_array_equal(got[k], want[k])
        n = len(want["id"])
        for start, stop in ((0, n), (n // 3, n - 2), (n, n + 5)):  # ranges across the parts' files
            sub = spill.read(b, start, stop, {"id": schema["id"], "positions": schema["positions"]})
            np.testing.assert_array_equal(sub["id"], want["id"][start:stop])
    spill.remove(0)
    assert len(spill.read(0)["id"]) == 0


def test_count_merging_equals_np_unique_of_the_concatenation():
    rng = np.random.default_rng(3)
    tables = [np.sort(rng.integers(0, 500, int(rng.integers(0, 300)))) for _ in range(5)]
    k, c = np.zeros(0, np.int64), np.zeros(0, np.int64)
    for t in tables:
        k, c = merge_counts(k, c, t, np.ones(len(t), np.int64))  # repeated keys within a table too
    wk, wc = np.unique(np.concatenate(tables), return_counts=True)
    np.testing.assert_array_equal(k, wk)
    np.testing.assert_array_equal(c, wc)
    np.testing.assert_array_equal(unique_counts(tables[0])[1], np.unique(tables[0], return_counts=True)[1])
    ck, cc = coarsen(k, c, 2)
    np.testing.assert_array_equal(ck, np.unique(np.concatenate(tables) >> 6))
    assert cc.sum() == c.sum()
    a = rng.integers(0, 600, 100)
    np.testing.assert_array_equal(in_sorted(a, wk), np.isin(a, wk))


@pytest.mark.parametrize("cuts", [[0, 9000], [0, 300, 4000, 9000], [0, 1, 2, 8500, 9000]])
def test_cell_counts_of_parts_add_up_to_the_table_of_all_points(cuts):
    """Parts counted alone, each against the whole cap, stop at different shifts; their tables
    added give the np.unique table of all points at the finest shift that fits the cap."""
    p = clustered(9000, seed=4)
    grid = FineGrid(p.min(0), float(np.ptp(p, axis=0).max()) / ((1 << 20) - 1))
    cap = 300
    # several parts run through the executor's imap, as tasks would (here, in this process)
    counts, part_n, _ = count_input(parts_of(p, cuts), InProcess(), grid, cap, slice_points=700)
    assert part_n == np.diff(cuts).tolist()
    q = grid.coords(p)
    shift = next(s for s in range(22) if len(np.unique(morton_encode(q >> s))) <= cap)
    assert counts.shift == shift > 0
    wk, wc = np.unique(morton_encode(q >> shift), return_counts=True)
    np.testing.assert_array_equal(counts.keys, wk)
    np.testing.assert_array_equal(counts.counts, wc)
    # the same, adding the parts' tables in reverse order
    tables = [count_input([part], None, grid, cap, 700)[0] for part in parts_of(p, cuts)]
    rev = CellCounts(cap)
    for t in tables[::-1]:
        rev.add(t.keys, t.counts, t.shift)
    assert rev.shift == shift
    np.testing.assert_array_equal(rev.keys, wk)
