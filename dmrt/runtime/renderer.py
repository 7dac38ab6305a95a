"""The DMRT runtime renderer (paper Section 5): a scene bundle in, frame dicts out.

Per frame, each stage its own shader and GPU timer section:

1. ``visibility`` - the proxy splats in k label layers, depth peeling (:mod:`dmrt.runtime.visibility`);
2. ``raytracing`` - per pixel, the depth map of each layer's label is raytraced from the layer's
   splat depth (adaptive-step search, bisection, discontinuity test), first valid layer wins
   (``shaders/dmrt_raytrace.glsl`` documents the surface and the step formula); the fill passes
   search the neighbours of the holes it leaves, side by side, over a list of those holes;
3. ``labeling`` - the proxies splatted again with the 3D distance to the raytraced point as depth:
   each pixel takes the label of its nearest covering proxy (``shaders/dmrt_labeling.glsl``);
4. ``image_management`` - final labels (``shaders/dmrt_label_finalize.glsl``), the label
   histogram and the choice of the most frequent photos on the GPU
   (``shaders/dmrt_label_histogram.glsl``, ``shaders/dmrt_photo_choice.glsl``), and the chosen
   photos streamed into the full-resolution cache (:mod:`dmrt.runtime.texturing`). The CPU learns
   the choice from the frame's one status read-back (:mod:`dmrt.runtime.status`), which also
   carries the tiles path's list length;
5. ``texturing`` - colour from the label's photo at the projection of the raytraced point.

6. ``leveling`` (``RenderConfig.leveling``) - screen-space leveling (paper 5.2.3, last step): the
   colour offsets between photos measured along the frame's seams, one gain per photo solved on
   the GPU (``shaders/dmrt_leveling_solve.glsl``: nothing read back, the CPU does not wait),
   applied to every pixel (:mod:`dmrt.runtime.leveling`).

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
from typing import Literal

import moderngl
import numpy as np

from dmrt.options import option, validate

from dmrt.io.bundle import Bundle
from dmrt.camera import Camera
from dmrt.errors import ConfigError, InputError
from dmrt.gl import abi
from dmrt.gl.abi import EMPTY_BITS, EMPTY_LABEL, HIT_DTYPE, MAX_HIT_LAYER, STAT_LAYERS, STEP_BINS, hit_layer_iters
from dmrt.gl.context import get_context
from dmrt.gl.kernels import EMPTY_DISPATCH, fill_u32, groups, max_groups
from dmrt.gl.shaders import load_program, set_uniforms
from dmrt.gl.timer import GpuTimer
from dmrt.runtime.maps import MapCache
from dmrt.runtime.shading import FrameShading, camera_uniforms, hit_depth_at
from dmrt.runtime.tiles import DEFAULT_BATCH, DEFAULT_TOP, SPARSE_MIN, SPLIT_HOLD, SPLIT_MIN
from dmrt.runtime.view_choice import MAX_BLEND, ViewChoice
from dmrt.runtime.visibility import ProxySplats, VisibilityStage

_BARRIER = moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT
STAGES = ("visibility", "raytracing", "labeling", "image_management", "texturing", "leveling")


Visibility = Literal["tiles", "compute", "kbuffer", "raster"]


# Renderings of one frame at most: once, once more after the tile list grew or missing depth maps
# were loaded, and twice more for maps that only a later rendering's results needed.
RENDER_ATTEMPTS = 4


@dataclass
class RenderConfig:
    """Parameters of the DMRT runtime (defaults: the paper's, with the additions marked); each
    field is a ``dmrt render`` / ``dmrt view`` option."""

    layers: int = option(5, "label layers k (paper: 3-5 give high quality, Fig. 13; 11 for the worst case)",
                         minimum=1, level="common")
    max_steps: int = option(100, "iterative-search steps per layer (paper: <= 100)", minimum=1)
    binary_steps: int = option(20, "refinement steps of a hit at most (paper: 20 bisection steps)", minimum=0)
    refine: Literal["illinois", "bisection"] = option(
        "illinois", "refinement of an enclosed hit: illinois (regula falsi with the Illinois fix, stopping at "
                    "1e-6 of the depth: a few fetches) or bisection (the paper: always --binary-steps steps)")
    discontinuity_threshold: float = option(0.20, "depth disparity between the texels of a depth-map quad that "
                                                  "marks a discontinuity, metres (paper: 0.20)", minimum=0.0)
    discontinuity_test: Literal["quad", "triangle"] = option(
        "quad", "texels the discontinuity test checks: quad (paper: both triangles of the four texels around "
                "the hit) or triangle (only the one holding the hit: half as wide a band lost along depth edges)")
    search: Literal["adaptive", "secant"] = option(
        "secant", "iterative search: adaptive (paper: every step is the signed distance along the line to the "
                  "photo's centre) or secant (that step first, then secant steps along the pixel ray)")
    fill_passes: int = option(2, "addition to the paper: passes in which a covered pixel that no layer gave a "
                                 "surface searches its neighbours' depth maps near their depths; 0 = the paper",
                              minimum=0)
    # A fill search starts at a neighbour's hit, next to the surface it may take, and a pass lasts as
    # long as its longest search. small scene, all 48 photo cameras at 1024x684, 5 layers, against
    # 100 steps (bench_quality --fill-max-steps 100 32 16, reports/frame-h200 session 12): 32 steps
    # fill 8 pixels fewer of 11854 (holes 0.23119 -> 0.23128 %), depth error mean 104.000 -> 103.999
    # mm; 16 steps: 18 fewer. H100, every search capped at 32 (run 1): the two passes 0.235 -> 0.154
    # ms at 1280x720, 0.323 -> 0.236 ms at 3840x2160.
    fill_max_steps: int = option(32, "addition to the paper: iterative-search steps of a hole-filling pass's "
                                     "searches (their own cap: a pass takes as long as its longest search)", minimum=1)
    # tiles is the fastest path, with every layer equal to compute peeling's (paper preset, 5 layers,
    # the visibility stage of frames back to back: 0.82 ms at 720p and 3.59 ms at 4K against 5.29 /
    # 41.9 ms for compute peeling and 10.3 / 83.4 ms for the k-buffer on an H100, session 11 in
    # reports/frame-h200; Table 2 of reports/latest on an H200 agrees)
    method: Visibility = option(
        "tiles", "visibility stage: tiles (the discs binned into screen tiles, each pixel's layers found in "
                 "registers: dmrt/runtime/tiles.py), compute (depth peeling by atomicMin splatting, a "
                 "pass per layer), kbuffer (one splat pass into a per-pixel list of the nearest fragments in "
                 "global memory) or raster (the paper's GL_POINTS depth peeling); the same layers")
    tile_check: Literal["frame", "lagged"] = option(
        "frame", "tiles: frame (each frame's list length is read back late in the frame, with the photo choice, "
                 "and a frame that outgrew the list is rendered again: no frame loses discs) or lagged (reads "
                 "the length of two frames back and never waits; a frame whose list outgrew the buffer loses "
                 "the discs past its end)")
    # the tile raster's speed moves in steps with these two (the workgroups an SM holds at once): 12
    # hits and 288 discs are the fastest on an H200 (dmrt/runtime/tiles.py, TileVisibility's batch)
    tile_batch: int = option(DEFAULT_BATCH, "tiles: discs a workgroup holds in shared memory (36 bytes each; a tile's "
                                            "list up to this long is loaded once for all layers); the fastest value "
                                            "depends on the GPU: python -m bench.bench_visibility --tile-sweep",
                             minimum=1)
    tile_hits: int = option(DEFAULT_TOP, "tiles: nearest hits each pixel keeps sorted in registers, 4, 8, 12 or 16 "
                                         "(a pixel whose layers are not all among them walks its list again); the "
                                         "same layers either way", minimum=4, maximum=16)
    tile_walk: Literal["auto", "linear", "sparse"] = option(
        "auto", "tiles: how the raster finds a pixel's discs: linear (every disc of the tile in turn, its box "
                "tested: fastest for short lists), sparse (only the discs whose box holds the pixel: for long "
                f"ones) or auto (sparse for a frame whose tiles held more than {SPARSE_MIN} discs on average the "
                "last time the list length was read); the same layers")
    # H200, the small many walk (reports/many-photos): 1280x720 sustained 3.21 -> 1.97 ms, 3840x2160
    # 5.49 -> 5.44. The split runs only while a recent frame had a long list (tiles.SPLIT_HOLD): on
    # the paper preset, which has none, 1152 and 0 cost the same (1.113 / 1.115 ms at 1280x720)
    tile_split: int = option(SPLIT_MIN, "tiles: a tile whose list holds more discs than this is walked by one "
                                        "workgroup per tile_batch discs, their results merged (distant discs "
                                        "piling up at a vanishing point keep one workgroup busy for the whole "
                                        f"frame otherwise), while one of the last {SPLIT_HOLD} frames had such "
                                        "a tile; 0 = never; the same layers", minimum=0)
    kbuffer_slots: int = option(0, "k-buffer fragments kept per pixel; 0 = 6 per layer + 2 (>= 99.9 % of the "
                                   "peeled layers' pixels); a pixel with more fragments in front of its k-th layer "
                                   "loses its deepest layers", minimum=0)
    atomics: Literal["auto", "int64", "portable"] = option(
        "auto", "compute splatting: int64 (one pass with 64-bit atomicMin on depth and label, "
                "GL_NV_shader_atomic_int64), portable (a depth pass, then a label pass: any GL 4.3) or auto "
                "(int64 where the driver has it); the same results")
    cache_mb: float | None = option(None, "GPU memory for the full-resolution photo cache, MiB (paper: 1 GB); 0 = "
                                          "low-resolution copies only; default a quarter of the GPU memory the "
                                          "driver reports free after the depth maps, at least 1024 and at most "
                                          "half of it (NVIDIA, AMD), else 1024", minimum=0.0,
                                    level="common")
    async_photos: bool = option(True, "decode photos (and depth maps a partial map cache misses) on background "
                                      "threads so that no frame waits for a disk read (the low-resolution copy "
                                      "stands in until the upload); off, every frame's cache holds exactly its most "
                                      "frequent labels (deterministic colours)")
    max_uploads_per_frame: int = option(4, "photos uploaded to the cache per frame at most; 0 = no bound",
                                        minimum=0)
    cpu_cache_mb: float = option(1024.0, "decoded photos kept in CPU memory, MiB", minimum=0.0)
    map_cache_mb: float = option(0.0, "GPU memory for the photos' depth maps and low-resolution copies, MiB; 0 = "
                                      "as many as one texture array holds (2048 photos on NVIDIA and Mesa). With "
                                      "fewer slots than photos they are a cache: a frame read back that finds a "
                                      "map missing loads it and is rendered again; with async_photos a frame left "
                                      "on the GPU does not wait: the map is read in the background and shows as a "
                                      "hole until a later frame uploads it (dmrt/runtime/maps.py)", minimum=0.0)
    max_map_loads_per_frame: int = option(4, "depth maps (with their low-resolution copies) a frame left on the GPU "
                                             "uploads at most, with a partial map cache and async_photos; 0 = no "
                                             "bound", minimum=0)
    labeling: bool = option(True, "the per-pixel labeling pass (paper 5.2.1); off keeps the raytraced layer's "
                                  "label (ablation)")
    label_check: bool = option(True, "addition to the paper: a labeling-pass label whose depth map does not see the "
                                     "pixel's point falls back to the raytraced layer's label (no pixel textured "
                                     "from a photo in which it is occluded)")
    label_check_tolerance: float = option(0.05, "depth difference, metres, beyond which a depth map does not see "
                                                "a pixel's point (the label check)", minimum=0.0)
    # view: on the real kitchen (../shared/real/kitchen-7scenes, 8 held-out frames) 25.2 dB PSNR
    # against 15.3 dB with the fixed labels; the paper's experiments (bench/) keep "labels"
    photo_choice: Literal["labels", "view"] = option(
        "view", "the photo of each pixel: labels (the paper: the label fixed per proxy in preprocessing, from the "
                  "labeling pass) or view (addition to the paper: among the photos whose depth maps see the pixel's "
                  "point, those whose rays are closest in angle to the view ray: dmrt/runtime/view_choice.py)",
        level="common")
    view_blend: int = option(3, "view photo choice: photos mixed per pixel with unstructured-lumigraph weights "
                                "(smooth as the camera moves); 1 = the best alone", minimum=1, maximum=MAX_BLEND,
                             level="common")
    # 8: the kitchen's 8 held-out views (every 25th of 200 frames) 23.09 dB against 22.85 with 16 (before
    # the distance and turn terms), and half the per-pixel arithmetic (shaders/dmrt_view_choice.glsl)
    view_candidates: int = option(8, "view photo choice: photos each pixel tests besides its label, the frame's best "
                                     "scored (the per-pixel cost); 0 = the label only", minimum=0)
    # distance 0.3 and turn 0.5: the kitchen's 8 held-out frames (every 25th) 25.2 dB, against 23.1 with
    # neither and 23.5 with the distance term alone; turn weights 0.25-1.0 all gave 25.2-25.3 dB
    view_distance_weight: float = option(0.3, "view photo choice: radians of angle a photo pays per octave its distance "
                                              "to the point differs from the view's", minimum=0.0)
    view_turn_weight: float = option(0.5, "view photo choice: radians of angle a photo pays per radian its optical axis "
                                          "turns from the view's (photos from one place agree on every ray's angle; "
                                          "the one turned like the view is the better one)", minimum=0.0)
    # Off by default, chosen by held-out real photos (reports/real-views): on the real kitchen the gains
    # cost 5.7 dB with the view choice (0.9 dB with the fixed labels): a held-out frame keeps its own
    # exposure, which the neighbouring photos the view choice blends share and the gains take away. On
    # synthetic scenes with known per-photo exposures they help (+0.4 to +0.7 dB).
    photometric: bool = option(False, "addition to the paper: multiply each photo's colours by its gain from the "
                                      "global photometric adjustment of preprocessing (bundle.json photo_gains; a "
                                      "bundle without them: 1): even colours across seams; off, colours are the "
                                      "photos' own", level="common")
    leveling: bool = option(False, "screen-space leveling (paper 5.2.3): per-photo colour gains solved each frame "
                                   "from the seams on screen; off by default so that colours are the photos' own",
                            level="common")
    leveling_min_samples: int = option(16, "leveling: seam samples a photo pair needs to count", minimum=1)
    leveling_max_gain: float = option(2.0, "leveling: the bound on a gain and its inverse", minimum=1.0)
    raytrace: bool = option(True, "the raytracing pass; off, the first splat layer is the surface (ablation: "
                                  "coarse splats, paper Fig. 8a)")
    statistics: bool = option(False, "record the iterative search's step lengths per layer and step "
                                     "(frame['step_stats'], Figs. 9/10); costs time, so off for timing runs")
    width: int | None = option(None, "frame width in pixels; default the camera's", minimum=1)
    height: int | None = option(None, "frame height in pixels; default the camera's aspect", minimum=1)
    max_thread_pixels: int = option(256, "compute splatting: discs with a larger pixel box are splatted by a whole "
                                         "workgroup each", minimum=1)

    def __post_init__(self):
        validate(self)
        if self.statistics and self.layers > STAT_LAYERS:
            raise ConfigError("layers", f"the step statistics record at most {STAT_LAYERS} layers, not {self.layers}")
        if self.tile_hits % 4:
            raise ConfigError("tile_hits", f"must be 4, 8, 12 or 16, not {self.tile_hits}")
        if self.layers + self.fill_passes > MAX_HIT_LAYER:
            raise ConfigError("layers", f"layers + fill_passes must be at most {MAX_HIT_LAYER} (the Hit record's "
                                        f"layer field), not {self.layers + self.fill_passes}")


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
        self.timer = GpuTimer(self.ctx, wait=False)  # a render loop never waits on its timers
        has_int64 = {"GL_NV_shader_atomic_int64", "GL_ARB_gpu_shader_int64"} <= set(self.ctx.extensions)
        if self.config.atomics == "int64" and not has_int64:
            raise ValueError("RenderConfig.atomics='int64': this driver lacks GL_NV_shader_atomic_int64")
        self.int64 = self.config.atomics == "int64" or (self.config.atomics == "auto" and has_int64)

        # depth maps and low-resolution photos: every one resident, or a cache of them
        self.maps = MapCache(self.ctx, bundle, self.config.map_cache_mb, self.config.async_photos,
                             self.config.max_map_loads_per_frame)
        self._centres = np.array([c.center for c in self.cameras])
        self.depthmaps, self.depth_sizes = self.maps.depthmaps, self.maps.depth_sizes
        map_defines = self.maps.defines
        # the end of the frame (histogram, photo cache, texturing, leveling) is DMT's too
        self.shading = FrameShading(self.ctx, bundle, self.timer, self.depth_sizes, self.config,
                                    self.config.label_check_tolerance, self.maps)
        self.images, self.photos, self.leveler = self.shading.images, self.shading.photos, self.shading.leveler
        labels = np.asarray(bundle.proxy["labels"])
        if len(labels) and labels.max() >= n:
            raise InputError(bundle.root / "proxy.npz", f"array 'labels' holds photo index {labels.max()} "
                                                        f"but the bundle has {n} photos")
        self.splats = ProxySplats(self.ctx, bundle.proxy, self.config.max_thread_pixels)
        self.visibility = VisibilityStage(self.ctx, self.splats, self.config.method, self.int64,
                                          self.config.kbuffer_slots or 6 * self.config.layers + 2, n,
                                          self.config.tile_check, self.shading.status, hit_masks=self.config.labeling,
                                          tile_batch=self.config.tile_batch, tile_top=self.config.tile_hits,
                                          tile_walk=self.config.tile_walk, tile_split=self.config.tile_split,
                                          map_defines=map_defines)
        defines = {"QUAD_TEST": int(self.config.discontinuity_test == "quad"),
                   "SECANT": int(self.config.search == "secant"), "RAYTRACE": int(self.config.raytrace),
                   "STATISTICS": int(self.config.statistics), "ILLINOIS": int(self.config.refine == "illinois"),
                   **map_defines}
        # the search and fill programs, by whether the frame is read back: only such a frame has
        # normals, and leaving their code out of the others' programs (NORMALS 0, not just u_normals 0)
        # made the search 15 % faster at 3840x2160 on the H100 (6 % at 1280x720; reports/frame-h200)
        self._search_programs = {
            readback: tuple(load_program(self.ctx, "dmrt_raytrace", {**defines, "FILL": fill, "NORMALS": int(readback)})
                            for fill in (0, 1))
            for readback in (False, True)}
        # the labeling pass on the tiles path's lists leaves the final labels itself (no labels written
        # and read back by a finalize pass, so no buffers for them)
        self._labels_finalized = self.config.labeling and self.visibility.tiles is not None
        self._max_groups = max_groups(self.ctx)
        self.view_choice = None
        if self.config.photo_choice == "view":
            self.view_choice = ViewChoice(self.ctx, n, self.config.view_candidates, self.config.view_blend,
                                          self.config.view_distance_weight, self.config.view_turn_weight,
                                          self.config.label_check_tolerance,
                                          max(c.fx * s[0] / c.width for c, s in zip(self.cameras, self.depth_sizes)),
                                          map_defines)
        self._finalize = load_program(self.ctx, "dmrt_label_finalize", {"PACKED_LABELS": int(self.int64), **map_defines})
        self.step_stats = self.ctx.buffer(reserve=16 * self.config.layers * STEP_BINS) if self.config.statistics else None
        self._size: tuple[int, int] | None = None
        self._buffers: dict = {}
        self.gpu_bytes = {**self.shading.nbytes, **self.maps.nbytes, "proxies": self.splats.nbytes}

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
            ``step_stats``) are returned. Timing runs use it: reading every buffer back costs
            more wall time than the frame itself, and with the GPU idle that long between frames
            the stage times of light frames came out inflated (H200: 1 layer read 26.6 ms, more
            than 5 layers).

        Returns
        -------
        dict
            The frame contract of :mod:`dmrt.io.frames` - ``depth`` (h, w) float32 camera z (0 =
            background), ``label`` (h, w) int32 (-1 = none), ``color`` (h, w, 3) uint8, ``normal``
            (h, w, 3) float32 unit world normal - plus ``label_raw`` (h, w) int32 (the label of
            the layer whose depth map was hit, before the labeling pass), ``layer_used`` (h, w)
            int32 (0-based layer, -1 = none), ``iterations`` (h, w) int32 (iterative-search steps
            over all layers tried), ``timings`` {stage: GPU ms} of an earlier frame, NaN where
            unavailable, and ``timings_lag`` (:meth:`dmrt.gl.GpuTimer.frame_timings`) and ``cpu_ms``
            {``status_read``: wall ms reading the frame's status record for the photo choice
            (with ``tile_check="frame"`` it waits for the visibility stage, issued long before;
            with synchronous photos for the frame so far; 0 when the lagged tiles path read its
            record already), ``image_management``: wall ms decoding (synchronous streaming) and uploading
            photos, with leveling ``leveling``: wall ms issuing its passes
            (the gains are solved on the GPU)}. With ``config.leveling`` and ``readback`` also
            ``leveling_gains`` (n_photos, 3) float32; with ``config.statistics`` also
            ``step_stats`` (see :meth:`_read_step_stats`). A frame whose tile list outgrew its
            buffer (``tile_check="frame"``), or that wanted depth maps the cache did not hold
            (``map_cache_mb``, more photos than one texture array holds), is rendered again and
            carries ``rerendered`` True; its timings are those of the last rendering. With a
            partial map cache also ``maps_missing``: the maps the frame still did not find (0
            unless it needs more maps than the cache holds); without ``readback`` the frame is not
            rendered again, and ``maps_missing`` counts those the frame two before did not find,
            loaded now (with ``async_photos``: read in the background, uploaded by this or a later
            frame, at most ``max_map_loads_per_frame`` a frame; :mod:`dmrt.runtime.maps`).
        """
        # None: the tile list outgrew its buffer (grown now), or depth maps were missing (loaded
        # now; a frame's second rendering may find a map that only its first's results needed)
        for attempt in range(RENDER_ATTEMPTS):
            frame = self._frame(camera, width, height, readback, retry=attempt == RENDER_ATTEMPTS - 1)
            if frame is not None:
                if attempt:
                    frame["rerendered"] = True
                return frame
        raise RuntimeError("the tile list outgrew its buffer twice for the same view")

    def _frame(self, camera: Camera, width: int | None, height: int | None, readback: bool,
               retry: bool = False) -> dict | None:
        """One rendering of :meth:`render`'s frame; None if its tile list outgrew its buffer, or
        (unless ``retry``) if it wanted depth maps that were not resident (loaded now)."""
        cfg = self.config
        cam = camera.resized(width or cfg.width, height or cfg.height)
        w, h = cam.width, cam.height
        self._allocate(w, h)
        b = self._buffers
        local = cam.relative_to(self.origin)
        cam_uniforms = camera_uniforms(local)
        npix = w * h
        grid = (groups(w, 8), groups(h, 8))
        ctx, timer = self.ctx, self.timer
        timer.reset()
        self.splats.begin_frame()
        self.shading.begin_frame()
        self.maps.bind()
        view_list = None  # every photo scored: every map is resident (the paper's scenes)
        if self.maps.partial and self.view_choice is not None:
            # the view choice scores a short list, not every photo (up to 2048 resident ones: 4.1 ms
            # a frame on the H200 with 10,240 photos): the 4 x view_candidates photos nearest the
            # camera and the first 4 x view_candidates the last frame wanted (its label histogram,
            # which counts each of its candidates: the photos it chose, then the other candidates
            # and runners-up), at most 8 x view_candidates rows (64 by default), whatever the scene.
            # The nearest come in before the frame, a quarter of the slots at most (the rest hold
            # the maps the labels need); a listed photo whose map is not resident costs nothing.
            # A partial sort, every frame over every photo
            m = 4 * self.config.view_candidates
            dist = np.linalg.norm(self._centres - cam.center, axis=1)
            near = np.argpartition(dist, m - 1)[:m] if 0 < m < len(dist) else np.arange(len(dist))[:m]
            near = near[np.argsort(dist[near])]
            self.maps.ensure(near[:min(m, self.maps.n_slots // 4)], block=readback)
            view_list = np.fromiter(dict.fromkeys([*near.tolist(), *self.images.wanted[:m]]), np.int64)

        self.visibility.run(cam_uniforms, (w, h), cfg.layers, b["layer_depth"], b["layer_label"], timer)

        # the search, which lists the holes it leaves; then the fill passes, each over the holes the
        # one before left (work lists: shaders/dmrt_raytrace.glsl)
        fill_passes = cfg.fill_passes if cfg.raytrace else 0
        # normals only for a frame that is read back (dmrt_frame.glsl: the Hit record leaves them out)
        search = {"u_layers": cfg.layers, "u_max_steps": cfg.max_steps, "u_binary_steps": cfg.binary_steps,
                  "u_threshold": float(cfg.discontinuity_threshold), "u_depthmaps": 0,
                  "u_max_groups": self._max_groups, "u_normals": int(readback), **cam_uniforms}
        holes = (b["holes_a"], b["holes_b"])
        raytrace, fill = self._search_programs[readback]
        with timer.section("raytracing:search"):
            if self.step_stats is not None:
                fill_u32(ctx, self.step_stats, 0, 4 * cfg.layers * STEP_BINS)
                ctx.memory_barrier(_BARRIER)
                self.step_stats.bind_to_storage_buffer(abi.B_STEP_STATS)
            holes[0].write(EMPTY_DISPATCH)
            b["layer_depth"].bind_to_storage_buffer(abi.B_LAYER_DEPTH)
            b["layer_label"].bind_to_storage_buffer(abi.B_LAYER_LABEL)
            b["hits"].bind_to_storage_buffer(abi.B_HITS)
            holes[0].bind_to_storage_buffer(abi.B_HOLES_NEXT)
            b["normals"].bind_to_storage_buffer(abi.B_NORMALS)
            self.photos.bind_to_storage_buffer(abi.B_PHOTOS)
            self.depthmaps.use(0)
            set_uniforms(raytrace, u_fill=int(fill_passes > 0), **search)
            raytrace.run(*grid)
            ctx.memory_barrier(_BARRIER)
        with timer.section("raytracing:hole_fill"):
            for fill_pass in range(fill_passes):
                current, following = holes[fill_pass % 2], holes[(fill_pass + 1) % 2]
                following.write(EMPTY_DISPATCH)
                current.bind_to_storage_buffer(abi.B_HOLES)
                following.bind_to_storage_buffer(abi.B_HOLES_NEXT)
                set_uniforms(fill, u_pass=fill_pass, u_fill=int(fill_pass + 1 < fill_passes),
                             **{**search, "u_max_steps": cfg.fill_max_steps})
                fill.run_indirect(current)
                ctx.memory_barrier(_BARRIER)

        # the final labels' label check (shaders/dmrt_final_label.glsl)
        check = {"u_label_check": int(cfg.label_check), "u_visibility_tol": float(cfg.label_check_tolerance),
                 "u_depthmaps": 0}
        self.photos.bind_to_storage_buffer(abi.B_PHOTOS)
        self.depthmaps.use(0)
        tiles = self.visibility.tiles
        finalized = self._labels_finalized  # by the labeling pass on the tile lists (no splatting)
        with timer.section("labeling"):
            if finalized:
                tiles.label_pass(cam_uniforms, b["hits"], finalize=check)
            else:
                fill_u32(ctx, b["key"], EMPTY_BITS, 2 * npix if self.int64 else npix)
                if not self.int64:
                    fill_u32(ctx, b["vlabel"], EMPTY_LABEL, npix)
                ctx.memory_barrier(_BARRIER)
                if cfg.labeling and self.int64:
                    self.splats.run("dmrt_labeling", {"INT64": 1}, cam_uniforms,
                                    {abi.B_KEY: b["key"], abi.B_HITS: b["hits"]})
                elif cfg.labeling:
                    for resolve in (0, 1):
                        self.splats.run("dmrt_labeling", {"RESOLVE": resolve}, cam_uniforms,
                                        {abi.B_KEY: b["key"], abi.B_VLABEL: b["vlabel"], abi.B_HITS: b["hits"]})

        # image management: the final labels here (unless the labeling pass left them), then the
        # histogram pass and the uploads (timed on the GPU); the readback between them waits for the
        # frame so far and is CPU time
        if not finalized:
            with timer.section("image_management:label_finalize"):
                b["key"].bind_to_storage_buffer(abi.B_KEY)
                b["vlabel"].bind_to_storage_buffer(abi.B_VLABEL)
                b["hits"].bind_to_storage_buffer(abi.B_HITS)
                set_uniforms(self._finalize, u_use_labeling=int(cfg.labeling), **check, **cam_uniforms)
                self._finalize.run(*grid)
                ctx.memory_barrier(_BARRIER)
        blend = None
        if self.view_choice is not None:
            self.view_choice.run(timer, b["hits"], self.photos, self.depthmaps, cam_uniforms, view_list)
            blend = self.view_choice.blend_buffer
        frame, hits = self.shading.finish(b["hits"], b["colors"], b["normals"], self.depthmaps, cam_uniforms, STAGES,
                                          "rendering a DMRT frame", readback, blend)
        if tiles is not None and tiles.end_frame():
            return None
        if self.maps.partial:  # maps a frame wanted and did not find: loaded (and a read-back frame again)
            used = self.images.wanted
            missing = self.maps.end_frame(used, wait=readback)
            # the photos this frame used stay: the missing ones take the least recently used others
            loaded = self.maps.ensure([*missing, *used], block=readback) if len(missing) else 0
            if readback and loaded and not retry:
                return None
            frame["maps_missing"] = len(missing)
        if readback:
            frame["label_raw"] = hits["label"].copy()
            frame["layer_used"], frame["iterations"] = hit_layer_iters(hits)
        if self.step_stats is not None:
            frame["step_stats"] = self._read_step_stats()
        return frame

    def _read_step_stats(self) -> dict:
        """``mean_step_m`` (k, STEP_BINS) float64 mean step length along the ray (metres) of the
        i-th iterative-search step in layer l (0 where none; the last bin pools later steps) and
        ``count`` (k, STEP_BINS) int64 number of such steps."""
        raw = np.frombuffer(self.shading.staging.read(self.step_stats), np.uint32).reshape(self.config.layers, STEP_BINS, 4)
        count = raw[..., 0].astype(np.int64)
        total = (raw[..., 1].astype(np.float64) + raw[..., 2].astype(np.float64) * 2.0 ** 32) * 1e-5
        return {"mean_step_m": np.divide(total, count, out=np.zeros_like(total), where=count > 0),
                "count": count}

    def flush_photos(self) -> int:
        """Wait for the photos being streamed and upload all that the last frame wanted; the next
        frame of the same view is then textured as with synchronous, unbounded streaming."""
        return self.shading.flush_photos()

    def depth_at(self, x: int, y: int) -> float:
        """The last frame's camera z at pixel (x, y) (:class:`dmrt.runtime.protocol.GpuColorRenderer`)."""
        return hit_depth_at(self.shading.staging, self._buffers["hits"], self._size[0], x, y)

    def gpu_colors(self) -> moderngl.Buffer:
        """The last frame's colours on the GPU (:class:`dmrt.runtime.protocol.GpuColorRenderer`)."""
        return self._buffers["colors"]

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
        read = self.shading.staging.read  # the layer buffers stay in GPU memory (Staging: why)
        bits = np.frombuffer(read(self._buffers["layer_depth"], 4 * k * w * h), np.uint32).reshape(k, h, w)
        label = np.frombuffer(read(self._buffers["layer_label"], 4 * k * w * h), np.int32).reshape(k, h, w).copy()
        depth = bits.view(np.float32).copy()
        depth[bits == EMPTY_BITS] = 0.0
        label[label == EMPTY_LABEL] = -1
        return {"depth": depth, "label": label}

    def release(self) -> None:
        """Free this renderer's GPU resources (cached programs stay with the context)."""
        self._release_frame()
        self.timer.release()
        self.visibility.release()
        self.splats.release()
        self.shading.release()
        for obj in (self.maps, self.step_stats, self.view_choice):
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
            "normals": self.ctx.buffer(reserve=12 * npix),
            "colors": self.ctx.buffer(reserve=4 * npix),
            # the fill passes' lists of holes: a 16-byte header, then at most one pixel index per pixel
            "holes_a": self.ctx.buffer(reserve=16 + 4 * npix),
            "holes_b": self.ctx.buffer(reserve=16 + 4 * npix),
        }
        if not self._labels_finalized:  # the labeling pass's labels, for the finalize pass
            self._buffers["key"] = self.ctx.buffer(reserve=8 * npix)  # 64-bit keys on the int64 path
            self._buffers["vlabel"] = self.ctx.buffer(reserve=4 * npix)
        self._size = (w, h)
        self.gpu_bytes["layers"] = 8 * k * npix
        if self.config.method == "kbuffer":
            self.gpu_bytes["kbuffer"] = 4 * npix * (self.config.kbuffer_slots or 6 * k + 2)
        self.gpu_bytes["frame"] = sum(buf.size for name, buf in self._buffers.items() if not name.startswith("layer_"))

    def _release_frame(self) -> None:
        for buf in self._buffers.values():
            buf.release()
        self._buffers = {}
        self._size = None
