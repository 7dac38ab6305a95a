"""Table 3's labeling times: DMT's graph cuts in a process pool, the budgeted subset and its
extrapolation, DMRT's labeling run again, and the Table 3 rows of the report.

* The pool's labels equal one process's bit for bit (real PyMaxflow in real spawned processes).
* The subset and extrapolation arithmetic against numbers worked out by hand.
* DMRT's labeling, run again from the bundle, gives the labels preprocessing stored.
* The report's Table 3 rows (CPU and wall ratios, the "extrapolated" note) from a result whose
  numbers are known.

The ``tiny`` bundle (12 photos, 256-wide depth maps) is copied once for this module: DMT writes its
label caches into the bundle.
"""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from dmrt.errors import ConfigError

WIDTH = 64  # DMT width: graph cuts of 12 maps of 64x43 take a second


@pytest.fixture(scope="module")
def bundle(tiny_bundle, tmp_path_factory):
    from dmrt.io.bundle import read_bundle

    dst = tmp_path_factory.mktemp("table3") / "tiny"
    shutil.copytree(tiny_bundle, dst)
    return read_bundle(dst)


@pytest.fixture(scope="module")
def serial(bundle):
    """Graph-cut labels and meta of every map at WIDTH, one process."""
    from baselines.dmt.labeling import DMTLabelingConfig, dmt_labels

    return dmt_labels(bundle, WIDTH, DMTLabelingConfig(workers=1), progress=False, recompute=True)


# ---------------------------------------------------------------------------------------------
# the pool
# ---------------------------------------------------------------------------------------------
def test_pool_labels_equal_serial_labels(bundle, serial):
    """Two spawned processes label the maps exactly as one process does; each map's CPU seconds are
    the process's own and their sum is the recorded total; a subset through a pool gives those
    maps' labels, in the order asked."""
    from baselines.dmt.labeling import DMTLabelingConfig, dmt_labels, label_maps
    from dmrt.preprocess.parallel import open_executor

    labels, meta = serial
    par, pmeta = dmt_labels(bundle, WIDTH, DMTLabelingConfig(workers=2), progress=False, recompute=True)
    assert meta["workers"] == 1 and pmeta["workers"] == 2
    assert len(par) == len(labels) == len(bundle.cameras)
    for a, b in zip(labels, par):
        assert a.dtype == b.dtype == np.int32
        np.testing.assert_array_equal(a, b)
    assert pmeta["energy"] == meta["energy"] and pmeta["counts"] == meta["counts"]
    for m in meta, pmeta:
        cpu = [s["cpu_s"] for s in m["maps"]]
        assert all(c > 0 for c, s in zip(cpu, m["maps"]) if s["texels"])
        assert m["timings"]["cpu_s"] == pytest.approx(sum(cpu), abs=2e-3)  # rounded to ms

    maps = [7, 2, 11]
    with open_executor(None, workers=2) as executor:
        got = label_maps(bundle, WIDTH, maps, DMTLabelingConfig(), executor)
    for i, (lab, stats) in zip(maps, got):
        np.testing.assert_array_equal(lab, labels[i])
        assert stats["texels"] == meta["maps"][i]["texels"]


def test_bad_worker_counts_are_refused():
    from baselines.dmt.labeling import DMTLabelingConfig
    from bench.experiments import Table3Params, Walk

    with pytest.raises(ConfigError, match="--workers: must be >= 1"):
        DMTLabelingConfig(workers=0)
    walk = Walk((64, 48), 2, 2, 0)
    with pytest.raises(ConfigError, match="--dmt-budget-s: must be >= 0"):
        Table3Params((64,), walk, dmt_budget_s=-1.0)
    with pytest.raises(ConfigError, match="--dmt-workers: must be >= 1"):
        Table3Params((64,), walk, dmt_workers=0)
    with pytest.raises(ConfigError, match="--labeler"):
        Table3Params((64,), walk, labeler="icm")


