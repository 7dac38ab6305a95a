"""The end of a frame, shared by the DMRT and DMT renderers: both write the per-pixel ``Hit`` records
of ``shaders/dmrt_frame.glsl``, and from there on a frame is the same work:

1. ``image_management`` - the label histogram and the choice of the most frequent photos on the
   GPU (``shaders/dmrt_photo_choice.glsl``), the choice read back with the frame's one status
   record (:mod:`dmrt.runtime.status`), and the chosen photos streamed into the full-resolution
   cache (:class:`dmrt.runtime.texturing.ImageCache`). While streaming (``async_photos``) an
   earlier frame's choice is followed: reading the current one back would make the CPU wait for
   the frame so far (9-13 ms a frame at paper scale on an H200), and photos stream in over
   several frames anyway;
2. ``texturing`` - colour from each pixel's photo (:func:`dmrt.runtime.texturing.texture_frame`),
   times the photo's photometric gain (bundle.json ``photo_gains``; all 1 with ``photometric`` off);
3. ``leveling`` (optional) - screen-space leveling (:class:`dmrt.runtime.leveling.ScreenLeveler`),
   all on the GPU: the seams, the gains solved from them and this frame's label histogram (which
   never leaves the GPU for it), the gains applied;
4. the GL error check, the read-back (unless timing) and the per-stage timings.
"""

from __future__ import annotations

import time

import moderngl
import numpy as np

from dmrt.camera import Camera
from dmrt.gl import abi
from dmrt.gl.abi import HIT_DTYPE, PHOTO_FLOATS
from dmrt.gl.context import check_gl
from dmrt.gl.kernels import Staging, fill_u32, groups
from dmrt.gl.shaders import load_program, set_uniforms
from dmrt.io.frames import empty_frame
from dmrt.runtime.leveling import ScreenLeveler
from dmrt.runtime.ranking import PhotoRanking
from dmrt.runtime.status import FrameStatus
from dmrt.runtime.texturing import ImageCache, gains_buffer_data, texture_frame

_BARRIER = moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT
# pixels of a column each thread of the histogram pass counts (shaders/dmrt_label_histogram.glsl): its
# loads come one after another, so shorter runs mean more threads in flight
HISTOGRAM_RUN = 16


def photo_params(cameras, origin, depth_sizes, low_sizes) -> np.ndarray:
    """(n, PHOTO_FLOATS) float32 rows of the ``Photo`` struct of ``shaders/dmrt_photos.glsl``.

    ``cameras`` in world coordinates; intrinsics are scaled to each depth map's resolution.
    """
    out = np.zeros((len(cameras), PHOTO_FLOATS), np.float32)
    for j, (cam, (dw, dh), (lw, lh)) in enumerate(zip(cameras, depth_sizes, low_sizes)):
        c = cam.relative_to(origin).scaled(dw, dh)
        out[j, 0:12] = np.concatenate([c.R, c.t[:, None]], axis=1).ravel()
        out[j, 12:16] = (c.fx, c.fy, c.cx, c.cy)
        out[j, 16:20] = (dw, dh, lw, lh)
        out[j, 20:22] = (cam.width, cam.height)
    return out


def camera_uniforms(local: Camera) -> dict:
    """The render camera's uniforms, every frame pass's: ``u_R`` the world->camera rotation
    (column-major, float32 bytes), ``u_t`` (3,) metres (float32 bytes), ``u_K`` (fx, fy, cx, cy)
    pixels, ``u_size`` (w, h). ``local``: the camera relative to the scene origin. Bytes, converted
    once a frame: ``set_uniforms`` compares and writes them as they are."""
    return {"u_R": local.R.T.astype(np.float32).tobytes(), "u_t": np.float32(local.t).tobytes(),
            "u_K": (local.fx, local.fy, local.cx, local.cy), "u_size": (local.width, local.height)}


def hit_depth_at(staging: Staging, hits: moderngl.Buffer, width: int, x: int, y: int) -> float:
    """Camera z (metres, 0 = background) of pixel (x, y) of a frame's ``Hit`` records, ``width``
    pixels a row: one 4-byte read (it waits for the frame), through ``staging``: read directly, the
    records would move to host memory on NVIDIA's driver, and every later frame write them there."""
    offset = HIT_DTYPE.itemsize * (y * width + x)  # Hit.depth is the record's first word
    return float(np.frombuffer(staging.read(hits, 4, offset), np.float32)[0])


