"""The DMRT runtime renderer (paper Section 5) on a real GL context (Mesa llvmpipe in CI): the frame
contract, the configuration, the stage pictures, and whole frames against the Embree reference at
photo cameras and at novel viewpoints between photo cameras.

The stages have their own modules, each against its numpy twin (:mod:`reference.twins`):
test_visibility, test_raytracing, test_labeling_pass, test_texturing, test_leveling. All use the
test bundle of ``conftest.py`` (:func:`helpers.build_test_bundle`: exact depth maps, even proxies).
"""

from __future__ import annotations

import numpy as np
import pytest

from helpers import DM_WIDTH, W, novel_camera, reference_points, representable, silhouette_band, views_for_tests


@pytest.fixture(scope="module")
def scan_tree(tiny_scene, bundle):
    from scipy.spatial import cKDTree

    from dmrt.io.scene import load_scene

    return cKDTree(load_scene(tiny_scene).read_points().positions - bundle.origin)


def test_config_is_validated():
    """Bad options are ConfigErrors (ValueErrors) that name the option as the command line spells it."""
    from dmrt.errors import ConfigError
    from dmrt.runtime.renderer import RenderConfig

    with pytest.raises(ConfigError, match="^--method: must be one of 'tiles', 'compute', 'kbuffer', 'raster', not 'cuda'"):
        RenderConfig(method="cuda")
    with pytest.raises(ConfigError, match="^--discontinuity-test: .*'edge'"):
        RenderConfig(discontinuity_test="edge")
    with pytest.raises(ValueError, match="^--layers: must be >= 1, not 0"):
        RenderConfig(layers=0)
    with pytest.raises(ConfigError, match="^--leveling-max-gain: must be >= 1.0"):
        RenderConfig(leveling=True, leveling_max_gain=0.5)
    with pytest.raises(ConfigError, match="^--layers: the step statistics record at most 16 layers"):
        RenderConfig(layers=17, statistics=True)


def test_frame_contract(renderers, bundle):
    renderer = renderers[3]
    cam = bundle.cameras[0]
    frame = renderer.render(cam, W)  # height follows the aspect ratio
    h = round(W * cam.height / cam.width)
    assert frame["depth"].shape == (h, W) and frame["depth"].dtype == np.float32
    assert frame["color"].shape == (h, W, 3) and frame["color"].dtype == np.uint8
    assert frame["normal"].shape == (h, W, 3) and frame["normal"].dtype == np.float32
    for key in ("label", "label_raw", "layer_used", "iterations"):
        assert frame[key].shape == (h, W) and frame[key].dtype == np.int32, key
    assert set(frame["timings"]) == {"visibility", "raytracing", "labeling", "image_management", "texturing",
                                     "leveling"}
    assert frame["timings"]["leveling"] == 0.0  # off by default
    assert set(frame["cpu_ms"]) == {"status_read", "image_management"}
    hit = frame["depth"] > 0
    assert 0.5 < hit.mean() <= 1.0
    # background is background in every buffer, surface is surface in every buffer
    assert (frame["label"][~hit] == -1).all() and (frame["layer_used"][~hit] == -1).all()
    assert (frame["color"][~hit] == 0).all() and (frame["normal"][~hit] == 0).all()
    assert (frame["label"][hit] >= 0).all() and (frame["label_raw"][hit] >= 0).all()
    # layers 0..2, or 3..4 for a pixel filled from its neighbours in fill pass 0..1
    assert (frame["layer_used"][hit] >= 0).all() and (frame["layer_used"] < 3 + 2).all()
    assert (frame["iterations"][hit] >= 1).all()
    np.testing.assert_allclose(np.linalg.norm(frame["normal"][hit], axis=1), 1.0, atol=1e-4)
    # normals face the camera
    dirs, _ = cam.resized(W).pixel_rays()
    assert (np.einsum("ij,ij->i", frame["normal"].reshape(-1, 3), dirs)[hit.ravel()] < 0).all()
    # another size reallocates the frame buffers; the same size renders the same frame
    assert renderer.render(cam, 64, 40)["depth"].shape == (40, 64)
    again = renderer.render(cam, W)
    for key in ("depth", "label", "color", "normal", "iterations"):
        np.testing.assert_array_equal(again[key], frame[key], err_msg=key)
    # a frame left on the GPU (timing runs) returns its timings only, and changes nothing after it
    kept = renderer.render(bundle.cameras[1], W, readback=False)
    assert set(kept) == {"timings", "part_timings", "timings_lag", "cpu_ms"}
    assert set(kept["timings"]) == set(frame["timings"])
    # the timed parts of stages are named "stage:part" after stages of the frame
    assert kept["part_timings"] and {k.split(":")[0] for k in kept["part_timings"]} <= set(frame["timings"])
    # its search program leaves the normals' code out (NORMALS 0): the same surface as a frame read back
    c1 = bundle.cameras[1]
    pixels = [(x, y) for y in range(0, round(W * c1.height / c1.width), 7) for x in range(0, W, 9)]
    kept_depth = [renderer.depth_at(x, y) for x, y in pixels]
    shown = renderer.render(c1, W)["depth"]
    assert kept_depth == [float(shown[y, x]) for x, y in pixels]
    assert np.count_nonzero(kept_depth) > len(kept_depth) // 2
    after = renderer.render(cam, W)
    for key in ("depth", "label", "color"):
        np.testing.assert_array_equal(after[key], frame[key], err_msg=key)


