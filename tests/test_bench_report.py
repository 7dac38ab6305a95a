"""The benchmark harness and report end to end on the ``ci`` preset (CPU, Mesa llvmpipe), and the
report's failure modes.

One session-scoped ``dmrt bench --preset ci`` run (on conftest's tiny scene) feeds the checks that
the report is complete and built from the measured data: every required table and figure present,
numbers in REPORT.md equal to those in the JSON files, figures that are not blank, hole maps of the
frame's shape. Speed is never asserted (GPU timer values are meaningless on llvmpipe). The failure
modes (missing, failed and truncated result files) are checked on small hand-made result sets.
"""

from __future__ import annotations

import json
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pytest

from bench.report import REQUIRED_EXPERIMENTS, fmt


# ----------------------------------------------------------------------------------------------
# The ci preset, once
# ----------------------------------------------------------------------------------------------
@pytest.fixture(scope="session")
def ci_run(tiny_scene, tmp_path_factory):
    """``dmrt bench --preset ci`` then ``dmrt report --check``: (results dir, result set dir, report dir)."""
    from dmrt.app.cli import main

    root = tmp_path_factory.mktemp("bench")
    results, report = root / "results", root / "report"
    assert main(["bench", "--preset", "ci", "--out", str(results), "--work", str(root / "work"),
                 "--scene", str(tiny_scene), "--quiet"]) == 0
    assert main(["report", str(results), "--out", str(report), "--check"]) == 0
    (set_dir,) = [p for p in results.glob("*/*") if p.is_dir()]
    return results, set_dir, report


def _result(set_dir: Path, name: str) -> dict:
    return json.loads((set_dir / f"{name}.json").read_text())


def _md_rows(md: str) -> set[str]:
    return {line for line in md.splitlines() if line.startswith("| ")}


@pytest.mark.e2e
@pytest.mark.slow
def test_ci_results_layout(ci_run):
    """asv layout: RESULTS/<machine>/<commit>-ci/<experiment>.json with machine, commit, preset,
    parameters, version and raw measurements; machine.json beside the result sets."""
    from bench.experiments import EXPERIMENTS

    results, set_dir, _ = ci_run
    assert set_dir.name.endswith("-ci")
    assert (set_dir.parent / "machine.json").is_file()
    for name in REQUIRED_EXPERIMENTS:
        assert name in EXPERIMENTS
        r = _result(set_dir, name)
        assert r["experiment"] == name and r["preset"] == "ci" and r["version"] == EXPERIMENTS[name].version
        assert r["machine"]["gl_renderer"] and r["machine"]["gl_version"] and r["machine"]["cpu_cores"] >= 1
        assert r["machine"]["cpu"]
        assert re.fullmatch(r"[0-9a-f]{12}|unknown", r["commit"]["hash"])
        assert set_dir.name == f"{r['commit']['hash']}-ci"
        assert r["parameters"] is not None and r["measurements"]
    assert not list(set_dir.glob("*.failed.json"))


@pytest.mark.e2e
@pytest.mark.slow
def test_report_is_complete(ci_run):
    """Every required section with its tables (CSV too) and non-blank figures; nothing 'not run'."""
    import matplotlib.image as mpimg

    _, _, report = ci_run
    md = (report / "REPORT.md").read_text()
    page = (report / "index.html").read_text()
    assert md.splitlines()[2].startswith("**Complete**")
    assert "INCOMPLETE" not in md and "FAILED" not in md
    for name in REQUIRED_EXPERIMENTS:
        assert f"no `{name}.json`" not in md
        assert f"id='{name}'" in page
    figures = ["table2_stages.png", "fig12_fps.png", "fig7_proxies.png", "fig8_heatmaps.png", "fig9_step_sizes.png",
               "fig9_iterations.png", "fig13_holes.png"]
    for f in figures:
        path = report / "figures" / f
        assert path.stat().st_size > 10_000, f
        img = mpimg.imread(path)
        assert img.ndim == 3 and img[..., :3].std() > 0.05, f"{f} looks blank"
        assert f"figures/{f}" in md and f"figures/{f}" in page
    for csv in ["table1_scene", "table1_preprocessing", "table2_tiles", "table2_compute", "table2_raster",
                "table2_ratios", "table2_large",
                "table3", "fig7", "fig7_holes", "fig8", "fig9_10", "fig13", "memory"]:
        assert (report / "csv" / f"{csv}.csv").stat().st_size > 50, csv
        assert f"csv/{csv}.csv" in md
    assert sorted(p.name for p in (report / "results").glob("*.json")) == sorted(
        [f"{n}.json" for n in REQUIRED_EXPERIMENTS] + ["machine.json"])


