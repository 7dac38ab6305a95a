"""Depth maps of the dense point cloud seen from each photo's camera (paper Section 4.1).

The point cloud P_HD is rendered from a photo's camera as oriented circular splats (a disc of
radius ``r`` centred at ``p`` with normal ``n``, two-sided) into a float32 map of camera-space z,
``0.0`` where nothing was hit. A pixel's depth is the camera z where its ray (through the pixel
centre) meets a disc's plane within ``r`` of the disc's centre; the nearest such disc wins. Rays
that (almost) lie in a disc's plane (|cos| < 1e-3) take the disc centre's z where they pass within
``r`` of it (``GRAZING_COS`` in ``shaders/splat_depth_common.glsl`` says why).

Two GPU paths produce the same maps (``DepthMapConfig.method``):

``"compute"`` (default)
    One thread per splat, ``atomicMin`` on the float bits of z in a storage buffer; discs larger
    than ``max_thread_pixels`` pixels go to a second pass with one workgroup per disc. The fast path
    on NVIDIA Hopper, whose few raster units make GL_POINTS 10-60x slower (``shared/GPU.md``).
``"raster"``
    The paper's way: GL_POINTS sprites with a per-fragment ray-disc test, z-buffering (24-bit
    log-spaced depth test plus a MIN blend on the float32 colour target, so the stored z is the
    exact minimum); discs too big for a point sprite are drawn as geometry-shader quads.

Neither path cuts large discs: a disc close to the camera covers all of its pixels.
The module also reads and writes depth maps as OpenEXR files with one float32 channel ``Z``.
"""

from __future__ import annotations

import os
import tempfile
from collections.abc import Iterable
from contextlib import nullcontext
from dataclasses import dataclass
from pathlib import Path

import moderngl
import numpy as np

from dmrt.camera import Camera
from dmrt.errors import InputError
from dmrt.gl.shaders import load_program, set_uniforms
from dmrt.gl.timer import GpuTimer

_EMPTY_BITS = 0xFFFFFFFF  # compute path: an untouched pixel (above every positive float's bits)
_EMPTY_Z = float(np.finfo(np.float32).max)  # raster path: the colour target's clear value
_FLOATS_PER_SPLAT = 7  # position xyz, normal xyz, radius: the layout both paths read
_LARGE_GROUPS = 1024  # workgroups of the large-disc compute pass (they stride over the list)


@dataclass
class DepthMapConfig:
    """How depth maps are rendered."""

    # Depth-map width in pixels; the height follows the photo's aspect ratio (rounded). The paper
    # uses 1024 (x 684 for its 3:2 photos).
    width: int = 1024
    # "compute" (atomicMin splatting, fast on every GPU) or "raster" (the paper's GL_POINTS).
    method: str = "compute"
    # Points uploaded to the GPU per batch: 4M points = 112 MB of float32 attributes.
    chunk_points: int = 4_000_000
    # Compute path: a disc whose pixel box exceeds this many pixels is splatted by a whole
    # workgroup instead of one thread, so that one near disc does not stall its warp (16 x 16).
    max_thread_pixels: int = 256


def depth_map_size(camera: Camera, width: int) -> tuple[int, int]:
    """``(width, height)`` of a depth map ``width`` pixels wide for ``camera``'s aspect ratio."""
    return int(width), max(1, int(round(width * camera.height / camera.width)))


