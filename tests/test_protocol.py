"""One renderer interface: DMRT, DMT and the Embree reference all satisfy FrameRenderer and return
the same frame contract at the same camera; only DMRT has label layers."""

import numpy as np
import pytest

from dmrt.io.bundle import read_bundle
from dmrt.io.scene import load_scene
from dmrt.runtime.protocol import FrameRenderer, LayeredRenderer

pytestmark = pytest.mark.gpu


def test_every_renderer_speaks_the_protocol(ctx, tiny_scene, tiny_bundle):
    from baselines.dmt import DMTConfig, DMTRenderer
    from dmrt.runtime.renderer import RenderConfig, Renderer
    from reference.render import EmbreeReference

    bundle = read_bundle(tiny_bundle)
    renderers = [Renderer(bundle, RenderConfig(layers=2, async_photos=False), ctx),
                 DMTRenderer(bundle, DMTConfig(width=64, labeler="own", progress=False), ctx=ctx),
                 EmbreeReference.from_scene(load_scene(tiny_scene))]
    camera = bundle.cameras[0]
    frames = {}
    for r in renderers:
        assert isinstance(r, FrameRenderer), r.name
        assert isinstance(r, LayeredRenderer) == (r.name == "dmrt")
        frame = r.render(camera, 64, 43)
        assert r.flush_photos() >= 0
        frames[r.name] = frame
        r.release()
    assert sorted(frames) == ["dmrt", "dmt", "embree"]
    for name, f in frames.items():
        assert f["depth"].shape == (43, 64) and f["depth"].dtype == np.float32, name
        assert f["label"].dtype == np.int32 and f["color"].shape == (43, 64, 3) and f["color"].dtype == np.uint8
        assert f["normal"].shape == (43, 64, 3) and isinstance(f["timings"], dict)
        # the photo camera sees the scene's surface in most pixels whichever renderer draws it
        assert (f["depth"] > 0).mean() > 0.5, name
