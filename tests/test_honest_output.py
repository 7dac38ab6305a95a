"""What the suite prints and writes says what was measured and what was asked for: unmeasured GPU
times as unavailable (n/a, null), a user's scene's report with its name and its experiments only,
``--help`` with the options most users need first, ``--version``, and an interrupt that cannot
catch a folder between its two renames."""

import json
import math
import os
import re
import signal

import numpy as np
import pytest

from dmrt.app.cli import build_parser, main


def test_json_text_writes_unmeasured_times_as_null():
    from dmrt.io.atomic import json_text

    doc = {"ms": {"a": math.nan, "b": 0.5, "c": np.float32(0.25)}, "totals": [math.inf, np.float64("nan"), 1],
           "size": np.array([2, 3])}
    assert json.loads(json_text(doc)) == {"ms": {"a": None, "b": 0.5, "c": 0.25}, "totals": [None, None, 1],
                                          "size": [2, 3]}


def test_render_prints_and_writes_unmeasured_times_as_unavailable(tiny_bundle, tmp_path, capsys):
    """A software rasterizer measures no GPU time: ``dmrt render`` says so and ``--stats`` holds
    null (it printed "0.00 ms" for every stage); a GPU's frame has its own times (the command's
    timer waits for them)."""
    from dmrt.gl import get_context, renderer_info

    stats = tmp_path / "s.json"
    assert main(["render", str(tiny_bundle), "--camera", "photo_0002.png", "--width", "64", "--out",
                 str(tmp_path / "f.png"), "--stats", str(stats)]) == 0
    printed = capsys.readouterr().out
    ms = json.loads(stats.read_text())["timings_ms"]
    assert ms["leveling"] == 0.0  # off: no work, known without a timer
    if renderer_info(get_context())["is_software"]:
        assert "GPU times unavailable" in printed and all(ms[k] is None for k in ms if k != "leveling")
    else:
        assert all(isinstance(v, float) for v in ms.values()) and " ms" in printed


def test_report_of_a_users_scene_names_it_and_shows_its_experiments_only(tmp_path):
    from bench.report import build_report
    from bench.workspace import PRESETS, result_label
    from test_bench_report import _table1_payload, _write_set

    # a scene of the user's gets result sets of its own; the preset's synthetic scene does not
    scene = tmp_path / "My Kitchen"
    scene.mkdir()
    assert result_label(PRESETS["ci"], scene) == "ci@My_Kitchen" and result_label(PRESETS["ci"]) == "ci"
    (scene / "synthetic.json").write_text(json.dumps({"config": {"name": "tiny"}}))
    assert result_label(PRESETS["ci"], scene) == "ci"
    payload = {**_table1_payload(), "scene": {"name": "My_Kitchen", "path": str(scene)}}
    _write_set(tmp_path / "results", preset="ci@My_Kitchen", table1=payload)
    r = build_report(tmp_path / "results", tmp_path / "report")
    assert r.missing == [] and r.failed == []
    md = (tmp_path / "report" / "REPORT.md").read_text()
    lines = md.splitlines()
    assert lines[0] == "# DMRT benchmark report: scene My_Kitchen (ci preset)"
    assert lines[2].startswith("**Complete**: every experiment run on scene `My_Kitchen`")
    assert "Not run" not in md and "INCOMPLETE" not in md and str(scene) in md
    assert [ln for ln in lines if ln.startswith("## ")] == ["## Table 1: scene characteristics and preprocessing"]


def test_help_lists_common_options_first_and_tuning_knobs_last(capsys):
    def help_of(command: str) -> list[str]:
        with pytest.raises(SystemExit):
            build_parser().parse_args([command, "--help"])
        return capsys.readouterr().out.splitlines()

    for command, common, knobs in (("render", ["--camera", "--out", "--layers", "--leveling"], ["--max-steps"]),
                                   ("view", ["--photo", "--layers", "--cache-mb"], ["--tile-batch"])):
        text = help_of(command)
        groups = [i for i, ln in enumerate(text) if ln and not ln.startswith(" ") and ln.endswith(":")]
        assert text[groups[1]] == "options:" and text[groups[-1]] == "tuning (the renderer):", text
        main_options = " ".join(text[groups[1]:groups[2]])
        last_group = " ".join(text[groups[-1]:])

        def has(section: str, option: str) -> bool:
            return re.search(rf"\s{option}(?![\w-])", section) is not None

        assert all(has(main_options, o) for o in common) and not any(has(main_options, o) for o in knobs)
        assert all(has(last_group, o) for o in knobs)
        assert len(text[0]) < 100  # a usage line, not every option


def test_version_is_the_package_metadata(capsys):
    from importlib.metadata import version

    with pytest.raises(SystemExit) as exc:
        main(["--version"])
    assert exc.value.code == 0 and capsys.readouterr().out.strip() == f"dmrt {version('dmrt')}"


def test_option_levels_are_checked():
    from dmrt.options import option

    assert option(1, "x", level="common").metadata["level"] == "common"
    assert option(1, "x").metadata["level"] == "tuning"
    with pytest.raises(ValueError, match="level"):
        option(1, "x", level="advanced")


def test_an_interrupt_between_the_renames_is_delivered_after_them(tmp_path, monkeypatch):
    """Ctrl-C in atomic_dir's renames (old aside, new into place) would leave neither under the
    name: it is held until both are done, then raised."""
    from dmrt.io.atomic import atomic_dir

    out = tmp_path / "out"
    with atomic_dir(out) as tmp:
        (tmp / "old").write_text("1")
    renames = []

    def replace(src, dst):
        renames.append(dst)
        if len(renames) == 1:
            os.kill(os.getpid(), signal.SIGINT)  # right after the old folder went aside
        real_replace(src, dst)

    real_replace = os.replace
    with pytest.raises(KeyboardInterrupt):
        with atomic_dir(out) as tmp:
            (tmp / "new").write_text("2")
            monkeypatch.setattr(os, "replace", replace)
    monkeypatch.undo()
    assert len(renames) == 2 and sorted(p.name for p in out.iterdir()) == ["new"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
