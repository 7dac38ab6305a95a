"""The raytracing pass (paper Section 5.1.2) against its float64 numpy twin
(:func:`reference.twins.raytrace`) on the GPU's own layers, its step statistics, and the
variants: the coarse-splats ablation, hole filling from neighbours, the secant search.
"""

from __future__ import annotations

import numpy as np
import pytest

from helpers import W, novel_camera
from reference.twins import raytrace


@pytest.mark.parametrize("refine", ["bisection", "illinois"])
def test_raytracing_matches_numpy(ctx, bundle, depthmaps, refine):
    """The raytracing pass (the paper's adaptive search; the paper's bisection or the Illinois
    refinement) against its float64 numpy version on the GPU's own layers. Rounding can flip a
    decision (enclosure, discontinuity threshold) on a few pixels: >= 99.5 % of the pixels agree on
    hit / miss and layer, and common hits agree to 1e-4 relative depth (both refinements stop far
    below that: 20 halvings of a step, or |h| <= 1e-6 of the depth)."""
    from dmrt.runtime.renderer import RenderConfig, Renderer

    paper = Renderer(bundle, RenderConfig(layers=3, search="adaptive", fill_passes=0, async_photos=False,
                                          max_uploads_per_frame=0, refine=refine), ctx)
    for cam in (bundle.cameras[5].resized(W), novel_camera(bundle.cameras[6], bundle.cameras[7]).resized(W)):
        frame = paper.render(cam)
        layers = paper.layers()
        depth, layer = raytrace(cam, bundle.cameras, depthmaps, layers["depth"], layers["label"], refine=refine)
        assert np.mean((depth > 0) == (frame["depth"] > 0)) >= 0.995
        assert np.mean(layer == frame["layer_used"]) >= 0.995
        both = (depth > 0) & (frame["depth"] > 0)
        rel = np.abs(frame["depth"][both] - depth[both]) / depth[both]
        assert np.mean(rel <= 1e-4) >= 0.995
    paper.release()


def test_step_statistics_match_numpy(ctx, bundle, depthmaps):
    """``statistics=True`` (the paper's Figs. 9 and 10): the step counts and mean step lengths per
    layer and step index equal those of the float64 numpy search on the same layers. Rounding flips
    the decisions of <= 0.5 % of the pixels (see test_raytracing_matches_numpy), each changing a
    bin by at most one step: counts agree within 0.5 % of the layer's searches (its first bin), and
    mean lengths wherever a bin holds >= 50 steps within 2 % plus what its flipped steps can move
    it (the GPU sums lengths in 10 um fixed point, far below that)."""
    from dmrt.runtime.renderer import STEP_BINS, RenderConfig, Renderer

    r = Renderer(bundle, RenderConfig(layers=3, search="adaptive", statistics=True, method="compute", fill_passes=0,
                                      async_photos=False, max_uploads_per_frame=0), ctx)
    cam = novel_camera(bundle.cameras[6], bundle.cameras[7]).resized(W)
    frame = r.render(cam)
    layers = r.layers()
    steps = np.zeros((3, STEP_BINS, 2))
    raytrace(cam, bundle.cameras, depthmaps, layers["depth"], layers["label"], steps=steps)
    gpu = frame["step_stats"]
    assert gpu["count"].shape == (3, STEP_BINS) and gpu["count"][0, 0] > 1000
    assert (np.abs(gpu["count"] - steps[..., 0]) <= 0.005 * steps[:, :1, 0] + 1).all()
    # A bin's mean moves by each step one side has and the other lacks (a flipped pixel): by about
    # that step's length, within ~2x of the bin's mean, over the bin's count. So 2 % (rounding of
    # the kept steps) plus 2 x (count difference + 1) / count: 2.2 % for a bin of 9000 steps, 9 %
    # for one of 80 that differs by 2 steps (the late bins of a layer hold few steps).
    big = steps[..., 0] >= 50
    n = steps[..., 0][big]
    rtol = 0.02 + 2 * (np.abs(gpu["count"][big] - n) + 1) / n
    rel = np.abs(gpu["mean_step_m"][big] / (steps[..., 1][big] / n) - 1)
    assert (rel <= rtol).all(), (rel, rtol)
    r.release()


