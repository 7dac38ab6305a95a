"""The bad-input corpus, end to end through the ``dmrt`` command: every case is the real command
(``dmrt.app.cli.main`` in-process, or a subprocess where the interpreter itself must differ) and
must answer with exit status 2 and ONE line on stderr, ``dmrt: error: <message>``, that names the
file or the option; no traceback; and nothing left where the command was told to write (no output
file or folder, no ``.partial`` folder, no hidden temporary file).

Groups: scenes (the scene corpus of ``test_scene_errors.py``, through ``dmrt preprocess``, plus the
command-level scene cases), bundles (corrupted copies of the tiny bundle), render requests (options
and outputs), camera poses (``--pose``), camera paths (``--path``), other commands, and missing
optional dependencies.
"""

import json
import math
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from dmrt.app.cli import main
from dmrt.io.bundle import camera_to_json, read_bundle

PHOTO = "photo_0002.png"  # a photo camera of the tiny scene


# -- the one assertion every case makes ----------------------------------------------------------
def _snapshot(folder: Path) -> set:
    return {p.relative_to(folder) for p in folder.rglob("*")} if folder.exists() else set()


def assert_bad_input(argv, capfd, names, watch):
    """Run ``dmrt argv``; assert exit 2, one ``dmrt: error:`` line naming each of ``names`` (all
    substrings), no traceback, and that nothing appeared under folder ``watch`` (where the
    command was told to write)."""
    watch = Path(watch)
    before = _snapshot(watch)
    capfd.readouterr()
    status = main([str(a) for a in argv])
    out, err = capfd.readouterr()
    lines = err.splitlines()
    assert status == 2, (status, err)
    assert len(lines) == 1, err
    assert lines[0].startswith("dmrt: error: "), err
    assert "Traceback" not in err + out
    for name in names:
        assert str(name) in lines[0], (name, lines[0])
    assert _snapshot(watch) == before, f"left behind: {_snapshot(watch) - before}"
    return lines[0]


# -- the bundle to corrupt -----------------------------------------------------------------------
@pytest.fixture
def bundle_copy(tiny_bundle, tmp_path):
    """A private copy of the tiny bundle, to corrupt."""
    dst = tmp_path / "in" / "b"
    shutil.copytree(tiny_bundle, dst)
    return dst


@pytest.fixture
def out_dir(tmp_path):
    """The folder a command is told to write into (watched for leftovers)."""
    d = tmp_path / "out"
    d.mkdir()
    return d


def _meta(b):
    return json.loads((b / "bundle.json").read_text())


def _set_meta(b, **changes):
    meta = _meta(b)
    for k, v in changes.items():
        if v is None:
            meta.pop(k)
        else:
            meta[k] = v
    (b / "bundle.json").write_text(json.dumps(meta))


def _write_exr(path, depth):
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"Z": np.ascontiguousarray(depth, np.float32)}).write(str(path))


def _proxy_with(b, **changes):
    with np.load(b / "proxy.npz") as z:
        arrays = {k: z[k] for k in z.files}
    for k, v in changes.items():
        if v is None:
            arrays.pop(k)
        else:
            arrays[k] = v(arrays[k]) if callable(v) else v
    np.savez(b / "proxy.npz", **arrays)


def _truncate(path, keep=0.5):
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def _camera0(b, key, value):
    meta = _meta(b)
    meta["cameras"][0][key] = value
    (b / "bundle.json").write_text(json.dumps(meta))


