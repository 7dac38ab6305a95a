"""The DMRT runtime renderer (paper Section 5): a scene bundle in, frame dicts out.

Per frame, each stage its own shader and GPU timer section:

1. ``visibility`` - the proxy splats in k label layers, depth peeling (:mod:`dmrt.runtime.visibility`);
2. ``raytracing`` - per pixel, the depth map of each layer's label is raytraced from the layer's
   splat depth (adaptive-step search, bisection, discontinuity test), first valid layer wins
   (``shaders/dmrt_raytrace.glsl`` documents the surface and the step formula);
3. ``labeling`` - the proxies splatted again with the 3D distance to the raytraced point as depth:
   each pixel takes the label of its nearest covering proxy (``shaders/dmrt_labeling.glsl``);
4. ``image_management`` - final labels (``shaders/dmrt_label_finalize.glsl``), the label
   histogram on the GPU (``shaders/dmrt_label_histogram.glsl``), read back (CPU time, reported in
   ``frame["cpu_ms"]``, not in the GPU timings), and the most frequent photos streamed into the
   full-resolution cache (:mod:`dmrt.runtime.texturing`);
5. ``texturing`` - colour from the label's photo at the projection of the raytraced point.

6. ``leveling`` (``RenderConfig.leveling``) - screen-space leveling (paper 5.2.3, last step): the
   colour offsets between photos measured along the frame's seams, one gain per photo solved on
   the CPU, applied to every pixel (:mod:`dmrt.runtime.leveling`).

Ablations and statistics: ``RenderConfig.raytrace=False`` takes the first splat layer as the
surface (the paper's coarse splats, Fig. 8a), ``labeling=False`` keeps each layer's splat label
(Fig. 8b), ``statistics=True`` records the iterative-search step lengths per layer and step index
(Figs. 9, 10) in ``frame["step_stats"]``.

Usage::

    renderer = Renderer(read_bundle("scene.bundle"), RenderConfig(layers=3))
    frame = renderer.render(camera, 1280, 720)   # camera in world coordinates
    frame["depth"], frame["label"], frame["color"], frame["timings"]

Everything on the GPU is relative to the bundle's scene origin (float32 keeps millimetres).
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np

from dmrt.io.bundle import Bundle
from dmrt.camera import Camera
from dmrt.errors import InputError
from dmrt.io.frames import empty_frame
from dmrt.gl.context import check_gl, get_context
from dmrt.gl.shaders import load_program, set_uniforms
from dmrt.gl.timer import GpuTimer
from dmrt.runtime.leveling import ScreenLeveler
from dmrt.runtime.texturing import ImageCache, texture_frame
from dmrt.runtime.visibility import EMPTY_BITS, EMPTY_LABEL, ProxySplats, VisibilityStage, groups

_BARRIER = moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT
HIT_DTYPE = np.dtype([("depth", "<f4"), ("label", "<i4"), ("layer", "<i4"), ("iters", "<i4"),
                      ("normal", "<f4", 3), ("final_label", "<i4")])  # shaders/dmrt_frame.glsl
STAGES = ("visibility", "raytracing", "labeling", "image_management", "texturing", "leveling")
STEP_BINS = 32  # shaders/dmrt_raytrace.glsl
MAX_STATISTICS_LAYERS = 16  # STAT_LAYERS there: the per-workgroup step sums in shared memory


def read_frame(hits_buffer: moderngl.Buffer, colors_buffer: moderngl.Buffer, w: int, h: int) -> tuple[dict, np.ndarray]:
    """Read a frame's ``Hit`` records and packed RGBA8 colours back (shared by DMRT and DMT).

    Returns
    -------
    frame : dict, the contract of :mod:`dmrt.io.frames` (``depth``, ``label``, ``color``, ``normal``)
    hits : (h, w) HIT_DTYPE records, for the renderer's own extra buffers
    """
    hits = np.frombuffer(hits_buffer.read(), HIT_DTYPE).reshape(h, w)
    colors = np.frombuffer(colors_buffer.read(), np.uint8).reshape(h, w, 4)
    frame = empty_frame(h, w)
    frame["depth"] = hits["depth"].copy()
    frame["label"] = hits["final_label"].copy()
    frame["color"] = colors[..., :3].copy()
    frame["normal"] = hits["normal"].copy()
    return frame, hits


@dataclass
class RenderConfig:
    """Parameters of the DMRT runtime (defaults: the paper's)."""

    # Number of label layers k (paper: 3-5 give high quality, Fig. 13; 11 for the worst case).
    layers: int = 5
    # Iterative-search steps per layer (paper: <= 100) and bisection steps (paper: 20).
    max_steps: int = 100
    binary_steps: int = 20
    # Depth disparity (metres) between texels of a depth-map quad that marks a discontinuity
    # (paper: 20 cm).
    discontinuity_threshold: float = 0.20
    # Which texels the discontinuity test checks: "quad" (paper: both triangles of the four texels
    # around the hit) or "triangle" (only the triangle containing the hit; loses half as wide a band
    # along each depth edge of a depth map). See shaders/dmrt_raytrace.glsl.
    discontinuity_test: str = "quad"
    # Iterative search: "adaptive" (paper: every step is h, the signed distance along the line to
    # the photo's centre) or "secant" (h first, then secant steps along the pixel ray).
    search: str = "secant"
    # Addition to the paper: passes in which a pixel the layers left without a surface searches
    # the depth maps of its neighbours' hits (shaders/dmrt_raytrace.glsl, FILL); 0 = the paper.
    fill_passes: int = 2
    # Visibility stage: "kbuffer" (all layers from one splat pass: a per-pixel list of the nearest
    # fragments; 4x faster than peeling for 5 layers on an H200), "compute" (depth peeling by
    # atomicMin splatting, one pass per layer) or "raster" (the paper's GL_POINTS with depth
    # peeling); the same layers (dmrt.runtime.visibility).
    method: str = "kbuffer"
    # k-buffer: fragments kept per pixel (0 = 6 per layer + 2: >= 99.9 % of the peeled layers'
    # pixels on the small preset, 4 per layer + 2: 99.5 %). Fewer cost less memory and time; a
    # pixel with more fragments in front of its k-th layer loses its deepest layers.
    kbuffer_slots: int = 0
    # Compute splatting (visibility and labeling passes): "int64" = one pass with 64-bit atomicMin
    # on (depth bits, label) (NVIDIA GL_NV_shader_atomic_int64), "portable" = an atomicMin pass on
    # the depth then a label-resolve pass (any GL 4.3, e.g. Mesa llvmpipe); "auto" = int64 where
    # the driver has it. Same results.
    atomics: str = "auto"
    # GPU memory for the full-resolution photo cache, MiB (paper: 1 GB); 0 = low-res only.
    cache_mb: float = 1024.0
    # Photo streaming (dmrt.runtime.texturing): decode photos on background threads so that no frame waits
    # for a disk read (the low-res copy stands in until the upload), and upload at most this many
    # photos per frame (0 = no bound). False / 0 make every frame's cache exactly its most frequent
    # labels (deterministic colours: use for quality measurements, or call flush_photos()).
    async_photos: bool = True
    max_uploads_per_frame: int = 4
    # Decoded photos kept in CPU memory, MiB.
    cpu_cache_mb: float = 1024.0
    # The per-pixel labeling pass (paper 5.2.1); False keeps the raytraced layer's label (ablation).
    labeling: bool = True
    # Addition to the paper: a labeling-pass label whose depth map does not see the pixel's point
    # (|depth difference| > label_check_tolerance) falls back to the raytraced layer's label, so
    # that no pixel is textured from a photo in which it is occluded.
    label_check: bool = True
    label_check_tolerance: float = 0.05
    # Screen-space leveling (paper 5.2.3): per-photo colour gains solved each frame from the seams
    # on screen (dmrt.runtime.leveling); off by default so that colours are the photos' own.
    leveling: bool = False
    # Leveling: seam samples a photo pair needs to count, and the bound on a gain (and its inverse).
    leveling_min_samples: int = 16
    leveling_max_gain: float = 2.0
    # The raytracing pass; False = the first splat layer is the surface (ablation: coarse splats).
    raytrace: bool = True
    # Record the iterative search's step lengths per layer and step (frame["step_stats"]); costs
    # atomics in the raytracing pass, so off for timing runs.
    statistics: bool = False
    # Frame size; None = the camera's own (render() arguments override these).
    width: int | None = None
    height: int | None = None
    # Compute splatting: discs with a larger pixel box are splatted by a whole workgroup each.
    max_thread_pixels: int = 256

    def __post_init__(self):
        if self.layers < 1 or self.max_steps < 1 or self.binary_steps < 0 or self.fill_passes < 0:
            raise ValueError("RenderConfig: layers and max_steps must be >= 1, binary_steps and fill_passes >= 0")
        if self.discontinuity_test not in ("quad", "triangle"):
            raise ValueError(f"RenderConfig.discontinuity_test must be 'quad' or 'triangle', "
                             f"not {self.discontinuity_test!r}")
        if self.atomics not in ("auto", "int64", "portable"):
            raise ValueError(f"RenderConfig.atomics must be 'auto', 'int64' or 'portable', not {self.atomics!r}")
        if self.search not in ("adaptive", "secant"):
            raise ValueError(f"RenderConfig.search must be 'adaptive' or 'secant', not {self.search!r}")
        if self.method not in ("compute", "kbuffer", "raster"):
            raise ValueError(f"RenderConfig.method must be 'compute', 'kbuffer' or 'raster', not {self.method!r}")
        if self.statistics and self.layers > MAX_STATISTICS_LAYERS:
            raise ValueError(f"RenderConfig.statistics records at most {MAX_STATISTICS_LAYERS} layers, "
                             f"not {self.layers}")
        if self.kbuffer_slots < 0:
            raise ValueError("RenderConfig.kbuffer_slots must be >= 0")
        if self.leveling_max_gain < 1.0:
            raise ValueError("RenderConfig.leveling_max_gain must be >= 1")


def photo_params(cameras: list[Camera], origin, depth_sizes, low_sizes) -> np.ndarray:
    """(n, 24) float32 rows of the ``Photo`` struct of ``shaders/dmrt_photos.glsl``.

    ``cameras`` in world coordinates; intrinsics are scaled to each depth map's resolution.
    """
    out = np.zeros((len(cameras), 24), np.float32)
    for j, (cam, (dw, dh), (lw, lh)) in enumerate(zip(cameras, depth_sizes, low_sizes)):
        c = cam.relative_to(origin).scaled(dw, dh)
        out[j, 0:12] = np.concatenate([c.R, c.t[:, None]], axis=1).ravel()
        out[j, 12:16] = (c.fx, c.fy, c.cx, c.cy)
        out[j, 16:20] = (dw, dh, lw, lh)
        out[j, 20:22] = (cam.width, cam.height)
    return out


class Renderer:
    """Multi-depth-map raytracing of a scene bundle on one GL context.

    Parameters
    ----------
    bundle : Bundle
        From :func:`dmrt.io.bundle.read_bundle`. Every depth map, the low-resolution photos, the
        proxies and the photos' cameras are uploaded here, once.
    config : RenderConfig, optional
    ctx : moderngl.Context, optional
        Default: the process-wide context (:func:`dmrt.gl.get_context`).

    Attributes
    ----------
    gpu_bytes : dict
        GPU memory per resource (``depthmaps``, ``images_low``, ``image_cache``, ``proxies``,
        ``photos``, and after a frame ``layers`` and ``frame``), bytes.
    """

    name = "dmrt"

    def __init__(self, bundle: Bundle, config: RenderConfig | None = None, ctx: moderngl.Context | None = None):
        self.bundle = bundle
        self._config = config or RenderConfig()
        self.ctx = ctx or get_context()
        self.origin = np.asarray(bundle.origin, np.float64)
        self.cameras = bundle.cameras
        n = len(self.cameras)
        if n == 0:
            raise ValueError(f"{bundle.root}: the bundle has no photos")
        self.timer = GpuTimer(self.ctx)
        has_int64 = {"GL_NV_shader_atomic_int64", "GL_ARB_gpu_shader_int64"} <= set(self.ctx.extensions)
        if self.config.atomics == "int64" and not has_int64:
            raise ValueError("RenderConfig.atomics='int64': this driver lacks GL_NV_shader_atomic_int64")
        self.int64 = self.config.atomics == "int64" or (self.config.atomics == "auto" and has_int64)

        # depth maps: one R32F layer each, written one at a time (no n x h x w host copy)
        self.depth_sizes = []
        for i in range(n):
            m = bundle.depth_map(i)
            self.depth_sizes.append((m.shape[1], m.shape[0]))
            if i == 0:
                # maps share one width; heights follow each photo's aspect (dmrt.preprocess.depthmaps rule)
                w0 = m.shape[1]
                h0 = max([m.shape[0]] + [int(round(w0 * c.height / c.width)) for c in self.cameras])
                dims = self._depth_dims = (w0, h0)
                self.depthmaps = self.ctx.texture_array((*dims, n), 1, dtype="f4")
                self.depthmaps.filter = (moderngl.NEAREST, moderngl.NEAREST)
            if m.shape[0] > dims[1] or m.shape[1] > dims[0]:
                raise InputError(bundle.path("depthmaps", i), f"depth map {m.shape[1]}x{m.shape[0]} "
                                 f"larger than the first one's {dims[0]}x{dims[1]}")
            self.depthmaps.write(np.ascontiguousarray(m, np.float32).tobytes(),
                                 viewport=(0, 0, i, m.shape[1], m.shape[0], 1))
        self.images = ImageCache(self.ctx, bundle, self.config.cache_mb, self.config.max_uploads_per_frame,
                                 self.config.async_photos, self.config.cpu_cache_mb)
        self.photos = self.ctx.buffer(photo_params(self.cameras, self.origin, self.depth_sizes,
                                                   self.images.low_sizes).tobytes())
        labels = np.asarray(bundle.proxy["labels"])
        if len(labels) and labels.max() >= n:
            raise InputError(bundle.root / "proxy.npz", f"array 'labels' holds photo index {labels.max()} "
                                                        f"but the bundle has {n} photos")
        self.splats = ProxySplats(self.ctx, bundle.proxy, self.config.max_thread_pixels)
        self.visibility = VisibilityStage(self.ctx, self.splats, self.config.method, self.int64,
                                          self.config.kbuffer_slots or 6 * self.config.layers + 2, n)
        defines = {"QUAD_TEST": int(self.config.discontinuity_test == "quad"),
                   "SECANT": int(self.config.search == "secant"), "RAYTRACE": int(self.config.raytrace),
                   "STATISTICS": int(self.config.statistics)}
        self._raytrace = load_program(self.ctx, "dmrt_raytrace", defines)
        self._fill = load_program(self.ctx, "dmrt_raytrace", {**defines, "FILL": 1})
        self._finalize = load_program(self.ctx, "dmrt_label_finalize", {"PACKED_LABELS": int(self.int64)})
        self._histogram = load_program(self.ctx, "dmrt_label_histogram", {"N_PHOTOS": n, "PIXELS_PER_THREAD": 64})
        self.counts = self.ctx.buffer(reserve=4 * n)
        self.step_stats = self.ctx.buffer(reserve=16 * self.config.layers * STEP_BINS) if self.config.statistics else None
        c = self.config
        self.leveler = ScreenLeveler(self.ctx, n, c.leveling_min_samples, c.leveling_max_gain,
                                     c.discontinuity_threshold, c.label_check_tolerance) if c.leveling else None
        self._size: tuple[int, int] | None = None
        self._buffers: dict = {}
        self.gpu_bytes = {"depthmaps": self._depth_dims[0] * self._depth_dims[1] * n * 4, **self.images.nbytes,
                          "proxies": self.splats.nbytes, "photos": self.photos.size}
        if self.leveler is not None:
            self.gpu_bytes["leveling"] = self.leveler.nbytes

    @property
    def config(self) -> RenderConfig:
        """The configuration; fixed at construction (programs and buffers are built from it)."""
        return self._config

    @config.setter
    def config(self, value) -> None:
        raise AttributeError("Renderer.config is fixed at construction: make a new Renderer for another "
                             "configuration")

    # -- public -------------------------------------------------------------------------------
    def render(self, camera: Camera, width: int | None = None, height: int | None = None,
               readback: bool = True) -> dict:
        """Render one frame.

        Parameters
        ----------
        camera : Camera
            World coordinates (as the bundle's cameras); any resolution.
        width, height : int, optional
            Frame size (default ``config.width/height``, else the camera's; a missing side follows
            the camera's aspect ratio).
        readback : bool
            False: the frame stays on the GPU and only ``timings``, ``cpu_ms`` (and
            ``leveling_gains``, ``step_stats``) are returned. Timing runs use it: reading every
            buffer back costs more wall time than the frame itself, and with the GPU idle that long
            between frames the stage times of light frames came out inflated (H200: 1 layer read
            26.6 ms, more than 5 layers).

        Returns
        -------
        dict
            The frame contract of :mod:`dmrt.io.frames` - ``depth`` (h, w) float32 camera z (0 =
            background), ``label`` (h, w) int32 (-1 = none), ``color`` (h, w, 3) uint8, ``normal``
            (h, w, 3) float32 unit world normal - plus ``label_raw`` (h, w) int32 (the label of
            the layer whose depth map was hit, before the labeling pass), ``layer_used`` (h, w)
            int32 (0-based layer, -1 = none), ``iterations`` (h, w) int32 (iterative-search steps
            over all layers tried), ``timings`` {stage: GPU ms} (meaningless on llvmpipe, see
            :class:`dmrt.gl.GpuTimer`; ``leveling`` 0 when off) and ``cpu_ms``
            {``label_readback``: wall ms waiting for the label histogram (the GPU finishing the
            frame so far), ``image_management``: wall ms choosing, decoding (synchronous
            streaming) and uploading photos, ``leveling``: reading the seam sums back and solving
            the gains}. With ``config.leveling`` also ``leveling_gains`` (n_photos, 3) float32;
            with ``config.statistics`` also ``step_stats`` (see :meth:`_read_step_stats`).
        """
        cfg = self.config
        cam = camera.resized(width or cfg.width, height or cfg.height)
        w, h = cam.width, cam.height
        self._allocate(w, h)
        b = self._buffers
        local = cam.relative_to(self.origin)
        cam_uniforms = {"u_R": local.R.T.ravel(), "u_t": local.t, "u_K": (local.fx, local.fy, local.cx, local.cy),
                        "u_size": (w, h)}
        npix = w * h
        grid = (groups(w, 8), groups(h, 8))
        ctx, timer = self.ctx, self.timer
        timer.reset()
        self.splats.begin_frame()

        with timer.section("visibility"):
            self.visibility.run(cam_uniforms, (w, h), cfg.layers, b["layer_depth"], b["layer_label"])

        with timer.section("raytracing"):
            if self.step_stats is not None:
                self.visibility.fill(self.step_stats, 0, 4 * cfg.layers * STEP_BINS)
                ctx.memory_barrier(_BARRIER)
                self.step_stats.bind_to_storage_buffer(8)
            b["layer_depth"].bind_to_storage_buffer(1)
            b["layer_label"].bind_to_storage_buffer(2)
            b["hits"].bind_to_storage_buffer(4)
            self.photos.bind_to_storage_buffer(5)
            self.depthmaps.use(0)
            set_uniforms(self._raytrace, u_layers=cfg.layers, u_max_steps=cfg.max_steps,
                         u_binary_steps=cfg.binary_steps, u_threshold=float(cfg.discontinuity_threshold),
                         u_depthmaps=0, **cam_uniforms)
            self._raytrace.run(*grid)
            ctx.memory_barrier(_BARRIER)
            for fill_pass in range(cfg.fill_passes if cfg.raytrace else 0):
                set_uniforms(self._fill, u_pass=fill_pass, u_layers=cfg.layers, u_max_steps=cfg.max_steps,
                             u_binary_steps=cfg.binary_steps, u_threshold=float(cfg.discontinuity_threshold),
                             u_depthmaps=0, **cam_uniforms)
                self._fill.run(*grid)
                ctx.memory_barrier(_BARRIER)

        with timer.section("labeling"):
            self.visibility.fill(b["key"], EMPTY_BITS, 2 * npix if self.int64 else npix)
            if not self.int64:
                self.visibility.fill(b["vlabel"], EMPTY_LABEL, npix)
            ctx.memory_barrier(_BARRIER)
            if cfg.labeling and self.int64:
                self.splats.run("dmrt_labeling", {"INT64": 1}, cam_uniforms, {1: b["key"], 4: b["hits"]})
            elif cfg.labeling:
                for resolve in (0, 1):
                    self.splats.run("dmrt_labeling", {"RESOLVE": resolve}, cam_uniforms,
                                    {1: b["key"], 2: b["vlabel"], 4: b["hits"]})

        # image management: the histogram pass and the uploads are timed on the GPU; the readback
        # between them waits for the frame so far and is CPU time (frame["cpu_ms"])
        with timer.section("image_management"):
            self.visibility.fill(self.counts, 0, len(self.cameras))
            ctx.memory_barrier(_BARRIER)
            b["key"].bind_to_storage_buffer(1)
            b["vlabel"].bind_to_storage_buffer(2)
            b["hits"].bind_to_storage_buffer(4)
            self.counts.bind_to_storage_buffer(6)
            self.photos.bind_to_storage_buffer(5)
            self.depthmaps.use(0)
            set_uniforms(self._finalize, u_use_labeling=int(cfg.labeling), u_label_check=int(cfg.label_check),
                         u_visibility_tol=float(cfg.label_check_tolerance), u_depthmaps=0, **cam_uniforms)
            self._finalize.run(*grid)
            ctx.memory_barrier(_BARRIER)
            set_uniforms(self._histogram, u_count=npix)
            self._histogram.run(groups(npix, 64 * 64))
            ctx.memory_barrier(_BARRIER | moderngl.BUFFER_UPDATE_BARRIER_BIT)
        counts, cpu_ms = texture_frame(ctx, timer, self.images, self.counts, b["hits"], b["colors"], self.photos,
                                       cam_uniforms)
        self.label_counts = counts
        if self.leveler is not None:
            cpu_ms["leveling"] = self.leveler.run(timer, b["hits"], b["colors"], self.photos, self.images,
                                                  self.depthmaps, cam_uniforms, counts)

        check_gl(ctx, "rendering a DMRT frame")
        frame = {}
        if readback:
            frame, hits = read_frame(b["hits"], b["colors"], w, h)
            frame["label_raw"] = hits["label"].copy()
            frame["layer_used"] = hits["layer"].copy()
            frame["iterations"] = hits["iters"].copy()
        self.timer.check_executed("rendering a DMRT frame")
        ms = self.timer.ms
        frame["timings"] = {stage: ms.get(stage, 0.0) for stage in STAGES}
        frame["cpu_ms"] = cpu_ms
        if self.leveler is not None:
            frame["leveling_gains"] = self.leveler.gains.copy()
        if self.step_stats is not None:
            frame["step_stats"] = self._read_step_stats()
        return frame

    def _read_step_stats(self) -> dict:
        """``mean_step_m`` (k, STEP_BINS) float64 mean step length along the ray (metres) of the
        i-th iterative-search step in layer l (0 where none; the last bin pools later steps) and
        ``count`` (k, STEP_BINS) int64 number of such steps."""
        raw = np.frombuffer(self.step_stats.read(), np.uint32).reshape(self.config.layers, STEP_BINS, 4)
        count = raw[..., 0].astype(np.int64)
        total = (raw[..., 1].astype(np.float64) + raw[..., 2].astype(np.float64) * 2.0 ** 32) * 1e-5
        return {"mean_step_m": np.divide(total, count, out=np.zeros_like(total), where=count > 0),
                "count": count}

    def flush_photos(self) -> int:
        """Wait for the photos being streamed and upload all that the last frame wanted; the next
        frame of the same view is then textured as with synchronous, unbounded streaming."""
        return self.images.flush()

    def layers(self) -> dict:
        """The last frame's label layers.

        Returns
        -------
        dict
            ``depth`` (k, h, w) float32 camera z of each layer's splat (0 = empty) and ``label``
            (k, h, w) int32 (-1 = empty).
        """
        w, h = self._size
        k = self.config.layers
        bits = np.frombuffer(self._buffers["layer_depth"].read(), np.uint32)[:k * w * h].reshape(k, h, w)
        label = np.frombuffer(self._buffers["layer_label"].read(), np.int32)[:k * w * h].reshape(k, h, w).copy()
        depth = bits.view(np.float32).copy()
        depth[bits == EMPTY_BITS] = 0.0
        label[label == EMPTY_LABEL] = -1
        return {"depth": depth, "label": label}

    def release(self) -> None:
        """Free this renderer's GPU resources (cached programs stay with the context)."""
        self._release_frame()
        self.visibility.release()
        self.splats.release()
        self.images.release()
        for obj in (self.depthmaps, self.photos, self.counts, self.step_stats, self.leveler):
            if obj is not None:
                obj.release()

    # -- internals ----------------------------------------------------------------------------
    def _allocate(self, w: int, h: int) -> None:
        if self._size == (w, h):
            return
        self._release_frame()
        npix, k = w * h, self.config.layers
        self._buffers = {
            "layer_depth": self.ctx.buffer(reserve=4 * k * npix),
            "layer_label": self.ctx.buffer(reserve=4 * k * npix),
            "hits": self.ctx.buffer(reserve=HIT_DTYPE.itemsize * npix),
            "key": self.ctx.buffer(reserve=8 * npix),  # 64-bit keys on the int64 path
            "vlabel": self.ctx.buffer(reserve=4 * npix),
            "colors": self.ctx.buffer(reserve=4 * npix),
        }
        self._size = (w, h)
        self.gpu_bytes["layers"] = 8 * k * npix
        if self.config.method == "kbuffer":
            self.gpu_bytes["kbuffer"] = 4 * npix * (self.config.kbuffer_slots or 6 * k + 2)
        self.gpu_bytes["frame"] = (HIT_DTYPE.itemsize + 12) * npix

    def _release_frame(self) -> None:
        for buf in self._buffers.values():
            buf.release()
        self._buffers = {}
        self._size = None
