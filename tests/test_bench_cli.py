"""The component benchmarks that read a bundle (``--bundle``) answer a bundle (or scene) they cannot
read with one line naming it and exit status 2, before they write anything."""

import importlib

import pytest


@pytest.mark.parametrize("module", ["bench.bench_render", "bench.bench_visibility", "bench.occupancy"])
def test_missing_bundle_is_one_line(module, tmp_path, capsys):
    main = importlib.import_module(module).main
    with pytest.raises(SystemExit) as exit_info:
        main(["--bundle", str(tmp_path / "none"), "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert ": error: " in err and str(tmp_path / "none") in err and "\n" not in err
    assert not (tmp_path / "out").exists()  # nothing written


def test_quality_missing_scene_is_one_line(tmp_path, capsys):
    from bench.bench_quality import main

    with pytest.raises(SystemExit) as exit_info:
        main(["--scene", str(tmp_path / "no-scene"), "--bundle", str(tmp_path / "none"), "--out", str(tmp_path / "out")])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert ": error: " in err and str(tmp_path / "no-scene") in err and "\n" not in err
    assert not (tmp_path / "out").exists()


def test_render_walk_of_fewer_than_two_photos_is_one_line(tmp_path, capsys):
    from bench.bench_render import main

    with pytest.raises(SystemExit) as exit_info:
        main(["--bundle", str(tmp_path / "none"), "--out", str(tmp_path / "out"), "--walk-photos", "1"])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip()
    assert ": error: --walk-photos: 1 photos" in err and "\n" not in err
    assert not (tmp_path / "out").exists()


def test_render_keys_file_errors_are_one_line(tmp_path, capsys):
    """--keys names a camera path file: a missing one, or one given with --walk-photos, is one line
    and exit status 2 before anything is written."""
    from bench.bench_render import main

    for extra, expected in ((["--keys", str(tmp_path / "none.json")], "none.json"),
                            (["--keys", str(tmp_path / "k.json"), "--walk-photos", "4"], "give one")):
        with pytest.raises(SystemExit) as exit_info:
            main(["--bundle", str(tmp_path / "none"), "--out", str(tmp_path / "out"), *extra])
        assert exit_info.value.code == 2
        err = capsys.readouterr().err.strip()
        assert ": error: --keys" in err and expected in err and "\n" not in err
        assert not (tmp_path / "out").exists()