@pytest.mark.e2e
@pytest.mark.slow
def test_report_numbers_are_the_measured_ones(ci_run):
    """Rows of REPORT.md rebuilt from the JSON files (not from the report code) are in it verbatim."""
    from bench import paper

    _, set_dir, report = ci_run
    rows = _md_rows((report / "REPORT.md").read_text())

    c = _result(set_dir, "table1")["measurements"]["counts"]
    assert f"| points | {c['points']} | {paper.TABLE1['Scene 2']['points']} | " \
           f"{fmt(c['points'] / paper.TABLE1['Scene 2']['points'])} |" in rows
    assert f"| proxies | {c['proxies']} | 1000000 | {fmt(c['proxies'] / 1e6)} |" in rows

    t2 = _result(set_dir, "table2")["measurements"]
    assert [r["method"] for r in t2["runs"]] == ["tiles"] * 3 + ["compute"] * 3 + ["raster"] * 3
    k1 = t2["runs"][0]
    for r in t2["runs"]:
        # every frame of the sustained pass read one status record (the walkthrough's lists were
        # sized by the passes before it), and the sustained timed pass timed every stage
        assert r["status_reads_per_frame"] == 1.0, (r["method"], r["status_reads_per_frame"])
        # the photo cache was steady before the timed passes (all the tiny scene's photos fit)
        assert r["warm_up"]["steady"] and r["photo_uploads"] == 0, (r["method"], r["warm_up"])
        st = r["sustained_timed"]
        assert len(st["total_ms_per_frame"]) == len(r["wall_ms_per_frame"])  # the same walkthrough
        assert {"visibility", "raytracing", "texturing"} <= set(st["median_ms"])
        # each frame's sections, which add up to its total
        parts = st["part_ms_per_frame"]
        assert "raytracing:search" in parts and all(len(v) == len(st["total_ms_per_frame"]) for v in parts.values())
        # (NaN on both sides where no time was measured: a software rasterizer, dmrt.gl.timer)
        assert np.allclose([sum(v[i] for v in parts.values()) for i in range(len(st["total_ms_per_frame"]))],
                           st["total_ms_per_frame"], rtol=1e-6, equal_nan=True)
    # the raytracing row of the default path's table starts with the 1-layer median of the frames
    # rendered back to back and the paper's 1.2 ms
    assert any(r.startswith(f"| raytracing | {fmt(k1['sustained_timed']['median_ms']['raytracing'])} | 1.2 |")
               for r in rows)
    # the larger frame: every path but raster at 5 layers, its total in the larger-frames table
    large = t2["large_runs"]
    assert [(r["method"], r["layers"], r["frame_size"]) for r in large] == [("tiles", 5, [288, 192]),
                                                                           ("compute", 5, [288, 192])]
    assert any(r.startswith("| 288x192 | tiles | 5 |") and f"| {fmt(large[0]['sustained_timed']['median_total_ms'])} |" in r
               for r in rows)
    # mean search steps and the visibility ratios appear in the ratio table
    ratios = t2["visibility_ratios"]
    assert set(ratios) == {"raster/compute", "compute/tiles", "raster/tiles"}
    assert any(f"| {fmt(ratios['raster/compute']['1'])} | {fmt(ratios['compute/tiles']['1'])} | "
               f"{fmt(ratios['raster/tiles']['1'])} |" in r and f"| {fmt(k1['mean_iterations'])} |" in r
               for r in rows)

    dmt = _result(set_dir, "table3_fig12")["measurements"]["dmt"]
    dmrt_lab = dmt["dmrt"]["labeling"]
    assert dmrt_lab["labels_equal_bundle"] == 1.0  # the labeling run again is preprocessing's
    for e, p in zip(dmt["dmt"], paper.TABLE3_DMT.values()):
        w, h = e["size"]
        lab = e["labeling"]
        # the tiny scene's 12 maps fit the ci budget: every map graph-cut on every core (at most 12 processes)
        assert lab["labeler"] == "graphcut" and not lab["extrapolated"] and e["render_labeler"] == "graphcut"
        assert lab["maps"] == lab["maps_total"] == 12 and lab["workers"] == min(os.cpu_count(), 12)
        assert e["labeling_ratio_dmt_over_dmrt"]["cpu"] == pytest.approx(lab["cpu_s_all"] / dmrt_lab["cpu_s"])
        assert e["labeling_ratio_dmt_over_dmrt"]["wall"] == pytest.approx(lab["wall_s_all"] / dmrt_lab["wall_s"])
        per_map = "/".join(fmt(lab["cpu_s_per_map"][k]) for k in ("median", "p10", "p90"))
        want = (f"| DMT {w}x{h} | DMT {p['size'][0]}x{p['size'][1]} | 12 of 12 | {fmt(lab['wall_s_all'])} | "
                f"{fmt(lab['cpu_s_all'])} | {per_map} | {fmt(p['labeling_s'])} | "
                f"{fmt(e['labeling_ratio_dmt_over_dmrt']['cpu'])} | {fmt(e['labeling_ratio_dmt_over_dmrt']['wall'])} |")
        assert any(r.startswith(want) for r in rows), want
        assert any(f"| {fmt(e['fps_min_avg_max'][0])} | {fmt(e['fps_min_avg_max'][1])} | " in r for r in rows)
    assert any(r.startswith(f"| DMRT (5 layers) | DMRT 1024x684, 1M proxies, 5 layers | n/a | "
                            f"{fmt(dmrt_lab['wall_s'])} | {fmt(dmrt_lab['cpu_s'])} | n/a | 204 |") for r in rows)

    fig7 = _result(set_dir, "fig7")["measurements"]
    for s in fig7["sets"]:
        assert any(r.startswith(f"| {s['proxies']} | {fmt(s['subsampling_factor'])} | {fmt(s['labeling_total_s'])} |")
                   for r in rows)
    first = sorted(fig7["sets"], key=lambda s: -s["proxies"])
    want = "| 1 | " + " | ".join(fmt(100 * s["hole_rate_representable_per_layers"][0]) for s in first)
    assert any(r.startswith(want) for r in rows)

    fig8 = _result(set_dir, "fig8")["measurements"]["stages"]
    for stage, m in fig8.items():
        assert any(r.startswith(f"| {stage} | {fmt(1e3 * m['depth_median_m'])} | {fmt(1e3 * m['depth_mean_m'])} |")
                   for r in rows)

    for case in _result(set_dir, "fig9_10")["measurements"]["cases"]:
        want = f"| {case['case']} | {case['layers']} | {fmt(case['mean_iterations'])} |"
        assert any(r.startswith(want) for r in rows)

    for row in _result(set_dir, "fig13")["measurements"]["rows"]:
        assert any(r.startswith(f"| {row['layers']} | {fmt(100 * row['hole_rate'])} | "
                                f"{fmt(100 * row['hole_rate_representable'])} |") for r in rows)

    mem = _result(set_dir, "memory")["measurements"]
    got = mem["gpu_bytes"]["depthmaps"]
    assert any(r.startswith(f"| depthmaps | {fmt(got * 1e-6)} | {fmt(mem['formula_bytes']['depthmaps'] * 1e-6)} |")
               for r in rows)


