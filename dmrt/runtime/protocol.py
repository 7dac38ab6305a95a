"""The one renderer interface: DMRT (:class:`dmrt.runtime.renderer.Renderer`), the DMT baseline
(``baselines.dmt.DMTRenderer``) and the Embree ground truth (``reference.render.EmbreeReference``)
are used the same way by the command line, the viewer and the benchmarks.

    renderer: FrameRenderer = Renderer(read_bundle(path), RenderConfig(layers=3))
    frame = renderer.render(camera, 1280, 720)   # the frame contract of dmrt.io.frames
    if isinstance(renderer, LayeredRenderer):    # only DMRT has label layers
        splat_labels = renderer.layers()["label"][0]
    if isinstance(renderer, GpuColorRenderer):   # DMRT and DMT: a frame left on the GPU can be shown
        colors = renderer.gpu_colors()
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from dmrt.camera import Camera


@runtime_checkable
class FrameRenderer(Protocol):
    """Renders frames of one scene.

    ``name`` names the method (``"dmrt"``, ``"dmt"``, ``"embree"``); ``gpu_bytes`` is the GPU
    memory per resource in bytes (empty for a CPU renderer).
    """

    name: str
    gpu_bytes: dict

    def render(self, camera: Camera, width: int | None = None, height: int | None = None,
               readback: bool = True) -> dict:
        """One frame at ``camera`` (world coordinates), ``width`` x ``height`` pixels (default the
        camera's; a missing side keeps its aspect): the dict of :mod:`dmrt.io.frames` plus
        ``timings`` {stage: ms}. ``readback=False`` (timing runs) may leave the buffers on the GPU
        and return only ``timings``."""
        ...

    def flush_photos(self) -> int:
        """Finish streaming the photos the last frame wanted (a still frame is then exact); returns
        the number uploaded."""
        ...

    def release(self) -> None:
        """Free the renderer's resources."""
        ...


@runtime_checkable
class LayeredRenderer(FrameRenderer, Protocol):
    """A renderer with label layers (the visibility stage's output)."""

    def layers(self) -> dict:
        """The last frame's layers: ``depth`` (k, h, w) float32 camera z (0 = empty) and ``label``
        (k, h, w) int32 (-1 = empty)."""
        ...


@runtime_checkable
class GpuColorRenderer(FrameRenderer, Protocol):
    """A renderer whose last frame stays on the GPU, so that a display can show a frame rendered
    with ``readback=False`` without reading it back, and probe a pixel of it (the viewer)."""

    def gpu_colors(self):
        """The last frame's colours: a ``moderngl.Buffer`` of h x w packed RGBA8 (uint32, R in the
        low byte; row 0 at the top; background 0), valid until the next frame."""
        ...

    def depth_at(self, x: int, y: int) -> float:
        """Camera z (metres, 0 = background) of the last frame's pixel (x, y), row 0 at the top:
        one 4-byte read (it waits for the frame)."""
        ...