def read_gpu_frame(staging: Staging, hits_buffer: moderngl.Buffer, colors_buffer: moderngl.Buffer,
                   normals_buffer: moderngl.Buffer, w: int, h: int) -> tuple[dict, np.ndarray]:
    """Read a frame's ``Hit`` records, packed RGBA8 colours and normals back (through ``staging``:
    the frame's own buffers stay in GPU memory, see :class:`dmrt.gl.kernels.Staging`).

    Returns
    -------
    frame : dict, the contract of :mod:`dmrt.io.frames` (``depth``, ``label``, ``color``, ``normal``)
    hits : (h, w) HIT_DTYPE records, for the renderer's own extra buffers
    """
    n = w * h
    hits = np.frombuffer(staging.read(hits_buffer, HIT_DTYPE.itemsize * n), HIT_DTYPE).reshape(h, w)
    colors = np.frombuffer(staging.read(colors_buffer, 4 * n), np.uint8).reshape(h, w, 4)
    frame = empty_frame(h, w)
    frame["depth"] = hits["depth"].copy()
    frame["label"] = hits["final_label"].copy()
    frame["color"] = colors[..., :3].copy()
    frame["normal"] = np.frombuffer(staging.read(normals_buffer, 12 * n), np.float32).reshape(h, w, 3).copy()
    return frame, hits


