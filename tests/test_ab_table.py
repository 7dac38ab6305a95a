"""bench.ab_table: the trees of an A/B run side by side, from bench_render's JSON layout."""

from __future__ import annotations

import json

import pytest


def _run(size, total, raster, steps=3.1):
    return {"frame_size": list(size), "sustained_ms": total + 0.2, "sustained_call_ms": {"median": 1.4},
            "mean_iterations": steps, "surface_fraction": 0.99,
            "sustained_timed": {"median_total_ms": total, "p95_total_ms": 2 * total,
                                "median_part_ms": {"visibility:tile_raster": raster}, "median_ms": {"labeling": 0.1}}}


def test_table_per_size_against_the_first_tree(tmp_path, capsys):
    from bench.ab_table import main

    for name, total, raster in (("base", 2.0, 0.8), ("new", 1.5, 0.4)):
        (tmp_path / name).mkdir()
        runs = [_run((1280, 720), total, raster), _run((3840, 2160), 4 * total, 4 * raster)]
        (tmp_path / name / "render-bundle.json").write_text(json.dumps({"runs": runs}))
    main([str(tmp_path), "--trees", "base", "new"])
    out = capsys.readouterr().out
    assert "1280x720" in out and "3840x2160" in out
    rows = [line.split(" | ") for line in out.splitlines() if line.startswith("| new")]
    assert [r[2] for r in rows] == ["0.750", "0.750"]  # GPU / first: 1.5 / 2.0 and 6.0 / 8.0
    assert [r[7] for r in rows] == ["0.400", "1.600"]  # tile_raster


def test_list_passes_table(tmp_path, capsys):
    """A tree run with --passes gets a row of its tile lists' passes and their sum; one without none."""
    from bench.ab_table import main

    for name, passes in (("base", {}), ("split", {"visibility:lists_count": 0.024, "visibility:lists_scan": 0.081})):
        (tmp_path / name).mkdir()
        run = _run((3840, 2160), 3.5, 1.7)
        run["sustained_timed"]["median_part_ms"].update(passes)
        (tmp_path / name / "render-bundle.json").write_text(json.dumps({"runs": [run]}))
    main([str(tmp_path)])
    out = capsys.readouterr().out
    assert "the tile lists pass by pass" in out
    assert "| split | 0.0240 | 0.0810 | 0.105 |" in out
    assert not any(line.startswith("| base | 0.0") for line in out.split("pass by pass")[1].splitlines())


def test_tile_sweeps_per_size_and_setting(tmp_path, capsys):
    """A tree's sweeps (ab_run.sh SWEEP) become a table per frame size: the raster's ms per setting
    and tree, '-' where a tree lacks the setting, the layers' agreement where it is not 1."""
    from bench.ab_table import main

    for name, ms in (("base", 2.6), ("new", 2.0)):
        (tmp_path / name / "sweep-3840").mkdir(parents=True)
        (tmp_path / name / "render-bundle.json").write_text(json.dumps({"runs": [_run((3840, 2160), 5.0, ms)]}))
        entries = [{"tile": 16, "batch": 384, "top": 16, "warp_blocks": True, "tile_raster_ms": ms,
                    "layers_equal_to_first": 1.0}]
        if name == "new":
            entries.append({"tile": 16, "batch": 288, "top": 12, "warp_blocks": False, "tile_raster_ms": 1.8,
                            "layers_equal_to_first": 0.5})
            entries.append({"tile": 16, "batch": 288, "top": 12, "warp_blocks": True, "walk": "sparse",
                            "tile_raster_ms": 1.7, "layers_equal_to_first": 1.0})
        (tmp_path / name / "sweep-3840" / "visibility-b.json").write_text(
            json.dumps({"frame_size": [3840, 2160], "tile_sweep": entries}))
    main([str(tmp_path)])
    out = capsys.readouterr().out
    assert "| 16:384:16 | 2.600 | 2.000 |" in out
    assert "| 16:288:12:r | - | 1.800 (layers 0.500000) |" in out
    assert "| 16:288:12:s | - | 1.700 |" in out


def test_tile_sweep_settings_parse():
    """bench_visibility --tile-sweep settings: warps of rows with ':r', the raster's walk with ':s' or
    ':l'; anything else is refused."""
    from bench.bench_visibility import parse_tile_setting

    assert parse_tile_setting("16:288:12") == (16, 288, 12, True, "auto")
    assert parse_tile_setting("16:288:12:r:s") == (16, 288, 12, False, "sparse")
    assert parse_tile_setting("8:256:8:l") == (8, 256, 8, True, "linear")
    assert parse_tile_setting("12:256:8") == (12, 256, 8, False, "auto")  # no 8x4 blocks in 12 px
    for bad in ("16:288", "16:288:12:x", "16:288:12:s:r", "16:288:12:s:l", "40:288:12", "16:288:5"):
        with pytest.raises(ValueError):
            parse_tile_setting(bad)


def test_missing_tree_is_one_line_and_status_2(tmp_path, capsys):
    from bench.ab_table import main

    (tmp_path / "base").mkdir()
    with pytest.raises(SystemExit) as exc:
        main([str(tmp_path), "--trees", "base"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "base" in err and "render-*.json" in err and len(err.strip().splitlines()) == 1