# name -> (corrupt(bundle), what the message must name, relative to the bundle ("" = the folder))
BUNDLE_CASES = {
    "version_other": (lambda b: _set_meta(b, version=99), ["bundle.json", "'version'", "99"]),
    "schema_other": (lambda b: _set_meta(b, schema="something-else"), ["bundle.json", "'schema'"]),
    "json_garbage": (lambda b: (b / "bundle.json").write_text("{ not json"), ["bundle.json", "not valid JSON"]),
    "json_list": (lambda b: (b / "bundle.json").write_text("[1, 2]"), ["bundle.json", "object"]),
    "field_cameras_missing": (lambda b: _set_meta(b, cameras=None), ["bundle.json", "'cameras' missing"]),
    "field_depthmaps_missing": (lambda b: _set_meta(b, depthmaps=None), ["bundle.json", "'depthmaps' missing"]),
    "field_origin_bad": (lambda b: _set_meta(b, origin=[1, 2]), ["bundle.json", "'origin'"]),
    "depthmaps_too_few": (lambda b: _set_meta(b, depthmaps=_meta(b)["depthmaps"][:-1]),
                          ["bundle.json", "'depthmaps' lists 11 files for 12 cameras"]),
    "camera_R_shape": (lambda b: _camera0(b, "R", [[1, 0, 0], [0, 1, 0]]), ["bundle.json", "cameras[0]", "'R'"]),
    "camera_width_zero": (lambda b: _camera0(b, "width", 0), ["bundle.json", "cameras[0]", "'width'"]),
    "no_bundle_json": (lambda b: (b / "bundle.json").unlink(), ["bundle.json", "missing"]),
    "depthmap_truncated": (lambda b: _truncate(b / "depthmaps" / "photo_0002.exr"),
                           ["photo_0002.exr", "truncated or corrupt"]),
    "depthmap_garbage": (lambda b: (b / "depthmaps" / "photo_0003.exr").write_bytes(b"\x76\x2f\x31\x01junk" * 9),
                         ["photo_0003.exr"]),
    "depthmap_wrong_size": (lambda b: _write_exr(b / "depthmaps" / "photo_0004.exr", np.ones((85, 128))),
                            ["photo_0004.exr", "128x85", "256x171"]),
    "depthmap_deleted": (lambda b: (b / "depthmaps" / "photo_0005.exr").unlink(), ["photo_0005.exr", "missing"]),
    "depthmap_no_Z": (lambda b: _write_exr_channel(b / "depthmaps" / "photo_0006.exr"), ["photo_0006.exr", "'Z'"]),
    "proxy_truncated": (lambda b: _truncate(b / "proxy.npz", 0.6), ["proxy.npz", "truncated"]),
    "proxy_not_zip": (lambda b: (b / "proxy.npz").write_bytes(b"this is not a zip file" * 40),
                      ["proxy.npz", "not an .npz"]),
    "proxy_npy": (lambda b: np.save(b / "proxy.npz.npy", np.zeros(3)) or (b / "proxy.npz.npy").rename(b / "proxy.npz"),
                  ["proxy.npz", "not an .npz"]),
    "proxy_deleted": (lambda b: (b / "proxy.npz").unlink(), ["proxy.npz", "missing"]),
    "proxy_missing_labels": (lambda b: _proxy_with(b, labels=None), ["proxy.npz", "'labels'"]),
    "proxy_positions_shape": (lambda b: _proxy_with(b, positions=lambda a: a[:, :2].copy()),
                              ["proxy.npz", "'positions'", "(n, 3)"]),
    "proxy_labels_dtype": (lambda b: _proxy_with(b, labels=lambda a: a.astype(np.float64)),
                           ["proxy.npz", "'labels'", "int32"]),
    "proxy_rows_differ": (lambda b: _proxy_with(b, radii=lambda a: a[:-1].copy()), ["proxy.npz", "'radii'", "rows"]),
    "proxy_labels_out_of_range": (lambda b: _proxy_with(b, labels=lambda a: np.where(np.arange(len(a)) == 7, 12, a)
                                                        .astype(np.int32)), ["proxy.npz", "'labels'", "12"]),
    "proxy_labels_negative": (lambda b: _proxy_with(b, labels=lambda a: np.full_like(a, -5)),
                              ["proxy.npz", "'labels'", "-5"]),
    "proxy_nan_positions": (lambda b: _proxy_with(b, positions=lambda a: np.where(a == a.max(), np.nan, a)
                                                  .astype(np.float32)), ["proxy.npz", "'positions'", "NaN"]),
    "photo_deleted": (lambda b: (b / "images" / PHOTO).unlink(), ["images/photo_0002.png", "missing"]),
    "photo_low_deleted": (lambda b: (b / "images_low" / PHOTO).unlink(), ["images_low/photo_0002.png", "missing"]),
}


def _write_exr_channel(path):
    import OpenEXR

    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"Y": np.ones((171, 256), np.float32)}).write(str(path))


@pytest.mark.parametrize("case", sorted(BUNDLE_CASES))
def test_bad_bundle(case, bundle_copy, out_dir, capfd):
    corrupt, names = BUNDLE_CASES[case]
    corrupt(bundle_copy)
    assert_bad_input(["render", bundle_copy, "--camera", PHOTO, "--width", 64, "--out", out_dir / "f.png"],
                     capfd, names, out_dir)


def test_bundle_partial_leftover(tiny_bundle, tmp_path, out_dir, capfd):
    """An interrupted preprocessing leaves only ``B.partial``: both ``B`` and ``B.partial`` are
    refused, naming the folder and saying what happened."""
    partial = tmp_path / "b.partial"
    shutil.copytree(tiny_bundle, partial)
    (partial / "bundle.json").unlink()
    line = assert_bad_input(["render", tmp_path / "b", "--camera", PHOTO, "--out", out_dir / "f.png"],
                            capfd, [tmp_path / "b", "b.partial", "interrupted"], out_dir)
    assert "not found" in line
    assert_bad_input(["render", partial, "--camera", PHOTO, "--out", out_dir / "f.png"],
                     capfd, [partial, "interrupted"], out_dir)