class DepthMapRenderer:
    """Renders depth maps from streamed point chunks on one GL context.

    Parameters
    ----------
    ctx : moderngl.Context
        GL 4.3+ context (:func:`dmrt.gl.get_context`).
    config : DepthMapConfig, optional
    timer : GpuTimer, optional
        When given, GPU milliseconds are accumulated under ``"depthmap"`` (splatting) and
        ``"depthmap_upload"`` (the copy of each batch to the GPU, which the driver runs on the GPU
        timeline: 28 MB per million points, 3.5-12 ms per million measured on an H200).
        Do not also wrap :meth:`render` in a section of the same timer: sections cannot nest.
    """

    def __init__(self, ctx: moderngl.Context, config: DepthMapConfig | None = None,
                 timer: GpuTimer | None = None):
        self.ctx = ctx
        self.config = config or DepthMapConfig()
        self.timer = timer
        if self.config.method not in ("compute", "raster"):
            raise ValueError(f"DepthMapConfig.method must be 'compute' or 'raster', not {self.config.method!r}")
        if self.config.chunk_points < 1 or self.config.width < 1:
            raise ValueError("DepthMapConfig.width and chunk_points must be positive")
        self._splats = ctx.buffer(reserve=self.config.chunk_points * _FLOATS_PER_SPLAT * 4, dynamic=True)
        self._size: tuple[int, int] | None = None
        if self.config.method == "compute":
            defines = {"MAX_THREAD_PIXELS": int(self.config.max_thread_pixels)}
            self._cs = load_program(ctx, "splat_depth_compute", defines)
            self._cs_large = load_program(ctx, "splat_depth_compute_large")
            self._large = ctx.buffer(reserve=4 * (1 + self.config.chunk_points))
            self._fill = load_program(ctx, "fill_u32")
        else:
            self._points = load_program(ctx, "splat_depth_raster")
            self._quads = load_program(ctx, "splat_depth_raster_large")
            layout = [(self._splats, "3f 3f 1f", "in_position", "in_normal", "in_radius")]
            self._vao_points = ctx.vertex_array(self._points, layout)
            self._vao_quads = ctx.vertex_array(self._quads, layout)
            # the implementation's largest sprite (llvmpipe: 255 px; NVIDIA: thousands)
            self.max_point_size = float(ctx.info["GL_POINT_SIZE_RANGE"][1])

    # -- public -------------------------------------------------------------------------------
    def render(self, camera: Camera, chunks: Iterable[tuple[np.ndarray, np.ndarray, np.ndarray]]) -> np.ndarray:
        """Splat every chunk into one depth map seen from ``camera``.

        Parameters
        ----------
        camera : Camera
            The photo's camera, already relative to the scene origin; any resolution (it is scaled
            to ``config.width`` x the matching height).
        chunks : iterable of (positions, normals, radii)
            ``positions`` (n, 3) float32, metres, scene-origin-relative; ``normals`` (n, 3) float32
            (any length; zero = face the camera); ``radii`` (n,) float32, metres. Chunks larger than
            ``config.chunk_points`` are split.

        Returns
        -------
        depth : (height, width) float32
            Camera-space z in metres, row 0 at the top of the photo; 0.0 where no disc was hit.
        """
        w, h = depth_map_size(camera, self.config.width)
        cam = camera.scaled(w, h)
        self._begin(w, h)
        programs = (self._cs, self._cs_large) if self.config.method == "compute" else (self._points, self._quads)
        for program in programs:
            set_uniforms(program, u_R=cam.R.T.ravel(), u_t=cam.t, u_size=(w, h),
                         u_K=(cam.fx, cam.fy, cam.cx, cam.cy))
        for positions, normals, radii in chunks:
            data = _pack(positions, normals, radii)
            for start in range(0, len(data), self.config.chunk_points):
                self._splat(data[start:start + self.config.chunk_points])
        return self._finish()

    # -- internals ----------------------------------------------------------------------------
    def _begin(self, w: int, h: int) -> None:
        if self._size != (w, h):
            self._release_targets()
            if self.config.method == "compute":
                self._depth = self.ctx.buffer(reserve=4 * w * h)
            else:
                self._color = self.ctx.texture((w, h), 1, dtype="f4")
                self._zbuf = self.ctx.depth_texture((w, h))
                self._fbo = self.ctx.framebuffer([self._color], self._zbuf)
                # one scope per target, reused: moderngl only frees scopes on release()
                flags = moderngl.DEPTH_TEST | moderngl.BLEND | moderngl.PROGRAM_POINT_SIZE
                self._scope = self.ctx.scope(self._fbo, enable_only=flags)
            self._size = (w, h)
        if self.config.method == "compute":
            self._depth.bind_to_storage_buffer(0)
            set_uniforms(self._fill, u_value=_EMPTY_BITS, u_count=w * h)
            self._fill.run(min(-(-w * h // 256), 65535))
            self.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)
        else:
            self._fbo.clear(_EMPTY_Z, 0.0, 0.0, 0.0, depth=1.0)

    def _splat(self, data: np.ndarray) -> None:
        n = len(data)
        if n == 0:
            return
        # the driver's copy of the batch runs on the GPU timeline: time it apart from the splatting
        with self._timed("depthmap_upload"):
            self._splats.orphan(self._splats.size)  # let the GPU keep reading the previous batch
            self._splats.write(data)
        with self._timed("depthmap"):
            if self.config.method == "compute":
                self._splat_compute(n)
            else:
                self._splat_raster(n)

    def _timed(self, name: str):
        return self.timer.section(name) if self.timer is not None else nullcontext()

    def _splat_compute(self, n: int) -> None:
        self._large.write(b"\0\0\0\0")  # empty large-disc list
        self._splats.bind_to_storage_buffer(0)
        self._depth.bind_to_storage_buffer(1)
        self._large.bind_to_storage_buffer(2)
        set_uniforms(self._cs, u_count=n)
        set_uniforms(self._cs_large, u_count=n)
        self._cs.run(min(-(-n // 64), 65535))
        self.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)  # pass 2 reads the list
        self._cs_large.run(_LARGE_GROUPS)
        self.ctx.memory_barrier(moderngl.SHADER_STORAGE_BARRIER_BIT)  # the next batch's atomics

    def _splat_raster(self, n: int) -> None:
        ctx = self.ctx
        set_uniforms(self._points, u_max_point_size=self.max_point_size)
        set_uniforms(self._quads, u_max_point_size=self.max_point_size)
        with self._scope:  # binds the target and the flags, restores the caller's on exit
            # LEQUAL lets depth-key ties (1.4e-6 relative) through to the MIN blend, which keeps
            # the exact nearest float32 z
            ctx.depth_func, ctx.blend_equation = "<=", moderngl.MIN
            try:
                self._vao_points.render(moderngl.POINTS, vertices=n)
                self._vao_quads.render(moderngl.POINTS, vertices=n)
            finally:
                # moderngl cannot read these back: restore its defaults
                ctx.depth_func, ctx.blend_equation = "<", moderngl.FUNC_ADD

    def _finish(self) -> np.ndarray:
        w, h = self._size
        if self.config.method == "compute":
            self.ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT)
            bits = np.frombuffer(self._depth.read(), dtype=np.uint32).reshape(h, w)
            depth = bits.view(np.float32).copy()
            depth[bits == _EMPTY_BITS] = 0.0
        else:
            # row 0 of the texture is image row 0 (Camera.gl_view_projection's unflipped clip y)
            depth = np.frombuffer(self._color.read(), dtype=np.float32).reshape(h, w).copy()
            depth[depth >= _EMPTY_Z] = 0.0
        return depth

    def _release_targets(self) -> None:
        for name in ("_scope", "_depth", "_fbo", "_color", "_zbuf"):
            obj = self.__dict__.pop(name, None)
            if obj is not None:
                obj.release()

    def release(self) -> None:
        """Free this renderer's GPU buffers (the cached programs stay with the context)."""
        self._release_targets()
        self._size = None
        for name in ("_splats", "_large", "_vao_points", "_vao_quads"):
            obj = self.__dict__.pop(name, None)
            if obj is not None:
                obj.release()


def _pack(positions, normals, radii) -> np.ndarray:
    """Interleave one chunk into (n, 7) float32 rows: position, normal, radius."""
    positions = np.asarray(positions, dtype=np.float32)
    normals = np.asarray(normals, dtype=np.float32)
    radii = np.asarray(radii, dtype=np.float32)
    n = len(positions)
    if positions.shape != (n, 3) or normals.shape != (n, 3) or radii.shape != (n,):
        raise ValueError(f"a depth-map chunk needs positions (n, 3), normals (n, 3), radii (n,); got "
                         f"{positions.shape}, {normals.shape}, {radii.shape}")
    data = np.empty((n, _FLOATS_PER_SPLAT), dtype=np.float32)
    data[:, 0:3] = positions
    data[:, 3:6] = normals
    data[:, 6] = radii
    return data


# -- OpenEXR ----------------------------------------------------------------------------------
def write_depth_exr(path, depth: np.ndarray) -> None:
    """Write a depth map as OpenEXR, one float32 channel ``Z`` (ZIP compressed, scanlines).

    Written to a temporary file beside ``path`` and renamed, so an interrupted write never leaves
    a truncated map under the final name.

    Parameters
    ----------
    path : str or Path
    depth : (height, width) float32
        Camera z in metres, 0.0 = no surface.
    """
    import OpenEXR

    path = Path(path)
    depth = np.ascontiguousarray(depth, dtype=np.float32)
    if depth.ndim != 2:
        raise ValueError(f"a depth map is (height, width), got shape {depth.shape}")
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".exr", dir=path.parent)
    os.close(fd)
    try:
        OpenEXR.File(header, {"Z": depth}).write(tmp)
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def read_depth_exr(path) -> np.ndarray:
    """Read a depth map written by :func:`write_depth_exr`.

    Returns
    -------
    depth : (height, width) float32
        Camera z in metres, 0.0 = no surface.

    Raises
    ------
    InputError
        The file is missing, not OpenEXR, has no ``Z`` channel, or holds non-depth values
        (non-float, non-finite or negative); the message names the file.
    """
    import OpenEXR

    path = Path(path)
    if not path.is_file():
        raise InputError(path, "depth map not found")
    try:
        channels = OpenEXR.File(str(path)).channels()
    except Exception as exc:  # OpenEXR raises RuntimeError with the library's message
        raise InputError(path, f"not a readable OpenEXR file ({exc})") from None
    if "Z" not in channels:
        raise InputError(path, f"no 'Z' channel (channels: {', '.join(sorted(channels)) or 'none'})")
    z = np.asarray(channels["Z"].pixels)
    if z.ndim != 2 or z.dtype.kind != "f":
        raise InputError(path, f"channel 'Z' must be one float per pixel, got {z.dtype} {z.shape}")
    z = z.astype(np.float32, copy=False)
    if not np.isfinite(z).all() or (z < 0).any():
        raise InputError(path, "channel 'Z' holds non-finite or negative depths (0 = no surface)")
    return z
