"""The labeling pass (paper Section 5.2.1) against its numpy twin
(:func:`reference.twins.labeling_pass`, the geometry-aware Voronoi labels), and its effect on
silhouettes and occluded photos against the Embree reference.
"""

from __future__ import annotations

import numpy as np
import pytest

from helpers import W, reference_points, silhouette_band, views_for_tests
from reference.twins import labeling_pass, visible_in_depth_map


@pytest.mark.slow
def test_labeling_pass(ctx, bundle, depthmaps, reference):
    """The labeling pass (paper 5.2.1) is the Voronoi decomposition it claims to be, and it removes
    false labels at silhouettes.

    * Without the label check, the GPU labels equal the numpy Voronoi labels (nearest covering
      proxy in 3D) on >= 99 % of the hit pixels (distance ties and rim pixels may flip).
    * Near silhouettes (3 px of a reference depth jump) fewer pixels carry a label other than the
      reference's best photo than with the raw layer labels (Fig. 6: a silhouette splat's label
      leaks onto the background it overlaps).
    * With the label check (default) no more pixels than with raw labels are given a photo whose
      depth map does not see the pixel's point (2 cm + 2 texels), i.e. an occluded photo.
    """
    from dmrt.runtime.renderer import RenderConfig, Renderer

    plain = Renderer(bundle, RenderConfig(layers=3, label_check=False, photo_choice="labels"), ctx)
    checked = Renderer(bundle, RenderConfig(layers=3, photo_choice="labels"), ctx)
    try:
        cam = bundle.cameras[4].resized(64)
        frame = plain.render(cam)
        vor = labeling_pass(cam.relative_to(bundle.origin), bundle.proxy, frame["depth"])
        hit = frame["depth"] > 0
        assert np.mean(frame["label"][hit] == vor[hit]) >= 0.99

        wrong_raw = wrong_lab = occluded_raw = occluded_lab = 0
        for cam in views_for_tests(bundle.cameras, 3, 3):
            cam = cam.resized(W)
            frame = checked.render(cam)
            ref = reference.render(cam)
            band = silhouette_band(ref["depth"], px=3) & (frame["depth"] > 0) & (ref["label"] >= 0)
            wrong_raw += int((frame["label_raw"] != ref["label"])[band].sum())
            wrong_lab += int((frame["label"] != ref["label"])[band].sum())
            pts = reference_points(cam, frame["depth"])
            hit = (frame["depth"] > 0).ravel()
            for key in ("label_raw", "label"):
                labels = frame[key].ravel()
                seen = np.zeros(len(pts), bool)
                for j in np.unique(labels[hit]):
                    m = hit & (labels == j)
                    seen[m] = visible_in_depth_map(bundle.cameras[j], depthmaps[j], pts[m], slack=0.02)
                n = int((hit & ~seen).sum())
                if key == "label":
                    occluded_lab += n
                else:
                    occluded_raw += n
        print(f"silhouette pixels with a label other than the reference's: raw {wrong_raw}, labeled {wrong_lab}; "
              f"pixels textured from a photo that does not see them: raw {occluded_raw}, labeled {occluded_lab}")
        assert wrong_lab < 0.95 * wrong_raw
        assert occluded_lab <= occluded_raw + 10
    finally:
        plain.release()
        checked.release()
