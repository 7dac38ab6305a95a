"""Shared fixtures: one headless GL context per test session (moderngl's own test style).

Every test that uses ``ctx`` is checked for a clean GL error flag before and after it runs, so a
GL error is reported by the test that caused it rather than by whichever test reads it next.
"""

import pytest


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
    from dmrt.preprocess import PreprocessConfig, preprocess

    out = tmp_path_factory.mktemp("bundles") / "tiny"
    return preprocess(tiny_scene, out, PreprocessConfig(depthmap_width=256), progress=False)