@pytest.mark.e2e
@pytest.mark.slow
def test_maps_have_the_frame_shape_and_match_the_json(ci_run):
    """Fig. 8 and Fig. 13 maps are (h, w) of the frame, and the rates in the JSON are theirs."""
    _, set_dir, _ = ci_run
    fig8 = _result(set_dir, "fig8")["measurements"]
    w, h = fig8["frame_size"]
    with np.load(set_dir / fig8["maps_file"]) as z:
        maps = {k: z[k] for k in z.files}
    ref_surface = maps["reference_depth"] > 0
    for stage, m in fig8["stages"].items():
        holes = maps[f"{stage}_holes"]
        assert holes.shape == (h, w) and maps[f"{stage}_depth_error_m"].shape == (h, w)
        assert maps[f"{stage}_color"].shape == (h, w, 3)
        assert (holes > 0).sum() / ref_surface.sum() == pytest.approx(m["hole_rate"])

    fig13 = _result(set_dir, "fig13")["measurements"]
    w, h = fig13["frame_size"]
    with np.load(set_dir / fig13["maps_file"]) as z:
        for row in fig13["rows"]:
            holes = z[f"holes_{row['layers']}"]
            assert holes.shape == (h, w) and set(np.unique(holes)) <= {-1.0, 0.0, 1.0}
            assert z[f"color_{row['layers']}"].shape == (h, w, 3)
    rates = [r["hole_rate_representable"] for r in fig13["rows"]]
    assert rates[0] >= rates[1] >= rates[2]  # more layers never add holes
    for row in fig13["rows"]:
        # hole filling only gives surface to pixels the layers left empty: never more holes, and on
        # the tiny scene's silhouettes it fills some
        assert row["fill_passes"] > 0 and row["hole_rate_filled"] < row["hole_rate"]
        assert row["hole_rate_representable_filled"] <= row["hole_rate_representable"]