class FrameShading:
    """Photos, photo cache, label histogram and leveler of one renderer, and the end of its frames.

    Parameters
    ----------
    ctx : moderngl.Context
    bundle : dmrt.io.bundle.Bundle
    timer : dmrt.gl.GpuTimer, the renderer's (sections ``image_management``, ``texturing``, ``leveling``)
    depth_sizes : list of (w, h), each photo's depth map as the renderer holds it (texels)
    config : RenderConfig or DMTConfig (``cache_mb``, ``max_uploads_per_frame``, ``async_photos``,
        ``cpu_cache_mb``, ``photometric``, ``leveling``, ``leveling_min_samples``, ``leveling_max_gain``,
        ``discontinuity_threshold``; ``photo_choice``: "view" counts the candidates bound at
        ``abi.B_VIEW_CANDIDATES`` in the histogram)
    maps : dmrt.runtime.maps.MapCache, optional
        DMRT's depth maps, which hold the low-resolution photos too

    Attributes
    ----------
    photo_gains : (n_photos, 3) float32, the photometric gains applied (the bundle's, or all 1).
    seam_tolerance : float, metres: how closely a photo's depth map must see a seam point to count
    status : dmrt.runtime.status.FrameStatus, the frames' status records (the renderer's tiles
        path writes and reads them too)
    """

    def __init__(self, ctx, bundle, timer, depth_sizes, config, seam_tolerance: float, maps=None):
        n = len(bundle.cameras)
        self.ctx, self.timer = ctx, timer
        self.images = ImageCache(ctx, bundle, config.cache_mb, config.max_uploads_per_frame, config.async_photos,
                                 config.cpu_cache_mb, maps)
        self.photos = ctx.buffer(photo_params(bundle.cameras, bundle.origin, depth_sizes,
                                              self.images.low_sizes).tobytes())
        self.photo_gains = (bundle.photo_gains if config.photometric else np.ones((n, 3), np.float32)).copy()
        self.gains = ctx.buffer(gains_buffer_data(self.photo_gains, n).tobytes())
        # the label histogram: the photo choice and the leveling's gains solve read it on the GPU
        self._counts_gpu = ctx.buffer(reserve=4 * n)
        # with the view-dependent photo choice its candidates are counted too (shaders/dmrt_label_histogram.glsl)
        view = getattr(config, "photo_choice", "labels") == "view"
        self._histogram = load_program(ctx, "dmrt_label_histogram", {"PIXELS_PER_THREAD": HISTOGRAM_RUN,
                                                                     "VIEW_CANDIDATES": int(view)})
        self._choice = PhotoRanking(ctx, n)
        self.status = FrameStatus(ctx, self.images.n_slots)
        self.sync_photos = not config.async_photos
        self.leveler = ScreenLeveler(ctx, n, config.leveling_min_samples, config.leveling_max_gain,
                                     config.discontinuity_threshold, seam_tolerance,
                                     map_defines=self.images.defines) if config.leveling else None
        self.staging = Staging(ctx)  # frame read-backs (and the renderers' own, e.g. their layers)

    @property
    def nbytes(self) -> dict:
        """GPU bytes per resource: the photo caches, the Photo records, the photo choice's ranked
        list, the leveling buffers."""
        out = {**self.images.nbytes, "photos": self.photos.size + self.gains.size, "photo_choice": self._choice.nbytes}
        if self.leveler is not None:
            out["leveling"] = self.leveler.nbytes
        return out

    def begin_frame(self):
        """Start a frame: its status record (:meth:`dmrt.runtime.status.FrameStatus.begin`)."""
        return self.status.begin()

    def finish(self, hits, colors, normals, depthmaps, cam_uniforms: dict, stages, what: str,
               readback: bool, blend=None) -> tuple[dict, np.ndarray | None]:
        """Shade the frame whose ``Hit`` records are in ``hits`` (and, with ``readback``, normals in
        ``normals``: h x w x 3 float32) and return it. ``blend``: the view-dependent photo choice's
        blend records (:class:`dmrt.runtime.view_choice.ViewChoice`), mixed by the texturing pass.

        Returns
        -------
        frame : dict
            With ``readback`` the frame contract (``depth``, ``label``, ``color``, ``normal``);
            always ``timings``, ``part_timings``, ``timings_lag`` for ``stages``
            (:meth:`dmrt.gl.GpuTimer.frame_timings`) and ``cpu_ms``; with leveling
            ``cpu_ms["leveling"]`` (issuing its passes) and, with ``readback`` only,
            ``leveling_gains`` (n_photos, 3) float32 (reading them waits for the GPU).
        records : (h, w) HIT_DTYPE or None (without ``readback``)
        """
        ctx, timer = self.ctx, self.timer
        if self.status.frame < 0:
            raise RuntimeError("FrameShading.finish before begin_frame: the status records would be misread")
        w, h = cam_uniforms["u_size"]
        n_photos = self._counts_gpu.size // 4
        with timer.section("image_management:histogram"):
            fill_u32(ctx, self._counts_gpu, 0, n_photos)
            ctx.memory_barrier(_BARRIER)
            hits.bind_to_storage_buffer(abi.B_HITS)
            self._counts_gpu.bind_to_storage_buffer(abi.B_COUNTS)
            set_uniforms(self._histogram, u_size=(w, h))
            self._histogram.run(groups(w, 64), groups(h, HISTOGRAM_RUN))
            ctx.memory_barrier(_BARRIER)
            if self.images.n_slots:  # into the next frame's status record
                self._choice.run(self._counts_gpu, self.status.record(-1), self.images.n_slots)
                self.status.record(-1).written()
        t0 = time.perf_counter()
        if not self.images.n_slots:
            wanted = np.zeros(0, np.int64)
        elif self.sync_photos:  # this frame's own choice: waits for the frame so far
            wanted = self.status.read(-1)[1]
        else:  # an earlier frame's, read already in this frame or read now without a wait
            wanted = self.status.wanted()
        cpu_ms = {"status_read": (time.perf_counter() - t0) * 1e3}
        cpu_ms["image_management"] = texture_frame(ctx, timer, self.images, wanted, hits, colors, self.photos,
                                                   cam_uniforms, self.gains, blend)
        if self.leveler is not None:  # its seams compare the photos' colours after the gains
            self.gains.bind_to_storage_buffer(abi.B_PHOTO_GAINS)
            cpu_ms["leveling"] = self.leveler.run(timer, hits, colors, self.photos, self.images, depthmaps,
                                                  cam_uniforms, self._counts_gpu)
        check_gl(ctx, what)
        frame, records = {}, None
        if readback:
            frame, records = read_gpu_frame(self.staging, hits, colors, normals, w, h)
            if self.leveler is not None:
                frame["leveling_gains"] = self.leveler.read_gains(self.staging)
        timer.check_executed(what)
        frame.update(timer.frame_timings(stages))
        frame["cpu_ms"] = cpu_ms
        return frame, records

    def read_label_counts(self) -> np.ndarray:
        """(n_photos,) uint32 pixels per final label of the last frame (waits for the GPU; the
        frames themselves never read the histogram)."""
        return np.frombuffer(self.staging.read(self._counts_gpu), np.uint32).copy()

    def flush_photos(self) -> int:
        """Wait for the photos being streamed and upload all that the last frame chose; the next
        frame of the same view is then textured as with synchronous, unbounded streaming."""
        if self.images.n_slots and self.status.frame >= 0:
            self.images.update(self.status.read(-1)[1])  # the last frame's own choice
        return self.images.flush()

    def release(self) -> None:
        self.images.release()
        for obj in (self.photos, self.gains, self._counts_gpu, self._choice, self.status, self.leveler, self.staging):
            if obj is not None:
                obj.release()