def test_bundle_missing_or_a_file(tmp_path, out_dir, capfd):
    assert_bad_input(["render", tmp_path / "nowhere", "--camera", PHOTO, "--out", out_dir / "f.png"],
                     capfd, [tmp_path / "nowhere", "not found"], out_dir)
    (tmp_path / "file").write_text("x")
    assert_bad_input(["render", tmp_path / "file", "--camera", PHOTO, "--out", out_dir / "f.png"],
                     capfd, [tmp_path / "file", "not a directory"], out_dir)


@pytest.mark.parametrize("folder", ["images", "images_low"])
@pytest.mark.parametrize("streaming", ["--async-photos", "--no-async-photos"])
def test_photo_corrupt_at_render_time(folder, streaming, bundle_copy, out_dir, capfd):
    """A photo whose file is garbage is found when the frame needs it (the full-resolution one
    once the first pass has chosen it, streamed on a thread or not): named, nothing written."""
    (bundle_copy / folder / PHOTO).write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 100)
    assert_bad_input(["render", bundle_copy, "--camera", PHOTO, "--width", 64, streaming, "--out",
                      out_dir / "f.png"], capfd, [f"{folder}/{PHOTO}", "cannot read image"], out_dir)


# -- render requests -------------------------------------------------------------------------------
# name -> (extra argv (OUT = the output file), what the message must name); all with --camera PHOTO
# unless the argv gives its own camera selection
RENDER_CASES = {
    "width_huge": (["--width", "100000"], ["--width", "100000x", "pixels a side"]),
    "height_huge": (["--height", "70000"], ["--height", "x70000", "pixels a side"]),
    "width_zero": (["--width", "0"], ["--width", "must be >= 1, not 0"]),
    "width_negative": (["--width", "-5"], ["--width", "must be >= 1, not -5"]),
    "height_negative": (["--height", "-1"], ["--height", "must be >= 1, not -1"]),
    "buffer_too_large": (["--width", "16384", "--visibility", "kbuffer", "--kbuffer-slots", "64"],
                         ["--width", "GiB"]),
    "dmt_width_huge": (["--method", "dmt", "--width", "100000"], ["--width", "pixels a side"]),
    "layers_zero": (["--layers", "0"], ["--layers", "0"]),
    "layers_negative": (["--layers", "-3"], ["--layers", "-3"]),
    "camera_unknown": (["--camera", "nope.png"], ["--camera", "no photo named 'nope.png'"]),
    "camera_and_pose": (["--pose", "POSE"], ["exactly one of --camera", "--camera and --pose"]),
    "camera_and_path": (["--path", "POSE"], ["exactly one of --camera", "--camera and --path"]),
    "out_suffix": (["--out", "OUTDIR/f.txt"], ["--out", "f.txt", ".png or .exr"]),
    "out_no_suffix": (["--out", "OUTDIR/frame"], ["--out", "frame", ".png or .exr"]),
    "out_is_folder": (["--out", "OUTDIR"], ["--out", "is a folder"]),
    "out_parent_is_file": (["--out", "OUTDIR/afile/f.png"], ["afile", "is a file"]),
    "stats_parent_is_file": (["--stats", "OUTDIR/afile/s.json"], ["afile", "--stats"]),
    "dump_stages_is_file": (["--dump-stages", "OUTDIR/afile"], ["--dump-stages", "afile", "is a file"]),
    # root passes permission checks there: only a write tells
    "out_unwritable": (["--out", "/proc/x.png"], ["/proc", "not writable", "--out"]),
}


@pytest.mark.parametrize("case", sorted(RENDER_CASES))
def test_bad_render_request(case, tiny_bundle, out_dir, tmp_path, capfd):
    extra, names = RENDER_CASES[case]
    (out_dir / "afile").write_text("a file, not a folder")
    pose = tmp_path / "pose.json"
    pose.write_text(json.dumps(camera_to_json(read_bundle(tiny_bundle).cameras[4])))
    extra = [a.replace("OUTDIR", str(out_dir)).replace("POSE", str(pose)) for a in extra]
    argv = ["render", tiny_bundle]
    if "--camera" not in extra:
        argv += ["--camera", PHOTO]
    if "--out" not in extra:
        argv += ["--out", out_dir / "f.png"]
    assert_bad_input(argv + extra, capfd, names, out_dir)


def test_neither_camera_nor_pose_nor_path(tiny_bundle, out_dir, capfd):
    assert_bad_input(["render", tiny_bundle, "--out", out_dir / "f.png"], capfd,
                     ["--camera", "exactly one of --camera IMAGE_NAME, --pose FILE or --path FILE"], out_dir)


