"""Shared fixtures: one headless GL context per test session (moderngl's own test style), the
scenes and bundles, and the renderer tests' session-wide inputs (built once per run).

Every test that uses ``ctx`` is checked for a clean GL error flag before and after it runs, so a
GL error is reported by the test that caused it rather than by whichever test reads it next.

Markers (declared in ``pyproject.toml``): ``gpu`` is given here to every test that uses a fixture
needing a GL context (:data:`GL_FIXTURES`), and explicitly where a test makes its own; ``slow`` and
``e2e`` are set in the test modules. Plain helpers live in ``helpers.py``.
"""

import pytest

# fixtures that need a GL context (directly, or because building them splats on the GPU)
GL_FIXTURES = frozenset({"ctx", "tiny_bundle", "ci_run"})


def pytest_collection_modifyitems(config, items):
    for item in items:
        if GL_FIXTURES.intersection(getattr(item, "fixturenames", ())):
            item.add_marker(pytest.mark.gpu)


@pytest.fixture(scope="session")
def ctx():
    """The process-wide moderngl context (EGL; Mesa llvmpipe in CI)."""
    from dmrt.gl import get_context

    return get_context()


@pytest.fixture(autouse=True)
def _gl_error_check(request):
    if "ctx" not in request.fixturenames:
        yield
        return
    ctx = request.getfixturevalue("ctx")
    assert ctx.error == "GL_NO_ERROR", "a GL error was pending before this test"
    yield
    assert ctx.error == "GL_NO_ERROR"


@pytest.fixture(scope="session")
def tiny_scene(tmp_path_factory):
    """The ``tiny`` synthetic scene (≈200k points, 12 photos), generated once per session."""
    from bench.scenes.synthetic import PRESETS, generate_scene

    return generate_scene(PRESETS["tiny"], tmp_path_factory.mktemp("scenes") / "tiny", progress=False)


@pytest.fixture(scope="session")
def tiny_bundle(tiny_scene, tmp_path_factory):
    """The tiny scene preprocessed (256-wide depth maps: the photos' own resolution)."""
    from dmrt.preprocess.pipeline import PreprocessConfig, preprocess

    out = tmp_path_factory.mktemp("bundles") / "tiny"
    return preprocess(tiny_scene, out, PreprocessConfig(depthmap_width=256), progress=False)


@pytest.fixture(scope="session")
def reference(tiny_scene):
    """The Embree ground truth of the tiny scene (its reference mesh, textured from the photos)."""
    from dmrt.io.scene import load_scene
    from reference.render import EmbreeReference

    return EmbreeReference.from_scene(load_scene(tiny_scene))


# -- the renderer tests' inputs (test_renderer, test_visibility, test_raytracing, ...) -----------
@pytest.fixture(scope="session")
def bundle(tiny_scene, tmp_path_factory):
    """The renderer test bundle of the tiny scene (:func:`helpers.build_test_bundle`: exact depth
    maps, even proxies). test_dmt overrides this name with a copy of ``tiny_bundle``."""
    from helpers import build_test_bundle

    return build_test_bundle(tiny_scene, tmp_path_factory.mktemp("bundles") / "tiny.bundle")


@pytest.fixture(scope="session")
def depthmaps(bundle):
    """The test bundle's depth maps: list of (h, w) float32, one per photo."""
    return [bundle.depth_map(i) for i in range(len(bundle.cameras))]


@pytest.fixture(scope="session")
def renderers(ctx, bundle):
    """One renderer per layer count (the same GL context), the fixed labels, synchronous photo
    streaming so that colours are deterministic; released at the end of the session."""
    from dmrt.runtime.renderer import RenderConfig, Renderer

    # the paper's fixed labels, which the twins of the labeling and texturing passes compute
    # (tests/test_view_choice.py tests the view-dependent choice)
    cfg = {"async_photos": False, "max_uploads_per_frame": 0, "photo_choice": "labels"}
    out = {k: Renderer(bundle, RenderConfig(layers=k, **cfg), ctx) for k in (1, 2, 3)}
    yield out
    for r in out.values():
        r.release()
