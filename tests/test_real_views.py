"""The real_views experiment (bench/real_views.py): photos held out of preprocessing, rendered at
their cameras and compared with them; its metrics on image pairs of known error; its report
section."""

from __future__ import annotations

import json

import numpy as np
import pytest

from bench.real_views import VARIANTS, RealViewsParams, holdout_indices, psnr, psnr_matched, select_variants, ssim
from reference.metrics import flip


def _image(seed: int = 0, h: int = 40, w: int = 60) -> np.ndarray:
    rng = np.random.default_rng(seed)
    base = rng.integers(40, 200, (h // 4, w // 4, 3)).astype(np.uint8)
    return np.repeat(np.repeat(base, 4, axis=0), 4, axis=1)


def test_psnr_and_ssim_on_known_pairs():
    """PSNR of an image and the same image with a constant offset d is 20 log10(255 / d); over a mask
    only the masked pixels count; SSIM of an image with itself is 1 (also masked), and lower for a
    noisy copy; the exposure-matched PSNR takes a global gain out."""
    img = _image()
    mask = np.ones(img.shape[:2], bool)
    for d in (1, 5, 20):
        assert psnr(img + np.uint8(d), img, mask) == pytest.approx(20 * np.log10(255 / d), abs=1e-9)
    half = mask.copy()
    half[:, 30:] = False
    other = img.copy()
    other[:, 30:] = 0  # differs only outside the mask
    other[:, :30] += 10
    assert psnr(other, img, half) == pytest.approx(20 * np.log10(255 / 10), abs=1e-9)
    assert psnr(img, img, mask) == np.inf and np.isnan(psnr(img, img, np.zeros_like(mask)))
    assert ssim(img, img, mask) == pytest.approx(1.0, abs=1e-12)
    assert ssim(img, other - np.uint8(10) * half[..., None], half) == pytest.approx(1.0, abs=1e-12)
    noisy = np.clip(img + np.random.default_rng(1).normal(0, 20, img.shape), 0, 255).astype(np.uint8)
    assert 0.0 < ssim(noisy, img, mask) < 0.9
    darker = np.rint(img * 0.8).astype(np.uint8)
    assert psnr(darker, img, mask) < 25 and psnr_matched(darker, img, mask) > 45


def test_flip_on_known_pairs():
    """FLIP (flip-evaluator) is 0 for equal images, grows with the difference, counts only the
    masked pixels (a difference outside the mask is invisible) and gives a map of the frame's
    size in 0..1; nan on an empty mask."""
    img = _image()
    mask = np.ones(img.shape[:2], bool)
    same, fmap = flip(img, img, mask)
    assert same == 0.0 and fmap.shape == mask.shape and fmap.dtype == np.float32
    small, big = (flip(np.clip(img.astype(int) + d, 0, 255).astype(np.uint8), img, mask)[0] for d in (8, 40))
    assert 0 < small < big <= 1
    half = mask.copy()
    half[:, 30:] = False
    other = img.copy()
    other[:, 30:] = 255 - other[:, 30:]  # differs only outside the mask
    inside, omap = flip(other, img, half)
    # FLIP's spatial filters reach a few pixels over the mask's edge, where both images are black
    assert inside == 0.0 and omap[~half].max() == 0.0
    assert flip(other, img, mask)[0] > 0.1
    assert np.isnan(flip(img, img, np.zeros_like(mask))[0])


def test_select_variants():
    """Variants by name or pattern, in VARIANTS' order; a name that selects nothing is refused
    (also when the parameters are made); dmrt-view is the view-dependent photo choice, every
    other RenderConfig variant pins the fixed labels."""
    assert select_variants([]) == list(VARIANTS)
    assert select_variants(["dmt+gains", "dmrt"]) == ["dmrt", "dmt+gains"]
    assert set(select_variants(["dmrt*"])) == {v for v in VARIANTS if v.startswith("dmrt")}
    assert "dmt" not in select_variants(["dmrt*", "splats"])
    with pytest.raises(ValueError, match="--variants dtm"):
        select_variants(["dmrt", "dtm"])
    with pytest.raises(ValueError, match="no such real_views variant"):
        RealViewsParams(variants=("nope",))
    assert VARIANTS["dmrt-view"][1]["photo_choice"] == "view"
    assert all(o["photo_choice"] == "labels" for k, (r, o) in VARIANTS.items() if r != "dmt" and "view" not in k)


def test_report_reads_a_result_before_the_bounds(tmp_path):
    """A real_views result of version 1 (no FLIP, bounds or walkthrough: reports/history keeps
    them) still gives its section, without the bounds' tables."""
    from pathlib import Path

    from bench.report import ResultSet, Table, section_real_views

    old = Path(__file__).parents[1] / "reports/history/nvidia-h200-pcie-sse2/fdb23828dc27-paper/real_views.json"
    if not old.is_file():
        pytest.skip(f"{old} is not in this checkout")
    rs = ResultSet(tmp_path, "machine", "abc", "paper", experiments={"real_views": json.loads(old.read_text())})
    s = section_real_views(rs, tmp_path)
    tables = [b.name for b in s.blocks if isinstance(b, Table)]
    assert tables == ["real_views", "real_views_per_photo", "real_views_sources"]
    assert s.blocks[-1] == "No figure: real_views's image maps (.npz) are not in the results folder."


def test_holdout_indices():
    """Every N-th photo from photo 0 (the field's every 8th); N < 2 or a single photo: a clear error."""
    assert holdout_indices(12, 8) == [0, 8]
    assert holdout_indices(6, 8) == [0] and holdout_indices(6, 2) == [0, 2, 4]
    with pytest.raises(ValueError, match="holdout-every 1"):
        holdout_indices(12, 1)
    with pytest.raises(ValueError, match="1 photo"):
        holdout_indices(1, 8)


@pytest.mark.gpu
@pytest.mark.slow
def test_real_views_on_tiny(tiny_scene, tmp_path):
    """``dmrt bench --only real_views`` on the tiny scene (every 8th photo held out): photos 0 and 8 are
    not in the bundle (no camera, photo or depth map of theirs), every variant has finite PSNR/SSIM
    on part of each view, and the report has the section. The global gains make the photos a frame
    is textured from agree: the PSNR left once the held-out photo's own exposure (which nothing in
    the bundle can know) is matched rises, measured 22.2 -> 24.8 dB (DMRT and DMT alike). The plain
    PSNR then depends on how that photo's exposure compares with its group's mean: 19.9 -> 19.8 dB
    here; over --holdout-every 3..8 on this scene (2-4 views each) -2.3 .. +0.2 dB, on the small
    preset's 6 views +1.6 dB."""
    from bench.experiments import EXPERIMENTS
    from bench.real_views import VARIANTS
    from dmrt.app.cli import main

    results, work = tmp_path / "results", tmp_path / "work"
    assert main(["bench", "--preset", "ci", "--scene", str(tiny_scene), "--only", "real_views",
                 "--out", str(results), "--work", str(work), "--quiet"]) == 0
    (path,) = results.glob("*/*/real_views.json")
    r = json.loads(path.read_text())
    assert r["version"] == EXPERIMENTS["real_views"].version and r["parameters"]["holdout_every"] == 8
    m = r["measurements"]
    assert m["held_out"] == ["photo_0000.png", "photo_0008.png"] and m["kept"] == 10

    meta = json.loads((work / "real_views-every8" / "bundle" / "bundle.json").read_text())
    names = [c["name"] for c in meta["cameras"]]
    assert len(names) == 10 and not set(m["held_out"]) & set(names)
    files = " ".join(meta["images"] + meta["images_low"] + meta["depthmaps"])
    assert "photo_0000" not in files and "photo_0008" not in files
    depthmaps = {p.name for p in (work / "real_views-every8" / "bundle" / "depthmaps").iterdir()}
    assert len(depthmaps) == 10 and not {"photo_0000.exr", "photo_0008.exr"} & depthmaps

    rows = {v["variant"]: v for v in m["variants"]}
    assert set(rows) == set(VARIANTS)
    for v in rows.values():
        for view in v["views"]:
            assert 0.05 < view["surface_share"] <= 1.0
            assert 8 < view["psnr_db"] < 60 and 0 < view["ssim"] <= 1
    # the coarse splats cover more of the frame than the raytraced surface, and look worse on it
    assert rows["splats"]["mean_surface_share"] >= rows["dmrt"]["mean_surface_share"]
    assert rows["splats"]["mean_psnr_common_db"] < rows["dmrt"]["mean_psnr_common_db"]
    print({k: (round(v["mean_psnr_db"], 2), round(v["mean_psnr_matched_db"], 2)) for k, v in rows.items()})
    assert rows["dmrt+gains"]["mean_psnr_matched_db"] > rows["dmrt"]["mean_psnr_matched_db"] + 1.0
    assert rows["dmt+gains"]["mean_psnr_matched_db"] > rows["dmt"]["mean_psnr_matched_db"] + 1.0
    assert m["gain_recovery"]["log_spread_after"] < 0.5 * m["gain_recovery"]["log_spread_before"]
    # FLIP beside PSNR; the walkthrough's change (8-bit levels: a few, not tens, for renderers
    # whose photo choice is fixed per proxy); each variant's cost in seconds
    for v in rows.values():
        assert all(0 < view["flip"] < 1 for view in v["views"])
        assert 0 < v["stability"]["mean"] < 10 and len(v["stability"]["per_pair"]) == m["walkthrough"]["frames"] - 1
        assert v["seconds"] > 0
    # the bounds, through the tiny scene's mesh: on nearly all the common pixels for the per-pixel
    # choice, and every variant measured on the same pixels
    assert m["bounds"]["geometry"].startswith("the reference mesh") and m["bounds"]["seconds_per_view"] > 0
    for view in m["views"]:
        b = view["bounds"]
        assert b["view_closest"]["share"] > 0.9 and 10 < b["view_closest"]["psnr_db"] < 60
        assert b["best_single"]["photo"] in names and 0 < b["best_single"]["flip"] < 1
    assert all(8 < r["mean_view_closest_pixels_psnr_db"] < 60 for r in rows.values())

    report = tmp_path / "report"
    assert main(["report", str(results), "--out", str(report)]) == 0
    md = (report / "REPORT.md").read_text()
    assert "## Real views" in md and "figures/real_views.png" in md and "csv/real_views.csv" in md
    assert "csv/real_views_vs_bounds.csv" in md and "csv/real_views_bounds_per_photo.csv" in md
    assert (report / "figures" / "real_views.png").stat().st_size > 10_000


def test_holdout_every_reaches_the_experiment(tmp_path, monkeypatch):
    """``run_bench(holdout_every=N, variants=[...])`` (``dmrt bench --holdout-every N --variants
    ...``) sets the parameters of the experiments that have them, and the result file records them."""
    from bench import experiments
    from bench.harness import run_bench

    seen = []
    exp = experiments.EXPERIMENTS["real_views"]
    monkeypatch.setitem(experiments.EXPERIMENTS, "real_views", experiments.Experiment(
        exp.title, exp.version, lambda ws, p, out: seen.append(p) or {"ok": 1}, exp.params))
    status = run_bench("ci", tmp_path / "r", work=tmp_path / "w", only=["real_views"], progress=False,
                       holdout_every=3, variants=["dmrt*"])
    assert [(p.holdout_every, p.variants) for p in seen] == [(3, ("dmrt*",))]
    params = json.loads(status["written"]["real_views"].read_text())["parameters"]
    assert params["holdout_every"] == 3 and params["variants"] == ["dmrt*"]


def test_holdout_every_must_leave_photos(tmp_path, capsys):
    """``--holdout-every 1`` is refused with one line, before anything runs."""
    from dmrt.app.cli import main

    assert main(["bench", "--only", "real_views", "--holdout-every", "1", "--out", str(tmp_path / "r"),
                 "--work", str(tmp_path / "w")]) == 2
    err = capsys.readouterr().err
    assert "--holdout-every 1" in err and not (tmp_path / "r").exists()


def test_unknown_variant_is_refused(tmp_path, capsys):
    """``--variants`` with a name that selects nothing: one line naming it, exit 2, nothing written."""
    from dmrt.app.cli import main

    assert main(["bench", "--only", "real_views", "--variants", "dmrt", "dtm", "--out", str(tmp_path / "r"),
                 "--work", str(tmp_path / "w")]) == 2
    err = capsys.readouterr().err.strip()
    assert "--variants dtm" in err and len(err.splitlines()) == 1 and not (tmp_path / "r").exists()