def test_output_checked_before_the_bundle(tmp_path, out_dir, capfd):
    """An unsupported --out suffix fails before the bundle is even read, so long before any
    rendering: the bundle here does not exist, and the message is about --out."""
    assert_bad_input(["render", tmp_path / "no-bundle", "--camera", PHOTO, "--out", out_dir / "f.jpg"],
                     capfd, ["--out", "f.jpg"], out_dir)


def test_unknown_visibility_is_argparse_usage(tiny_bundle, out_dir, capfd):
    """An unknown choice is argparse's: usage, then one error line naming the option, exit 2."""
    with pytest.raises(SystemExit) as info:
        main(["render", str(tiny_bundle), "--camera", PHOTO, "--visibility", "sideways", "--out",
              str(out_dir / "f.png")])
    err = capfd.readouterr().err
    assert info.value.code == 2 and "Traceback" not in err
    assert err.splitlines()[-1].startswith("dmrt render: error: argument --visibility: invalid choice: 'sideways'")
    assert err.startswith("usage: dmrt render") and not any(out_dir.iterdir())


# -- camera poses (--pose) ---------------------------------------------------------------------------
def _pose_json(tiny_bundle, **changes):
    d = camera_to_json(read_bundle(tiny_bundle).cameras[4])
    for k, v in changes.items():
        if v is None:
            d.pop(k)
        else:
            d[k] = v
    return json.dumps(d)


POSE_CASES = {
    "not_json": (lambda b: "this is no JSON", ["not valid JSON"]),
    "empty_file": (lambda b: "", ["not valid JSON"]),
    "json_list": (lambda b: "[1, 2, 3]", ["JSON object", "list"]),
    "empty_object": (lambda b: "{}", ["'name'", "'R'", "missing"]),
    "missing_R": (lambda b: _pose_json(b, R=None), ["field 'R' missing"]),
    "R_2x3": (lambda b: _pose_json(b, R=[[1, 0, 0], [0, 1, 0]]), ["'R'", "3x3", "(2, 3)"]),
    "R_strings": (lambda b: _pose_json(b, R=[["a", "b", "c"]] * 3), ["'R'", "3x3 array of numbers"]),
    "R_not_rotation": (lambda b: _pose_json(b, R=[[2, 0, 0], [0, 2, 0], [0, 0, 2]]), ["'R'", "not a rotation"]),
    "t_two_numbers": (lambda b: _pose_json(b, t=[1.0, 2.0]), ["'t'", "3 numbers"]),
    "t_nan": (lambda b: _pose_json(b, t=[1.0, math.nan, 2.0]), ["'t'", "NaN"]),
    "fx_infinite": (lambda b: _pose_json(b, fx=math.inf), ["'fx'", "finite"]),
    "fx_negative": (lambda b: _pose_json(b, fx=-100.0), ["'fx'", "> 0"]),
    "width_zero": (lambda b: _pose_json(b, width=0), ["'width'", ">= 1"]),
    "width_string": (lambda b: _pose_json(b, width="wide"), ["'width'"]),
    "huge_camera": (lambda b: _pose_json(b, width=200000, height=100000), ["--width", "pixels a side"]),
}


@pytest.mark.parametrize("case", sorted(POSE_CASES))
def test_bad_pose(case, tiny_bundle, tmp_path, out_dir, capfd):
    make, names = POSE_CASES[case]
    pose = tmp_path / "pose.json"
    pose.write_text(make(tiny_bundle))
    if names[0] != "--width":
        names = [pose] + names
    assert_bad_input(["render", tiny_bundle, "--pose", pose, "--out", out_dir / "f.png"], capfd, names, out_dir)


def test_pose_folder_or_missing(tiny_bundle, tmp_path, out_dir, capfd):
    folder = tmp_path / "poses"
    folder.mkdir()
    assert_bad_input(["render", tiny_bundle, "--pose", folder, "--out", out_dir / "f.png"], capfd,
                     [folder, "is a folder"], out_dir)
    assert_bad_input(["render", tiny_bundle, "--pose", tmp_path / "nope.json", "--out", out_dir / "f.png"],
                     capfd, ["nope.json", "not found"], out_dir)


# -- camera paths (--path) ---------------------------------------------------------------------------
def _path_json(tiny_bundle, mutate=None):
    cams = [camera_to_json(c) for c in read_bundle(tiny_bundle).cameras[:3]]
    for c in cams:
        c.update(width=32, height=20, cx=16.0, cy=10.0, fx=20.0, fy=20.0)
    if mutate:
        mutate(cams)
    return json.dumps({"cameras": cams})