# ---------------------------------------------------------------------------------------------
# subset and extrapolation arithmetic
# ---------------------------------------------------------------------------------------------
def test_labeling_record_arithmetic():
    """4 maps of 1, 2, 3, 4 CPU s in 5 s wall, of 20 maps: parallelism 10 / 5 = 2, mean 2.5 s,
    extrapolated 2.5 x 20 = 50 CPU s and 50 / 2 = 25 s wall; numpy's linear percentiles of
    1..4: p10 = 1 + 0.3 x 1 = 1.3, p90 = 3 + 0.7 x 1 = 3.7. Every map: the measured numbers."""
    from bench.bench_dmt import labeling_record

    r = labeling_record([1.0, 2.0, 3.0, 4.0], 5.0, 20)
    assert r["maps"] == 4 and r["maps_total"] == 20 and r["extrapolated"] is True
    assert r["cpu_s"] == 10.0 and r["wall_s"] == 5.0 and r["parallelism"] == 2.0
    assert r["cpu_s_per_map"] == pytest.approx({"mean": 2.5, "median": 2.5, "p10": 1.3, "p90": 3.7})
    assert r["cpu_s_all"] == 50.0 and r["wall_s_all"] == 25.0

    r = labeling_record([1.0, 2.0, 3.0], 2.0, 3)
    assert r["extrapolated"] is False and r["cpu_s_all"] == 6.0 and r["wall_s_all"] == 2.0
    with pytest.raises(ValueError, match="at least one"):
        labeling_record([], 1.0, 3)


def test_subset_size_fits_the_budget():
    """Probe: 2 maps of 4 CPU s in 4 s wall (parallelism 2, 2 s wall a map from now on)."""
    from bench.bench_dmt import subset_size

    probe = [4.0, 4.0]
    assert subset_size(probe, 4.0, 10, 100.0) == 10    # all 10: 20 s <= the 96 s left
    assert subset_size(probe, 4.0, 100, 44.0) == 22    # 200 s > 40 s left: 2 + 40 / 2
    assert subset_size(probe, 4.0, 21, 44.0) == 21     # 42 s > 40 s, but 20 fit: the last 1 < a round of 2
    assert subset_size(probe, 4.0, 30, 44.0) == 22     # 8 left out >= a round of 2: fewer than all
    assert subset_size(probe, 4.0, 100, 1.0) == 2      # the probe spent the budget
    assert subset_size([0.0, 0.0], 1.0, 50, 0.0) == 50  # empty maps cost nothing


def test_budgeted_labeling_labels_a_seeded_subset(bundle, serial):
    """A budget of 0 s: only the probe (one map per process) is labelled, the maps of the seed's
    permutation, and extrapolated from their CPU seconds; a generous budget labels every map
    (labels equal the serial ones) without extrapolating."""
    from bench.bench_dmt import time_graphcut

    labels, rec = time_graphcut(bundle, WIDTH, workers=2, budget_s=0.0, seed=5, progress=False)
    assert labels is None
    n = len(bundle.cameras)
    assert rec["subset"] == sorted(np.random.default_rng(5).permutation(n)[:2].tolist())
    assert rec["maps"] == rec["probe_maps"] == 2 and rec["maps_total"] == n and rec["extrapolated"]
    assert rec["texels"] == sum(serial[1]["maps"][i]["texels"] for i in rec["subset"])
    assert rec["cpu_s_all"] == pytest.approx(rec["cpu_s"] / 2 * n)
    assert rec["wall_s_all"] == pytest.approx(rec["cpu_s_all"] * rec["wall_s"] / rec["cpu_s"])

    labels, rec = time_graphcut(bundle, WIDTH, workers=2, budget_s=600.0, progress=False)
    assert not rec["extrapolated"] and rec["maps"] == n and rec["probe_maps"] == 2 and rec["subset"] is None
    for a, b in zip(labels, serial[0]):
        np.testing.assert_array_equal(a, b)


def test_dmrt_labeling_run_again_is_preprocessings(bundle):
    """DMRT's candidates + graph cut, run again in a fresh process from the bundle, label every proxy
    as preprocessing did; wall and CPU seconds are each step's sum."""
    from bench.bench_dmt import dmrt_labeling

    r = dmrt_labeling(bundle.root)
    assert r["labels_equal_bundle"] == 1.0 and r["proxies"] == len(bundle.proxy["labels"])
    assert r["cpu_s"] > 0 and r["wall_s"] > 0
    assert r["cpu_s"] == pytest.approx(r["candidates_cpu_s"] + r["labeling_cpu_s"])
    assert r["wall_s"] == pytest.approx(r["candidates_wall_s"] + r["labeling_wall_s"])