def test_config_is_fixed_at_construction(renderers):
    """Programs and buffers are built from the configuration: changing it afterwards would be
    silently ignored, so it is refused."""
    import dataclasses

    r = renderers[1]
    with pytest.raises(AttributeError, match="fixed at construction"):
        r.config = dataclasses.replace(r.config, layers=3)
    assert r.config.layers == 1


def test_stage_images(renderers, bundle):
    """The Fig. 3 pictures of a frame: one distinct colour per label (and black for none), holes
    red exactly where a splat covers the pixel and no layer gave a surface."""
    from dmrt.io.frames import stage_images

    r = renderers[1]
    frame = r.render(novel_camera(bundle.cameras[6], bundle.cameras[7]).resized(W))
    splats = r.layers()["label"][0]
    images = stage_images(frame, splats)
    labels = np.unique(frame["label"])
    colours = {tuple(images["c_pixel_labels"][frame["label"] == j][0]) for j in labels}
    assert len(colours) == len(labels) and ((0, 0, 0) in colours) == (-1 in labels)
    red = np.all(images["holes"] == (255, 0, 0), axis=-1)
    holes = (frame["layer_used"] < 0) & (splats >= 0)
    assert holes.any()  # one layer leaves holes at this view
    np.testing.assert_array_equal(red, holes)
    assert images["b_raytraced_depth"][frame["depth"] == 0].max() == 0


@pytest.mark.slow
def test_against_embree_reference(renderers, bundle, depthmaps, reference, scan_tree):
    """Depth and holes against the Embree ground truth at photo cameras and novel viewpoints.

    Evaluated on the pixels whose reference surface point DMRT can show at all: scanned (a scan
    point within 5 cm: the proxies are scan points) and representable (some depth map holds it on
    a quad that passes the 20 cm discontinuity test; see :func:`representable`).
    * median |dz| <= the median depth-map texel footprint (``texel_footprint`` of the label that
      was raytraced): the search converges onto the depth map's surface, exact for planes;
    * with 3 layers at most 0.5 % of those pixels are holes away from silhouettes (2 px from a
      reference depth jump) and at most 2 % including silhouettes, where every depth map's quads
      straddle the edge (the paper's Fig. 13); holes do not increase from 1 to 3 layers.
    """
    from reference.metrics import compare, texel_footprint

    rows = []
    holes = {k: [0, 0, 0, 0] for k in renderers}  # smooth holes, smooth pixels, all holes, all pixels
    dz_all, fp_all = [], []
    for cam in views_for_tests(bundle.cameras):
        cam = cam.resized(W)
        ref = reference.render(cam)
        pts = reference_points(cam, ref["depth"])
        dist, _ = scan_tree.query(pts - bundle.origin, distance_upper_bound=0.05)
        ok = (representable(pts, bundle.cameras, depthmaps) & np.isfinite(dist)).reshape(ref["depth"].shape)
        ok &= ref["depth"] > 0
        smooth = ok & ~silhouette_band(ref["depth"])
        row = {"view": cam.name, "eval": round(float(ok.mean()), 3)}
        for k, renderer in renderers.items():
            frame = renderer.render(cam)
            hole = frame["depth"] == 0
            h = holes[k]
            h[0] += int((hole & smooth).sum()); h[1] += int(smooth.sum())
            h[2] += int((hole & ok).sum()); h[3] += int(ok.sum())
            row[f"holes_{k}"] = round(float((hole & ok).sum() / max(ok.sum(), 1)), 4)
            if k == 3:
                both = ok & ~hole
                dz = np.abs(frame["depth"][both].astype(np.float64) - ref["depth"][both])
                fp = texel_footprint(reference_points(cam, frame["depth"])[both.ravel()],
                                     frame["label_raw"][both], bundle.cameras, DM_WIDTH)
                dz_all.append(dz)
                fp_all.append(fp)
                c = compare(frame, ref)
                row.update(median_dz_mm=round(1e3 * float(np.median(dz)), 4),
                           p95_dz_mm=round(1e3 * float(np.percentile(dz, 95)), 2),
                           footprint_mm=round(1e3 * float(np.median(fp)), 2), psnr_db=round(c["psnr_db"], 2))
        rows.append(row)
    for row in rows:
        print(row)
    rate = {k: (h[0] / h[1], h[2] / h[3]) for k, h in holes.items()}
    print("hole rate (smooth, all) per layer count:", {k: (round(a, 5), round(b, 5)) for k, (a, b) in rate.items()})
    dz, fp = np.concatenate(dz_all), np.concatenate(fp_all)
    print(f"median |dz| {np.median(dz):.2e} m, median footprint {np.median(fp):.2e} m")
    assert np.median(dz) <= np.median(fp)
    assert rate[3][0] <= 0.005 and rate[3][1] <= 0.02
    assert rate[1][0] >= rate[2][0] >= rate[3][0] and rate[1][1] >= rate[2][1] >= rate[3][1]
    assert rate[1][1] > rate[3][1]  # the extra layers are needed here (paper Fig. 13)