PATH_CASES = {
    "not_json": (lambda b: "[[[", ["not valid JSON"]),
    "no_cameras_key": (lambda b: json.dumps({"frames": []}), ["\"cameras\""]),
    "json_list": (lambda b: json.dumps([1, 2]), ["\"cameras\""]),
    "empty_path": (lambda b: json.dumps({"cameras": []}), ["empty camera path"]),
    "cameras_not_list": (lambda b: json.dumps({"cameras": {"a": 1}}), ["'cameras' must be a list"]),
    "camera_missing_t": (lambda b: _path_json(b, lambda cs: cs[1].pop("t")), ["cameras[1]", "'t' missing"]),
    "camera_R_shape": (lambda b: _path_json(b, lambda cs: cs[2].update(R=[1, 0, 0])), ["cameras[2]", "'R'", "3x3"]),
    "camera_nan": (lambda b: _path_json(b, lambda cs: cs[0].update(cy=math.nan)), ["cameras[0]", "'cy'"]),
    "camera_height_negative": (lambda b: _path_json(b, lambda cs: cs[1].update(height=-20)),
                               ["cameras[1]", "'height'"]),
    "camera_not_object": (lambda b: _path_json(b, lambda cs: cs.append("frame 4")), ["cameras[3]", "JSON object"]),
    "frame_too_large": (lambda b: _path_json(b, lambda cs: cs[1].update(width=50000, height=30000)),
                        ["--width", "pixels a side"]),
}


@pytest.mark.parametrize("case", sorted(PATH_CASES))
def test_bad_camera_path(case, tiny_bundle, tmp_path, out_dir, capfd):
    make, names = PATH_CASES[case]
    path = tmp_path / "path.json"
    path.write_text(make(tiny_bundle))
    if names[0] != "--width":
        names = [path] + names
    assert_bad_input(["render", tiny_bundle, "--path", path, "--out", out_dir / "walk"], capfd, names, out_dir)


def test_camera_path_folder_missing_and_outputs(tiny_bundle, tmp_path, out_dir, capfd):
    path = tmp_path / "path.json"
    path.write_text(_path_json(tiny_bundle))
    assert_bad_input(["render", tiny_bundle, "--path", tmp_path, "--out", out_dir / "walk"], capfd,
                     [tmp_path, "is a folder"], out_dir)
    assert_bad_input(["render", tiny_bundle, "--path", tmp_path / "none.json", "--out", out_dir / "walk"],
                     capfd, ["none.json", "not found"], out_dir)
    # --out must be a folder: an existing file is refused, as is a folder holding other files
    (out_dir / "afile").write_text("x")
    assert_bad_input(["render", tiny_bundle, "--path", path, "--out", out_dir / "afile"], capfd,
                     ["--out", "afile", "is a file"], out_dir)
    (out_dir / "mine").mkdir()
    (out_dir / "mine" / "notes.txt").write_text("precious")
    assert_bad_input(["render", tiny_bundle, "--path", path, "--out", out_dir / "mine"], capfd,
                     [out_dir / "mine", "not a walkthrough"], out_dir)


def test_walkthrough_interrupted_leaves_nothing(bundle_copy, out_dir, capfd):
    """A photo that turns out unreadable at the path's third frame stops the walkthrough after two
    frames were rendered: the error names it, and neither OUT nor OUT.partial is left."""
    path = out_dir.parent / "path.json"
    path.write_text(json.dumps({"cameras": [camera_to_json(c) for c in read_bundle(bundle_copy).cameras[:3]]}))
    (bundle_copy / "images" / PHOTO).write_bytes(b"\x89PNG\r\n\x1a\n" + b"garbage" * 100)
    assert_bad_input(["render", bundle_copy, "--path", path, "--width", 64, "--no-async-photos", "--out",
                      out_dir / "walk"], capfd, [f"images/{PHOTO}"], out_dir)


# -- scenes --------------------------------------------------------------------------------------------
def _scene_cases():
    from test_scene_errors import CASES

    return CASES


@pytest.mark.parametrize("case", sorted(_scene_cases()))
def test_bad_scene_preprocess(case, tmp_path, out_dir, capfd):
    """The scene corpus of test_scene_errors.py through ``dmrt preprocess``: one line naming the
    file, and no bundle (nor ``.partial``) left."""
    from test_scene_errors import CASES, make_scene

    scene = tmp_path / "scene"
    make_scene(scene)
    breaker, pattern = CASES[case]
    breaker(scene)
    line = assert_bad_input(["preprocess", scene, "--out", out_dir / "b", "--quiet"], capfd, [scene], out_dir)
    import re

    assert re.search(pattern, line), (pattern, line)