# ---------------------------------------------------------------------------------------------
# the report's Table 3
# ---------------------------------------------------------------------------------------------
def _dmt_entry(width, size, labeling, ratio, fps, render_labeler="graphcut"):
    return {"width": width, "size": size, "labeling": labeling, "labeling_ratio_dmt_over_dmrt": ratio,
            "render_labeler": render_labeler, "fps_min_avg_max": fps, "fps_per_frame": [fps[1]] * 3}


def test_table3_rows_show_cpu_and_wall_ratios_and_the_extrapolation():
    from bench.bench_dmt import labeling_record
    from bench.report import fmt, table3_rows

    dmrt_lab = {"wall_s": 4.0, "cpu_s": 2.0, "proxies": 1000, "labels_equal_bundle": 1.0}
    whole = {"labeler": "graphcut", **labeling_record([1.0, 3.0], 2.0, 2), "workers": 2, "seed": 0}
    part = {"labeler": "graphcut", **labeling_record([1.0, 2.0, 3.0, 4.0], 5.0, 20), "workers": 2, "seed": 7}
    d = {"labeler": "graphcut", "dmrt_labeling_s": {"total_s": 3.0}, "machine": {"cpus": 2},
         "dmt": [_dmt_entry(256, [256, 171], whole, {"cpu": 4.0 / 2.0, "wall": 2.0 / 4.0}, [10.0, 20.0, 30.0]),
                 _dmt_entry(512, [512, 342], part, {"cpu": 50.0 / 2.0, "wall": 25.0 / 4.0}, [5.0, 8.0, 9.0],
                            render_labeler="own")],
         "dmrt": {"layers": 5, "labeling_s": 3.0, "labeling": dmrt_lab, "fps_min_avg_max": [40.0, 50.0, 60.0],
                  "fps_per_frame": [50.0] * 3}, "fps_ratio_dmrt_over_dmt": {"256": 2.5, "512": 6.25}}
    rows, per_frame = table3_rows({"dmt": d})
    r256, r512, rdmrt = rows
    assert r256["maps labelled"] == "2 of 2" and r256["labeling CPU (s)"] == 4.0 and r256["labeling wall (s)"] == 2.0
    assert r256["CPU DMT / DMRT"] == 2.0 and r256["wall DMT / DMRT"] == 0.5 and r256["note"] is None
    assert r512["maps labelled"] == "4 of 20" and r512["labeling CPU (s)"] == 50.0
    assert r512["labeling wall (s)"] == 25.0 and r512["CPU DMT / DMRT"] == 25.0
    assert r512["CPU s per map median/p10/p90"] == f"{fmt(2.5)}/{fmt(1.3)}/{fmt(3.7)}"
    assert "extrapolated from 4 of 20 maps" in r512["note"] and "seed 7" in r512["note"]
    assert "fps with own labels" in r512["note"]
    assert r512["paper DMT / DMRT"] == pytest.approx(23 * 60 / 204)
    assert rdmrt["labeling wall (s)"] == 4.0 and rdmrt["labeling CPU (s)"] == 2.0
    assert "preprocessing recorded 3 s wall" in rdmrt["note"]
    assert per_frame == {"DMT 256x171": [20.0] * 3, "DMT 512x342": [8.0] * 3, "DMRT": [50.0] * 3}

    # a result of version 1 (one labeling figure, own labels) still reads
    old = {"labeler": "own", "dmrt_labeling_s": {"total_s": 3.0},
           "dmt": [{"width": 256, "size": [256, 171], "labeling": {"seconds": 2.0, "cached": False},
                    "labeling_ratio_dmt_over_dmrt": 2.0 / 3.0, "fps_min_avg_max": [1.0, 2.0, 3.0],
                    "fps_per_frame": [2.0]}],
           "dmrt": {"layers": 5, "labeling_s": 3.0, "fps_min_avg_max": [4.0, 5.0, 6.0], "fps_per_frame": [5.0]}}
    rows, _ = table3_rows({"dmt": old})
    assert rows[0]["labeling wall (s)"] == 2.0 and rows[0]["wall DMT / DMRT"] == pytest.approx(2 / 3)
    assert rows[0]["CPU DMT / DMRT"] is None and "own labels: labeling time not comparable" in rows[0]["note"]
    assert rows[1]["labeling wall (s)"] == 3.0 and rows[1]["labeling CPU (s)"] is None