def test_coarse_splats_ablation(ctx, bundle):
    """``raytrace=False`` (the paper's Fig. 8a): the surface is the first splat layer itself."""
    from dmrt.runtime.renderer import RenderConfig, Renderer

    r = Renderer(bundle, RenderConfig(layers=2, raytrace=False, async_photos=False, max_uploads_per_frame=0), ctx)
    cam = bundle.cameras[3].resized(W)
    frame = r.render(cam)
    layer0 = r.layers()
    np.testing.assert_array_equal(frame["depth"], layer0["depth"][0])
    np.testing.assert_array_equal(frame["label_raw"], layer0["label"][0])
    assert (frame["iterations"] == 0).all()
    assert (frame["color"][frame["depth"] > 0].sum(-1) > 0).mean() > 0.99
    r.release()


def test_hole_filling_from_neighbours(ctx, bundle):
    """``fill_passes`` (an addition to the paper): a pixel that a splat covers but no layer gave a
    surface takes a hit in the depth map of a neighbour's label, within the discontinuity
    threshold of that neighbour's depth. Checked: it only fills (never changes a raytraced pixel),
    each filled pixel has such a neighbour from an earlier pass, the result is the same on every
    run (pass p reads only hits of earlier passes), and fewer holes remain. ``fill_max_steps``
    bounds each neighbour's search: a pixel's steps grow by at most passes x 8 x fill_max_steps."""
    from dmrt.runtime.renderer import RenderConfig, Renderer

    k = 1  # one layer leaves the most holes to fill
    sync = {"async_photos": False, "max_uploads_per_frame": 0, "layers": k}
    plain = Renderer(bundle, RenderConfig(fill_passes=0, **sync), ctx)
    filling = Renderer(bundle, RenderConfig(fill_passes=2, **sync), ctx)
    short = Renderer(bundle, RenderConfig(fill_passes=2, fill_max_steps=1, **sync), ctx)
    try:
        cam = novel_camera(bundle.cameras[6], bundle.cameras[7]).resized(W)
        a, b = plain.render(cam), filling.render(cam)
        again = filling.render(cam)
        np.testing.assert_array_equal(again["depth"], b["depth"])
        traced = a["layer_used"] >= 0
        np.testing.assert_array_equal(b["depth"][traced], a["depth"][traced])
        filled = b["layer_used"] >= k
        assert filled.sum() > 0.3 * (~traced & (plain.layers()["label"][0] >= 0)).sum()
        assert (a["layer_used"][filled] < 0).all()
        depth, label, layer = b["depth"], b["label_raw"], b["layer_used"]
        for y, x in zip(*np.nonzero(filled)):
            nb = [(depth[j, i], label[j, i]) for j in range(max(y - 1, 0), min(y + 2, depth.shape[0]))
                  for i in range(max(x - 1, 0), min(x + 2, depth.shape[1]))
                  if (j, i) != (y, x) and 0 <= layer[j, i] < layer[y, x]]
            assert any(lab == label[y, x] and abs(d - depth[y, x]) <= 0.2 + 1e-6 for d, lab in nb), (y, x)
        one = short.render(cam)
        assert (one["iterations"] - a["iterations"]).max() <= 2 * 8 * 1
        assert (b["iterations"] - a["iterations"]).max() > 2 * 8 * 1  # the default's searches run longer
        assert 0 < (one["layer_used"] >= k).sum() <= filled.sum()
    finally:
        plain.release()
        filling.release()
        short.release()


def test_secant_search_loses_fewer_pixels_than_the_papers(ctx, bundle):
    """The secant search (default) finds the surface wherever the paper's adaptive search does,
    give or take rounding, and more pixels overall."""
    from dmrt.runtime.renderer import RenderConfig, Renderer

    found = {}
    for search in ("adaptive", "secant"):
        r = Renderer(bundle, RenderConfig(layers=1, search=search, async_photos=False, max_uploads_per_frame=0), ctx)
        found[search] = [r.render(c, W)["depth"] > 0 for c in bundle.cameras[::3]]
        r.release()
    a, s = np.concatenate([x.ravel() for x in found["adaptive"]]), np.concatenate([x.ravel() for x in found["secant"]])
    assert s.sum() >= a.sum()
    assert np.mean(s[a]) >= 0.995