@pytest.mark.parametrize("model, coefficients", [("SIMPLE_RADIAL", "-1.0"), ("OPENCV_FISHEYE", "-0.9 0 0 0")])
def test_lens_that_folds_the_photo(model, coefficients, tmp_path, out_dir, capfd):
    """A distorted camera whose coefficients have no inverse out to the photo's border (the
    distortion folds it) cannot be undistorted: one line naming cameras.txt and the camera."""
    from test_scene_errors import make_scene

    scene = tmp_path / "scene"
    make_scene(scene)
    cameras = scene / "sparse" / "cameras.txt"
    lines = cameras.read_text().splitlines()
    cid, _, w, h, fx, fy, cx, cy = next(ln for ln in lines if ln.startswith("2 ")).split()
    head = f"{fx} {cx} {cy}" if model == "SIMPLE_RADIAL" else f"{fx} {fy} {cx} {cy}"
    cameras.write_text("\n".join(ln if not ln.startswith("2 ") else f"2 {model} {w} {h} {head} {coefficients}"
                                 for ln in lines) + "\n")
    assert_bad_input(["preprocess", scene, "--out", out_dir / "b", "--quiet"], capfd,
                     [cameras, f"camera 2 (line {len(lines)})", "fold"], out_dir)


def test_e57_scene_without_a_usable_image(tmp_path, out_dir, capfd):
    """A points.e57 without sparse/ is a scene only with a posed image: without images2D, one line
    naming sparse/ and the file; with only an unposed image, its warning line and then that line."""
    from test_e57 import pinhole_entry, write_raw_scans

    from dmrt.camera import Camera

    scene = tmp_path / "scene"
    scene.mkdir()
    xyz = {k: np.arange(3.0) for k in ("cartesianX", "cartesianY", "cartesianZ")}
    write_raw_scans(scene / "points.e57", [(xyz, None, None)])
    assert_bad_input(["preprocess", scene, "--out", out_dir / "b", "--quiet"], capfd,
                     [scene / "sparse", "points.e57 holds no image usable as a photo"], out_dir)
    cam = Camera.look_at("c", (0.0, -5.0, 1.0), (0.0, 0.0, 1.0), 16, 12)
    write_raw_scans(scene / "points.e57", [(xyz, None, None)],
                    [pinhole_entry("unposed", np.zeros((12, 16, 3), np.uint8), cam, pose=False)])
    capfd.readouterr()
    assert main(["preprocess", str(scene), "--out", str(out_dir / "b"), "--quiet"]) == 2
    err = capfd.readouterr().err.splitlines()
    assert err[0] == f"dmrt: warning: {scene / 'points.e57'}: image 0 ('unposed'): it has no pose; skipped"
    assert len(err) == 2 and err[1].startswith(f"dmrt: error: {scene / 'sparse'}: ") and "see the warnings" in err[1]
    assert not list(out_dir.iterdir())


def test_scene_missing_and_bundle_exists(tiny_scene, tiny_bundle, tmp_path, out_dir, capfd):
    assert_bad_input(["preprocess", tmp_path / "nowhere", "--out", out_dir / "b", "--quiet"], capfd,
                     [tmp_path / "nowhere"], out_dir)
    # an existing bundle is refused without --force, before the scene is read, and left as it was
    before = (tiny_bundle / "bundle.json").read_bytes()
    assert_bad_input(["preprocess", tiny_scene, "--out", tiny_bundle, "--quiet"], capfd,
                     [tiny_bundle, "exists", "--force"], tiny_bundle.parent)
    assert (tiny_bundle / "bundle.json").read_bytes() == before
    # the scene folder given as a file
    (tmp_path / "scene.txt").write_text("x")
    assert_bad_input(["preprocess", tmp_path / "scene.txt", "--out", out_dir / "b", "--quiet"], capfd,
                     ["scene.txt"], out_dir)


def test_synth_onto_existing_scene(tiny_scene, capfd):
    assert_bad_input(["scene", "synth", "--out", tiny_scene, "--quiet"], capfd, [tiny_scene, "exists"],
                     tiny_scene.parent)


# -- other commands ------------------------------------------------------------------------------------
PATH_COMMAND_CASES = {
    "frames_zero": (["--frames", "0"], ["--frames", "must be >= 1, not 0"]),
    "frames_negative": (["--frames", "-3"], ["--frames", "must be >= 1, not -3"]),
    "every_zero": (["--every", "0"], ["--every", ">= 1"]),
    "every_too_sparse": (["--every", "12"], ["--every", "at least 2"]),
    "width_negative": (["--width", "-640"], ["--width", ">= 1"]),
    "fov_out_of_range": (["--fov", "190"], ["--fov", "190"]),
    "out_suffix": (["--out", "OUTDIR/path.txt"], ["--out", "path.txt", ".json"]),
}


