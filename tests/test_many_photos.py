"""Thousands of photos (issue #39): the synthetic presets with many photos, and preprocessing more
photos than a texture array has layers (GL_MAX_ARRAY_TEXTURE_LAYERS = 2048 on Mesa and NVIDIA)."""

import json
from dataclasses import replace

import numpy as np
import pytest

from bench.scenes.synthetic import PRESETS, generate_scene


def test_many_preset_has_ten_thousand_photos_and_a_scaled_variant_is_deterministic(tmp_path):
    many = PRESETS["many"]
    assert many.photos >= 10_000 and many.photo_size == (1024, 684)
    assert many.photos / (many.rooms[0] * many.rooms[1]) == 80  # photos spread evenly over the rooms
    # the same 128 rooms, a few points and photos: the same files twice
    small = replace(many, points=20_000, photos=6, photo_size=(32, 21))
    one, two = (generate_scene(small, tmp_path / name, progress=False, workers=1) for name in ("one", "two"))
    for rel in ["points.ply", "sparse/images.txt", "images/photo_0005.png", "synthetic.json"]:
        assert (one / rel).read_bytes() == (two / rel).read_bytes(), rel
    meta = json.loads((one / "synthetic.json").read_text())
    assert len(meta["stations"]) == 128 and meta["config"]["name"] == "many"
    assert PRESETS["tiny-many"].photos == 2_100 > 2048 and PRESETS["tiny-many"].photo_size == (64, 43)


def test_bench_preprocess_reports_every_phase(tmp_path):
    from bench.bench_preprocess import main

    main(["--preset", "tiny", "--points", "20000", "--photos", "4", "--photo-size", "64", "43",
          "--depthmap-width", "64", "--work", str(tmp_path / "work"), "--out", str(tmp_path / "out")])
    result = json.loads((tmp_path / "out" / "preprocess-tiny.json").read_text())
    assert result["counts"]["photos"] == 4 and result["parameters"]["synth"]["photo_size"] == [64, 43]
    phases = ["octree_s", "normals_radii_s", "depthmaps_s", "proxies_s", "candidates_s", "labeling_s",
              "photometric_s", "photos_s"]
    for name in phases:
        assert result["seconds"][name] >= 0 and result["memory_mb"]["peak_rss_after_phase"][name] > 0
        assert name in result["memory_mb"]["peak_anon_per_phase"] and name in result["cpu_s_per_phase"]
    d = result["depthmaps"]
    assert d["splats_all"] == 4 * result["counts"]["points"] and 0 < d["splats"] <= d["splats_all"]
    assert not (tmp_path / "work").exists()  # without --keep


@pytest.mark.slow
def test_more_photos_than_a_texture_array_preprocess(tmp_path):
    """The tiny scene with 2,100 photos of 64x43 (the `tiny-many` preset): ~30 s to generate and
    ~90 s to preprocess on 2 CPU cores with Mesa (measured)."""
    from dmrt.io.bundle import read_bundle
    from dmrt.preprocess.pipeline import PreprocessConfig, preprocess

    scene = generate_scene(PRESETS["tiny-many"], tmp_path / "scene", progress=False)
    out = preprocess(scene, tmp_path / "bundle", PreprocessConfig(depthmap_width=64), progress=False)
    b = read_bundle(out)
    assert b.meta["counts"]["photos"] == len(b.cameras) == 2_100
    assert len({*b.meta["depthmaps"]}) == 2_100 and b.depth_map(2_099).shape == (43, 64)
    assert (b.proxy["labels"] >= 0).mean() > 0.9 and b.proxy["labels"].max() >= 2048  # labels beyond one array
    splats = b.meta["depthmap_splats"]
    assert splats["splats_all"] == 2_100 * b.meta["counts"]["points"] and splats["culled_fraction"] > 0.1
    assert np.isfinite(b.meta["photo_gains"]).all()