@pytest.mark.e2e
@pytest.mark.slow
def test_fig13_direct_renders_agree_with_fig7_from_one_render(ci_run):
    """Fig. 7 reads the hole rate of k layers off one max-layer frame (``hole_counts``); Fig. 13 renders
    1, 2, 3 layers directly at the same photo cameras: the rates must be equal."""
    _, set_dir, _ = ci_run
    main_proxies = _result(set_dir, "table1")["measurements"]["counts"]["proxies"]
    (main,) = [s for s in _result(set_dir, "fig7")["measurements"]["sets"] if s["proxies"] == main_proxies]
    for row in _result(set_dir, "fig13")["measurements"]["rows"]:
        k = row["layers"]
        # equal with depth peeling; the k-buffer keeps 6k + 2 fragments, so a 5-layer frame's first
        # layers may be (rarely) more complete than a 1-layer frame's: 0.1 percentage point
        assert row["hole_rate"] == pytest.approx(main["hole_rate_per_layers"][k - 1], abs=1e-3)
        assert row["hole_rate_representable"] == pytest.approx(main["hole_rate_representable_per_layers"][k - 1],
                                                               abs=1e-3)


@pytest.mark.e2e
@pytest.mark.slow
def test_derived_proxy_bundle_equals_preprocessing(ci_run, tiny_bundle):
    """The harness's main bundle (proxies relabeled on the base bundle's depth maps) holds exactly what
    ``dmrt preprocess`` writes for the same scene and settings."""
    from dmrt.io.bundle import read_bundle

    _, set_dir, _ = ci_run
    derived = read_bundle(_result(set_dir, "table1")["measurements"]["bundle"]["path"])
    direct = read_bundle(tiny_bundle)
    assert derived.meta.get("derived_from")
    for key in ("positions", "normals", "radii", "labels"):
        np.testing.assert_array_equal(derived.proxy[key], direct.proxy[key], err_msg=key)


# ----------------------------------------------------------------------------------------------
# Failure modes, on hand-made result sets (no GL)
# ----------------------------------------------------------------------------------------------
def _table1_payload() -> dict:
    counts = {"points": 1000, "photos": 4, "proxies": 100, "proxy_levels": 1}
    return {"experiment": "table1", "version": 1, "date": "2026-01-01T00:00:00+0000", "preset": "ci",
            "machine": {"gl_renderer": "test GL", "gl_version": "4.5", "cpu": "test CPU", "cpu_cores": 2},
            "commit": {"hash": "abcdef123456", "date": None, "dirty": False}, "parameters": {},
            "measurements": {"counts": counts, "depthmap_size": [64, 43], "photo_size": [64, 43],
                             "phases_s": {"octree_s": 0.5, "labeling_s": 0.25}, "preprocess_total_s": 0.75,
                             "bundle": {"proxies": 100}}}


def _write_set(root: Path, commit: str = "abcdef123456", preset: str = "ci", **files) -> Path:
    d = root / "test-gl" / f"{commit}-{preset}"
    d.mkdir(parents=True)
    for name, text in files.items():
        (d / f"{name}.json").write_text(text if isinstance(text, str) else json.dumps(text))
    return d


def test_missing_experiments_show_as_not_run_and_fail_the_check(tmp_path, capsys):
    from bench.report import build_report
    from dmrt.app.cli import main

    _write_set(tmp_path / "results", table1=_table1_payload())
    r = build_report(tmp_path / "results", tmp_path / "report")
    assert r.missing == [n for n in REQUIRED_EXPERIMENTS if n != "table1"]
    md = (tmp_path / "report" / "REPORT.md").read_text()
    assert md.splitlines()[2].startswith("**INCOMPLETE**")
    for name in r.missing:
        assert f"**Not run**: no `{name}.json`" in md
    assert "| points | 1000 |" in md
    assert "Not run" in (tmp_path / "report" / "index.html").read_text()
    # without --check the report is still written and the command succeeds; with it, it fails
    assert main(["report", str(tmp_path / "results"), "--out", str(tmp_path / "r2")]) == 0
    with pytest.raises(SystemExit) as exc:
        main(["report", str(tmp_path / "results"), "--out", str(tmp_path / "r3"), "--check"])
    assert exc.value.code == 1
    assert "INCOMPLETE" in capsys.readouterr().err