@pytest.mark.parametrize("case", sorted(PATH_COMMAND_CASES))
def test_bad_path_command(case, tiny_bundle, out_dir, capfd):
    extra, names = PATH_COMMAND_CASES[case]
    extra = [a.replace("OUTDIR", str(out_dir)) for a in extra]
    argv = ["path", tiny_bundle] + ([] if "--out" in extra else ["--out", out_dir / "p.json"])
    assert_bad_input(argv + extra, capfd, names, out_dir)


def test_report_on_missing_or_empty_results(tmp_path, out_dir, capfd):
    assert_bad_input(["report", tmp_path / "nores", "--out", out_dir / "rep"], capfd,
                     [tmp_path / "nores", "not found"], out_dir)
    (tmp_path / "empty").mkdir()
    assert_bad_input(["report", tmp_path / "empty", "--out", out_dir / "rep"], capfd,
                     [tmp_path / "empty"], out_dir)


# dmrt demo: every case is refused before the scene is made (out/scene would appear otherwise)
DEMO_CASES = {
    "width_zero": (["--width", "0"], ["--width", "not 0"]),
    "width_negative": (["--width", "-5"], ["--width", "not -5"]),
    "width_huge": (["--width", "100000"], ["--width", "4096", "not 100000"]),  # else minutes of ray casting
    "out_is_file": (["--out", "OUTDIR/afile"], ["--out", "afile", "is a file"]),
    "out_unwritable": (["--out", "/proc/demo"], ["/proc", "not writable"]),
}


@pytest.mark.parametrize("case", sorted(DEMO_CASES))
def test_bad_demo_request(case, out_dir, capfd):
    extra, names = DEMO_CASES[case]
    (out_dir / "afile").write_text("a file, not a folder")
    extra = [a.replace("OUTDIR", str(out_dir)) for a in extra]
    argv = ["demo", "--quiet"] + ([] if "--out" in extra else ["--out", out_dir / "demo"])
    assert_bad_input(argv + extra, capfd, names, out_dir)


def test_view_photo_out_of_range(tiny_bundle, out_dir, capfd):
    """Refused before a window opens (headless here), naming the option and the photos there are."""
    assert_bad_input(["view", tiny_bundle, "--window", "headless", "--photo", "99", "--screenshot",
                      out_dir / "s.png"], capfd, ["--photo", "99", "12 photos"], out_dir)


def test_view_missing_bundle(tmp_path, out_dir, capfd):
    assert_bad_input(["view", tmp_path / "nobundle", "--window", "headless", "--screenshot", out_dir / "s.png"],
                     capfd, [tmp_path / "nobundle", "not found"], out_dir)
    assert_bad_input(["view", tmp_path / "nobundle", "--window", "headless", "--frames", "0"],
                     capfd, ["--frames", ">= 1"], out_dir)


def test_reference_output_and_size_checked_first(tmp_path, out_dir, capfd):
    assert_bad_input(["reference", tmp_path / "noscene", "--camera", PHOTO, "--out", out_dir / "r.tiff"],
                     capfd, ["--out", "r.tiff"], out_dir)
    assert_bad_input(["reference", tmp_path / "noscene", "--camera", PHOTO, "--width", "0", "--out",
                      out_dir / "r.exr"], capfd, ["--width", ">= 1"], out_dir)


# -- configuration options (the dataclasses' bounds and choices: ConfigError naming the option) -------
CONFIG_CASES = {
    "render_max_steps_zero": (["render", "BUNDLE", "--camera", PHOTO, "--max-steps", "0", "--out", "OUTDIR/f.png"],
                              ["--max-steps", "0"]),
    "render_cache_negative": (["render", "BUNDLE", "--camera", PHOTO, "--cache-mb", "-1", "--out", "OUTDIR/f.png"],
                              ["--cache-mb", "-1"]),
    "render_tile_hits": (["render", "BUNDLE", "--camera", PHOTO, "--tile-hits", "6", "--out", "OUTDIR/f.png"],
                         ["--tile-hits", "6"]),
    "render_leveling_gain": (["render", "BUNDLE", "--camera", PHOTO, "--leveling-max-gain", "0.5", "--out",
                              "OUTDIR/f.png"], ["--leveling-max-gain", "0.5"]),
    "render_dmt_epsilon_negative": (["render", "BUNDLE", "--camera", PHOTO, "--method", "dmt", "--dmt-epsilon", "-1",
                                     "--out", "OUTDIR/f.png"], ["--dmt-epsilon", "-1"]),
    "render_dmt_resolution_zero": (["render", "BUNDLE", "--camera", PHOTO, "--method", "dmt", "--dmt-resolution", "0",
                                    "--out", "OUTDIR/f.png"], ["--dmt-resolution", "0"]),
    "preprocess_depthmap_width_zero": (["preprocess", "SCENE", "--out", "OUTDIR/b", "--depthmap-width", "0"],
                                       ["--depthmap-width", "0"]),
    "preprocess_normals_k": (["preprocess", "SCENE", "--out", "OUTDIR/b", "--normals-k", "1"], ["--normals-k", "1"]),
    "synth_points_zero": (["scene", "synth", "--out", "OUTDIR/s", "--points", "0"], ["--points", "0"]),
    "synth_photo_size": (["scene", "synth", "--out", "OUTDIR/s", "--photo-size", "4", "4"], ["--photo-size"]),
    "synth_room_size_order": (["scene", "synth", "--out", "OUTDIR/s", "--room-size", "6", "3"], ["--room-size"]),
    "synth_workers_zero": (["scene", "synth", "--out", "OUTDIR/s", "--workers", "0"], ["--workers", "0"]),
}


@pytest.mark.parametrize("case", sorted(CONFIG_CASES))
def test_bad_option(case, tiny_bundle, tiny_scene, out_dir, capfd):
    argv, names = CONFIG_CASES[case]
    argv = [a.replace("OUTDIR", str(out_dir)).replace("BUNDLE", str(tiny_bundle)).replace("SCENE", str(tiny_scene))
            for a in argv]
    assert_bad_input(argv, capfd, names, out_dir)


# -- missing optional dependencies: the real command in a fresh interpreter ---------------------------
def _run_without(module, argv, cwd):
    """``dmrt argv`` in a subprocess whose interpreter cannot import ``module``."""
    code = (f"import sys; sys.modules[{module!r}] = None\n"
            "from dmrt.app.cli import main\n"
            f"sys.exit(main({[str(a) for a in argv]!r}))")
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=300)


@pytest.mark.parametrize("module, argv, extra", [
    ("skimage", ["scene", "synth", "--preset", "tiny", "--quiet", "--out", "OUT/scene"], "bench"),
    ("pymeshlab", ["scene", "mesh", "SCENE", "--out", "OUT/mesh.ply"], "poisson"),
    ("pandas", ["report", "OUT", "--out", "OUT/report"], "bench"),
    # dmrt bench needs the whole extra before any work (each experiment failed alike without it)
    *[(m, ["bench", "--preset", "ci", "--out", "OUT/results", "--work", "OUT/work", "--scene", "SCENE"], "bench")
      for m in ("skimage", "pandas", "matplotlib")],
])
def test_missing_optional_dependency(module, argv, extra, tmp_path, out_dir):
    scene = tmp_path / "scene"
    scene.mkdir()
    argv = [a.replace("OUT", str(out_dir)).replace("SCENE", str(scene)) for a in argv]
    r = _run_without(module, argv, tmp_path)
    lines = r.stderr.splitlines()
    assert r.returncode == 2, r.stderr
    assert len(lines) == 1 and lines[0].startswith("dmrt: error: "), r.stderr
    assert f"'{module}'" in lines[0] and f"pip install -e '.[{extra}]'" in lines[0]
    assert "Traceback" not in r.stderr and not any(out_dir.iterdir())
    assert not (out_dir / "scene.partial").exists()


# -- Ctrl-C ------------------------------------------------------------------------------------------
def test_interrupted_preprocess_is_one_line_and_leaves_nothing(tiny_scene, out_dir):
    """Ctrl-C as a terminal sends it (SIGINT to the command's whole process group: the command and
    its worker processes) once preprocessing has started: one line, exit 130, no traceback from
    any process, and neither the bundle nor its ``.partial`` folder left."""
    import os
    import signal
    import time

    code = "import sys; from dmrt.app.cli import main; sys.exit(main(sys.argv[1:]))"
    bundle = out_dir / "b"
    p = subprocess.Popen([sys.executable, "-c", code, "preprocess", str(tiny_scene), "--out", str(bundle),
                          "--workers", "2", "--quiet"], start_new_session=True, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True,
                         preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))  # as a shell's job
    try:
        partial = bundle.with_name("b.partial")
        t0 = time.monotonic()
        while not partial.exists() and p.poll() is None and time.monotonic() - t0 < 120:
            time.sleep(0.05)  # the workers are started before the bundle's .partial folder is made
        assert partial.exists(), "preprocessing never started"
        time.sleep(0.5)
        os.killpg(p.pid, signal.SIGINT)
        out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
    assert p.returncode == 130, (p.returncode, err)
    assert err.splitlines() == ["dmrt: error: interrupted (Ctrl-C); no output was left half-written"], err
    assert not any(out_dir.iterdir()), list(out_dir.iterdir())