def test_failed_experiment_is_reported_as_failed(tmp_path):
    from bench.report import build_report

    _write_set(tmp_path / "results", table1=_table1_payload(),
               **{"fig8.failed": {"experiment": "fig8", "error": "RuntimeError: boom"}})
    r = build_report(tmp_path / "results", tmp_path / "report")
    assert r.failed == ["fig8"] and "fig8" not in r.missing  # listed once, as failed
    md = (tmp_path / "report" / "REPORT.md").read_text()
    assert "**FAILED**: `fig8` raised RuntimeError: boom" in md


def test_truncated_result_file_is_a_clear_error_and_keeps_the_old_report(tmp_path, capsys):
    from bench.report import build_report
    from dmrt.app.cli import main
    from dmrt.errors import InputError

    d = _write_set(tmp_path / "results", table1=_table1_payload())
    build_report(tmp_path / "results", tmp_path / "report")
    before = (tmp_path / "report" / "REPORT.md").read_text()
    text = json.dumps(_table1_payload())
    (d / "table2.json").write_text(text[: len(text) // 2])
    with pytest.raises(InputError) as exc:
        build_report(tmp_path / "results", tmp_path / "report")
    assert str(d / "table2.json") in str(exc.value) and "not valid JSON" in str(exc.value)
    assert main(["report", str(tmp_path / "results"), "--out", str(tmp_path / "report")]) == 2
    assert str(d / "table2.json") in capsys.readouterr().err
    # the previous report is untouched and no half-built one is left behind
    assert (tmp_path / "report" / "REPORT.md").read_text() == before
    assert not (tmp_path / "report.partial").exists()
    (d / "table2.json").write_text(json.dumps({"experiment": "table2"}))
    with pytest.raises(InputError, match="field 'version' missing"):
        build_report(tmp_path / "results", tmp_path / "report")


@pytest.mark.e2e
@pytest.mark.slow
def test_history_of_several_result_sets(ci_run, tmp_path):
    """Two result sets of one machine and preset: the newest gives the tables, both the history plot."""
    from bench.report import build_report

    results, set_dir, _ = ci_run
    copy = tmp_path / "results"
    shutil.copytree(results, copy)
    older = copy / set_dir.parent.name / "000000000000-ci"
    shutil.copytree(copy / set_dir.parent.name / set_dir.name, older)
    for f in older.glob("*.json"):
        r = json.loads(f.read_text())
        r["date"] = "2000-01-01T00:00:00+0000"
        r["commit"]["hash"] = "000000000000"
        f.write_text(json.dumps(r))
    out = build_report(copy, tmp_path / "report")
    assert out.result_set.dir.name == set_dir.name
    md = (tmp_path / "report" / "REPORT.md").read_text()
    assert "## History" in md and "| 2000-01-01" in md
    # each set with its default visibility path and frame size (the ci preset: tiles, 192x128, 5 layers)
    assert sum(1 for r in _md_rows(md) if "| tiles | 192x128 | 5 |" in r) == 2
    assert (tmp_path / "report" / "figures" / "history.png").stat().st_size > 10_000


@pytest.mark.gpu  # dmrt bench records the GL renderer
@pytest.mark.e2e
def test_a_failing_experiment_does_not_stop_the_others(tmp_path, monkeypatch, capsys):
    """A raising experiment leaves ``<name>.failed.json`` (and no stale result), the next one still runs,
    and ``dmrt bench`` exits non-zero naming it."""
    from dataclasses import dataclass

    from bench import experiments
    from dmrt.app.cli import main

    @dataclass
    class NoParams:
        pass

    def boom(ws, params, out):
        raise RuntimeError("boom")

    monkeypatch.setitem(experiments.EXPERIMENTS, "boom",
                        experiments.Experiment("fails", 1, boom, lambda p: NoParams()))
    monkeypatch.setitem(experiments.EXPERIMENTS, "fine", experiments.Experiment(
        "works", 1, lambda ws, params, out: {"value": 42}, lambda p: NoParams()))
    argv = ["bench", "--preset", "ci", "--out", str(tmp_path / "results"), "--work", str(tmp_path / "work"),
            "--machine", "test-machine", "--quiet", "--only", "boom", "fine"]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert "boom" in str(exc.value.code)
    (set_dir,) = (tmp_path / "results" / "test-machine").glob("*-ci")
    assert json.loads((set_dir / "boom.failed.json").read_text())["error"] == "RuntimeError: boom"
    assert not (set_dir / "boom.json").exists()
    fine = json.loads((set_dir / "fine.json").read_text())
    assert fine["measurements"] == {"value": 42} and fine["preset_config"]["name"] == "ci"
    assert fine["machine"]["name"] == "test-machine"


# ----------------------------------------------------------------------------------------------
# History
# ----------------------------------------------------------------------------------------------
def _table2_payload(commit: str, date: str, method: str, ms5: float, run_size=None, walk_size=None) -> dict:
    """A Table 2 result of 1 and 5 layers (5 layers: ``ms5`` GPU ms); the frame size in each run
    (``run_size``, as now) or only in the parameters' walk (``walk_size``, as before the sustained pass)."""
    runs = [{"method": method, "layers": k, "median_total_ms": ms5 * k / 5, "fps_median": 5e3 / (ms5 * k),
             **({"frame_size": run_size} if run_size else {})} for k in (1, 5)]
    return {"experiment": "table2", "version": 1, "date": date, "preset": "ci",
            "commit": {"hash": commit, "date": None, "dirty": False},
            "parameters": {"walk": {"frame_size": walk_size}} if walk_size else {},
            "measurements": {"runs": runs, "visibility_ratios": {}}}


def test_history_keeps_result_sets_of_every_default_path(tmp_path):
    """A k-buffer-era result set (frame size only in its parameters) and a tiles one (frame size in
    the run): both in the history, oldest first, each with its commit, method and frame size."""
    from bench.report import Table, load_results, section_history

    root = tmp_path / "results"
    _write_set(root, "aaaaaaaaaaaa", table2=_table2_payload("aaaaaaaaaaaa", "2026-01-01T00:00:00+0000", "kbuffer",
                                                            16.0, walk_size=[640, 360]))
    _write_set(root, "bbbbbbbbbbbb", table2=_table2_payload("bbbbbbbbbbbb", "2026-02-01T00:00:00+0000", "tiles",
                                                            5.0, run_size=[1280, 720]))
    out = tmp_path / "out"
    (out / "figures").mkdir(parents=True)
    s = section_history(load_results(root), out)
    (table,) = [b for b in s.blocks if isinstance(b, Table)]
    got = table.df[["commit", "method", "frame", "layers", "total GPU ms", "fps"]].values.tolist()
    assert got == [["aaaaaaaaaaaa", "kbuffer", "640x360", 5, 16.0, 62.5], ["bbbbbbbbbbbb", "tiles", "1280x720", 5, 5.0, 200.0]]
    assert (out / "figures" / "history.png").stat().st_size > 10_000


def test_a_report_kept_beside_the_results_is_not_read_as_results(tmp_path):
    """The nightly keeps the newest report in the results folder (``history/report``): its
    ``results/`` copies (machine.json among them) are not a result set of a machine "report"."""
    from bench.report import build_report, load_results

    root = tmp_path / "results"
    _write_set(root, table1=_table1_payload())
    (root / "test-gl" / "machine.json").write_text(json.dumps({"name": "test-gl"}))  # as dmrt bench writes it
    build_report(root, root / "report")
    assert (root / "report" / "results" / "machine.json").is_file()
    r = build_report(root, tmp_path / "again")
    assert [(s.machine, s.commit) for s in load_results(root)] == [("test-gl", "abcdef123456")]
    assert r.result_set.machine == "test-gl"


def test_table1_at_scene2_size_stands_beside_the_presets(tmp_path):
    """A `paper-full` result set (a preset name with a hyphen) of the same machine: its Table 1 is
    a section of the other preset's report, with CPU seconds per phase; alone it is its own report."""
    from bench.report import build_report, load_results

    root = tmp_path / "results"
    _write_set(root, table1=_table1_payload())
    full = _table1_payload()
    full["measurements"]["counts"] = dict(full["measurements"]["counts"], points=682_922_688)
    full["measurements"].update(cpu_s_per_phase={"octree_s": 7.0, "labeling_s": 1.0}, cores=16,
                                peak_anon_mb={"octree_s": 512.0, "labeling_s": 64.0})
    _write_set(root, "0123456789ab", preset="paper-full", table1=full)
    scene3 = _table1_payload()
    scene3["measurements"]["counts"] = dict(scene3["measurements"]["counts"], points=1_091_990_160)
    _write_set(root, "0123456789ab", preset="paper-scene3", table1=scene3)
    assert sorted((s.commit, s.preset) for s in load_results(root)) == [
        ("0123456789ab", "paper-full"), ("0123456789ab", "paper-scene3"), ("abcdef123456", "ci")]
    build_report(root, tmp_path / "report", preset="ci")
    md = (tmp_path / "report" / "REPORT.md").read_text()
    assert "## Table 1 at Scene 2's size: the `paper-full` preset (commit 0123456789ab" in md
    assert "| points | 682922688 | 682000000 |" in md
    assert "| octree | 0.5 | 7 | 14 | 512 |" in md  # wall s, CPU s, cores busy, peak MiB
    assert (tmp_path / "report" / "results" / "paper-full-table1.json").is_file()
    # Scene 3 beside the paper's Scene 3, which gives points and photos only
    assert "## Table 1 at Scene 3's size: the `paper-scene3` preset (commit 0123456789ab" in md
    assert md.index("Scene 2's size") < md.index("Scene 3's size")
    assert "| points | 1091990160 | 1.091e+09 | 1.001 |" in md  # a column with empty cells prints as floats
    own = build_report(root, tmp_path / "own", preset="paper-full")
    assert own.result_set.preset == "paper-full"
    assert "Scene 2's size" not in (tmp_path / "own" / "REPORT.md").read_text()


def test_a_set_without_its_image_maps_keeps_the_earlier_figure(ci_run, tmp_path):
    """reports/history keeps the JSON only: rebuilt from it, the report keeps the figures that its
    previous build drew from the same set's maps, and says so."""
    from bench.report import build_report

    results, set_dir, _ = ci_run
    copy = tmp_path / "results"
    shutil.copytree(results, copy)
    build_report(copy, tmp_path / "report")
    drawn = (tmp_path / "report" / "figures" / "fig8_heatmaps.png").read_bytes()
    for f in (copy / set_dir.parent.name / set_dir.name).glob("*.npz"):
        f.unlink()
    build_report(copy, tmp_path / "report")
    assert (tmp_path / "report" / "figures" / "fig8_heatmaps.png").read_bytes() == drawn
    md = (tmp_path / "report" / "REPORT.md").read_text()
    # figs. 8, 13 and the real views, each caption twice (the image's alt text and the caption)
    assert md.count("the image maps of this result set are not in the results folder") == 6
    build_report(copy, tmp_path / "fresh")  # no earlier build: no figure, a line instead
    assert not (tmp_path / "fresh" / "figures" / "fig8_heatmaps.png").exists()
    assert "No figure: fig8's image maps (.npz) are not in the results folder." in (tmp_path / "fresh" / "REPORT.md").read_text()


# ----------------------------------------------------------------------------------------------
# A newest result set of some experiments only (dmrt bench --only): the others carried
# ----------------------------------------------------------------------------------------------
# the committed JSON of a complete paper run (reports/history keeps it): real result files
HISTORY_SET = Path(__file__).parents[1] / "reports" / "history" / "nvidia-h200-pcie-sse2" / "fdb23828dc27-paper"
NEW_COMMIT = "123456789abc"


def _rerun(name: str) -> dict:
    """The history set's result of ``name`` as if run again at NEW_COMMIT a month later."""
    r = json.loads((HISTORY_SET / f"{name}.json").read_text())
    r["commit"] = dict(r["commit"], hash=NEW_COMMIT)
    r["date"] = "2026-12-24T00:00:00+0000"
    return r


def _partial_run(root: Path, **files) -> tuple[Path, Path]:
    """The history set (complete, older) and a set of ``files`` only at NEW_COMMIT, of one machine and
    preset: (older dir, newer dir)."""
    older = root / HISTORY_SET.parent.name / HISTORY_SET.name
    shutil.copytree(HISTORY_SET, older)
    newer = older.parent / f"{NEW_COMMIT}-paper"
    newer.mkdir()
    for name, payload in files.items():
        (newer / f"{name}.json").write_text(json.dumps(payload))
    return older, newer


def _write_fig8_maps(set_dir: Path) -> None:
    """Small image maps (.npz) with every array fig8.json lists: colours RGB8, the rest float."""
    m = json.loads((set_dir / "fig8.json").read_text())["measurements"]
    rng = np.random.default_rng(0)
    maps = {k: rng.integers(0, 256, (6, 9, 3), dtype=np.uint8) if k.endswith("color")
            else rng.random((6, 9)) > 0.5 if k == "representable" else rng.random((6, 9)).astype(np.float32)
            for k in m["maps"]}
    np.savez_compressed(set_dir / m["maps_file"], **maps)


def _sections(md: str) -> dict[str, str]:
    """REPORT.md's sections by their title up to a ':' (e.g. 'Table 2', 'Fig. 8')."""
    return {part.splitlines()[0].split(":")[0]: part for part in md.split("\n## ")[1:]}


def test_a_partial_run_carries_the_other_experiments_from_an_older_set(tmp_path):
    """A newest set with Table 2 only: the report is complete, Table 2 and the report's commit are
    the new ones, the others are carried from the older set and named in the header and in each
    section; the carried Fig. 8 is drawn from the maps in the older folder; results/ has every JSON."""
    from bench.report import build_report, missing_experiments

    t2 = _rerun("table2")
    t2["measurements"]["runs"][0]["median_ms"]["raytracing"] = 4321.0  # tiles, 1 layer
    older, newer = _partial_run(tmp_path / "results", table2=t2)
    _write_fig8_maps(older)
    r = build_report(tmp_path / "results", tmp_path / "report")
    carried = [n for n in REQUIRED_EXPERIMENTS if n != "table2"]
    rs = r.result_set
    assert rs.dir == newer and rs.commit == NEW_COMMIT and list(rs.carried) == carried
    assert {rs.carried[n].dir for n in carried} == {older}
    assert r.missing == [] and r.failed == [] and missing_experiments(rs) == []

    md = (tmp_path / "report" / "REPORT.md").read_text()
    assert md.splitlines()[2].startswith("**Complete**")
    assert (f"**Carried** from earlier runs of this machine and preset, not run at commit `{NEW_COMMIT}`: "
            f"{', '.join(carried)} (commit fdb23828dc27, 2026-11-23).") in md
    assert f"Commit `{NEW_COMMIT}`" in md and "newest result 2026-12-24T00:00:00+0000" in md
    sections = _sections(md)
    assert "| raytracing | 4321 | 1.2 |" in sections["Table 2"] and "**Carried**" not in sections["Table 2"]
    for title in ("Table 1", "Table 3 and Fig. 12", "Fig. 7", "Fig. 8", "Figs. 9 and 10", "Fig. 13",
                  "Section 6.2", "Real views"):
        assert sections[title].count("**Carried**: `") == 1, title
        assert "shows the result of commit `fdb23828dc27` (2026-11-23T" in sections[title], title
    assert 'class="carried"' in (tmp_path / "report" / "index.html").read_text()
    # Fig. 8's maps are in the older folder only
    assert not list(newer.glob("*.npz"))
    assert "figures/fig8_heatmaps.png" in sections["Fig. 8"] and "No figure" not in sections["Fig. 8"]
    assert (tmp_path / "report" / "figures" / "fig8_heatmaps.png").stat().st_size > 10_000
    # every JSON used, each under its own name: the new Table 2, the carried ones as they were
    res = tmp_path / "report" / "results"
    assert sorted(p.name for p in res.glob("*.json")) == sorted(f"{n}.json" for n in REQUIRED_EXPERIMENTS)
    assert json.loads((res / "table2.json").read_text())["commit"]["hash"] == NEW_COMMIT
    for n in carried:
        assert (res / f"{n}.json").read_bytes() == (older / f"{n}.json").read_bytes()
    # the history reads each set as it is: one row per set with a Table 2 of its own
    history = _md_rows(sections["History (nightly trend)"])
    assert {"fdb23828dc27", NEW_COMMIT} <= {row.split(" | ")[1] for row in history}

    # without the maps, the carried Fig. 8 keeps the figure this report drew before
    (older / "fig8.npz").unlink()
    build_report(tmp_path / "results", tmp_path / "report")
    md = (tmp_path / "report" / "REPORT.md").read_text()
    assert "the image maps of this result set are not in the results folder" in _sections(md)["Fig. 8"]


def test_a_failure_in_the_newest_set_is_not_replaced_by_an_older_result(tmp_path):
    """The new commit broke Fig. 8: FAILED (not the older set's Fig. 8), the report incomplete; the
    experiments it did not run are carried."""
    from bench.report import build_report

    _, newer = _partial_run(tmp_path / "results", table2=_rerun("table2"),
                            **{"fig8.failed": {"experiment": "fig8", "error": "RuntimeError: boom"}})
    r = build_report(tmp_path / "results", tmp_path / "report")
    assert r.failed == ["fig8"] and r.missing == [] and "fig8" not in r.result_set.carried
    assert "fig8" not in r.result_set.experiments and "table1" in r.result_set.carried
    md = (tmp_path / "report" / "REPORT.md").read_text()
    assert md.splitlines()[2] == "**INCOMPLETE** (failed: fig8)."
    assert "**FAILED**: `fig8` raised RuntimeError: boom" in _sections(md)["Fig. 8"]
    assert "fig8 (FAILED)" in md and "table1 (carried from fdb23828dc27)" in md
    res = tmp_path / "report" / "results"
    assert (res / "fig8.failed.json").is_file() and not (res / "fig8.json").exists()
