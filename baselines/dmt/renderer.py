"""The DMT runtime (Arikan et al. 2014, the baseline of the DMRT paper's Section 6.5): every depth
map triangulated and rasterized, overlapping maps stitched by an ε threshold.

Per frame, each stage timed on the GPU (:class:`dmrt.gl.GpuTimer`):

1. ``culling`` - one compute thread per depth map tests its bounding box against the view frustum
   and writes its draw command (``shaders/dmt_cull.glsl``); culled maps draw nothing;
2. ``rasterization`` - pass 1: every depth map as a grid mesh (two triangles per quad of texels,
   generated from ``gl_VertexID``; triangles touching an empty texel or spanning a depth jump larger
   than the discontinuity threshold are dropped, ``shaders/dmt_mesh.glsl``), z-buffered: the camera z
   of the nearest surface per pixel;
3. ``stitching`` - pass 2: the meshes again; fragments more than ε behind pass 1's surface are
   discarded (another surface), the rest are the same surface seen by several depth maps and the
   best-resolved one wins (smallest texel footprint ``z_j / (f_j |cos θ_j|)`` of its depth map at
   that point, by the depth test); then the pixel's label is that map's label at its texel nearest
   to the fragment (``shaders/dmt_resolve.glsl`` packs the results);
4. ``image_management`` and 5. ``texturing`` - DMRT's own passes and photo cache
   (:mod:`dmrt.runtime.texturing`) on the DMT labels.

The stitching rule. The DMRT paper (Fig. 11) describes DMT's behaviour: with a small ε two depth
maps of one surface that disagree by more than ε count as different surfaces and the nearer one
wins, even if it is the low-resolution one; and a surface less than ε behind another is taken for
the same surface, so a better-resolved hidden feature "shines through". Within ε the
better-resolved map is chosen - here by its texel footprint at the point, which with every map at the
same texel count means the closest and most frontal view (the labeling data term's preference).
Depth, normal and the map come from the winning fragment: DMT shows the winner's geometry, there
is no blending.

6. ``leveling`` (``DMTConfig.leveling``) - DMRT's screen-space leveling (:mod:`dmrt.runtime.leveling`).

Usage::

    renderer = DMTRenderer(read_bundle("scene.bundle"), DMTConfig(width=512))
    frame = renderer.render(camera, 1280, 720)
"""

from __future__ import annotations

from dataclasses import dataclass

import moderngl
import numpy as np

from baselines.dmt.geometry import bounding_box, box_corners, dmt_size, load_depth_map, texel_points
from baselines.dmt.labeling import DMTLabelingConfig, Labeler, dmt_labels
from dmrt.io.bundle import Bundle
from dmrt.camera import Camera
from dmrt.errors import InputError
from dmrt.gl.context import get_context
from dmrt.gl.shaders import load_program, set_uniforms
from dmrt.gl.timer import GpuTimer
from dmrt.options import option, validate
from dmrt.gl import abi
from dmrt.gl.abi import HIT_DTYPE
from dmrt.gl.kernels import fill_u32, groups
from dmrt.gl.mapped import MappedBuffer
from dmrt.runtime.shading import FrameShading, camera_uniforms, hit_depth_at

STAGES = ("culling", "rasterization", "stitching", "image_management", "texturing", "leveling")
_BARRIER = moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT
_MAX_VERTEX_ID = 2 ** 31 - 1


@dataclass
class DMTConfig:
    """Parameters of the DMT runtime (lengths in metres); each field is a ``dmrt render --method dmt``
    option (``--dmt-*`` for those whose names RenderConfig uses otherwise)."""

    width: int | None = option(None, "depth-map width in texels (paper: 256, 512, 1024; heights follow each "
                                     "photo's aspect); default and at most the bundle's maps' width (coarser maps "
                                     "are resampled from them)", minimum=2)
    # Two maps of one surface disagree by their triangulation error (under a texel footprint: 8 mm
    # at 5 m for a 1024-wide map of an 80-degree photo, 3.3 cm at 256) plus scan noise and splat
    # bias (a few mm); real features (door jambs, steps, furniture) stand out by more than 5 cm.
    # Smaller hides less (shows low-resolution surfaces), larger hides thin features (paper
    # Fig. 11); 5 cm also stays well under the 20 cm discontinuity threshold.
    epsilon: float = option(0.05, "stitching threshold: fragments within this behind the nearest surface are the "
                                  "same surface (the best-resolved map wins), metres", minimum=0.0)
    discontinuity_threshold: float = option(0.20, "triangles whose texels' depths span more than this are dropped, "
                                                  "metres (paper: 0.20)", minimum=1e-6)
    labeler: Labeler = option("graphcut", "graphcut (DMT's labeling, cached in the bundle), wta (winner-take-all) "
                                          "or own (each map's own photo); the last two for frame-rate runs")
    near: float = option(0.05, "near clipping plane of the rasterization, metres; the far plane follows the depth "
                               "maps' boxes", minimum=1e-6)
    min_cos: float = option(0.05, "clamp of |cos theta| in the quality key (a grazing view's footprint is at most "
                                  "20x its frontal one)", minimum=1e-6, maximum=1.0)
    cache_mb: float | None = option(None, "as RenderConfig's: GPU MiB for full-resolution photos (default from "
                                          "the GPU's free memory)", minimum=0.0)
    async_photos: bool = option(True, "as RenderConfig's: decode photos on background threads")
    max_uploads_per_frame: int = option(4, "as RenderConfig's: photo uploads per frame (0 = no bound)", minimum=0)
    cpu_cache_mb: float = option(1024.0, "as RenderConfig's: CPU MiB of decoded photos", minimum=0.0)
    progress: bool = option(True, "a progress bar when the labels must be computed")
    photometric: bool = option(False, "as RenderConfig's: the photos' gains from preprocessing's photometric "
                                      "adjustment")
    leveling: bool = option(False, "screen-space leveling, as RenderConfig's")
    leveling_min_samples: int = option(16, "leveling: seam samples a photo pair needs to count", minimum=1)
    leveling_max_gain: float = option(2.0, "leveling: the bound on a gain and its inverse", minimum=1.0)

    def __post_init__(self):
        validate(self)


class DMTRenderer:
    """DMT rendering of a scene bundle on one GL context.

    Parameters
    ----------
    bundle : Bundle
    config : DMTConfig, optional
    ctx : moderngl.Context, optional (default: the process-wide context)
    labels : list of (h_i, w_i) int32, optional
        Per-texel labels of every depth map at the DMT resolution; default
        :func:`baselines.dmt.labeling.dmt_labels` (cached in the bundle, computed on first use).

    Attributes
    ----------
    width : int, the DMT depth-map width.
    sizes : list of (w, h) per depth map.
    boxes : (n, 2, 3) float64 origin-relative bounding boxes of the maps (NaN for empty maps).
    labeling_meta : dict, the labeling cache's metadata (None when labels were given).
    gpu_bytes : dict, GPU memory per resource (``depthmaps``, ``labels``, ``images_low``,
        ``image_cache``, ``photos``, ``draw`` and after a frame ``frame``), bytes.
    """

    name = "dmt"

    def __init__(self, bundle: Bundle, config: DMTConfig | None = None, ctx: moderngl.Context | None = None,
                 labels: list | None = None):
        self.bundle = bundle
        self._config = cfg = config or DMTConfig()
        self.ctx = ctx or get_context()
        self.origin = np.asarray(bundle.origin, np.float64)
        self.cameras = bundle.cameras
        n = len(self.cameras)
        if n == 0:
            raise ValueError(f"{bundle.root}: the bundle has no photos")
        layers = self.ctx.info["GL_MAX_ARRAY_TEXTURE_LAYERS"]
        if n > layers:  # DMRT caches its maps (dmrt/runtime/maps.py); this baseline keeps every one
            raise InputError(bundle.root, f"{n} photos: DMT holds every depth map in one texture array, "
                                          f"at most {layers} on this GPU (DMRT has no such limit)")
        stored = [bundle.depth_map(i) for i in range(n)]
        self.width = int(cfg.width or stored[0].shape[1])
        depths = [load_depth_map(bundle, i, self.width, stored[i]) for i in range(n)]
        del stored
        self.labeling_meta = None
        if labels is None:
            labels, self.labeling_meta = dmt_labels(
                bundle, self.width, DMTLabelingConfig(labeler=cfg.labeler,
                                                      discontinuity_threshold=cfg.discontinuity_threshold),
                progress=cfg.progress)
        self.sizes = [dmt_size(c, self.width) for c in self.cameras]
        for i, (lab, (w, h)) in enumerate(zip(labels, self.sizes)):
            if np.shape(lab) != (h, w):
                raise ValueError(f"labels of depth map {i}: shape {np.shape(lab)}, expected ({h}, {w})")
        dims = (max(s[0] for s in self.sizes), max(s[1] for s in self.sizes))
        self.timer = GpuTimer(self.ctx, wait=False)  # as DMRT's: the render loop never waits on it
        ctx = self.ctx

        # depth maps (R32F) and labels (R16I when photo indices fit, else R32I), one layer per map
        ldtype = "i2" if n < 2 ** 15 else "i4"
        self.depthmaps = ctx.texture_array((*dims, n), 1, dtype="f4")
        self.labels = ctx.texture_array((*dims, n), 1, dtype=ldtype)
        for tex in (self.depthmaps, self.labels):
            tex.filter = (moderngl.NEAREST, moderngl.NEAREST)
        boxes = np.full((n, 2, 3), np.nan)
        for i, (d, lab) in enumerate(zip(depths, labels)):
            h, w = d.shape
            self.depthmaps.write(np.ascontiguousarray(d, np.float32).tobytes(), viewport=(0, 0, i, w, h, 1))
            self.labels.write(np.ascontiguousarray(lab, ldtype).tobytes(), viewport=(0, 0, i, w, h, 1))
            cam = self.cameras[i].relative_to(self.origin).scaled(w, h)
            boxes[i] = bounding_box(texel_points(d, cam))
        self.boxes = boxes
        # seam visibility tolerance: within a few DMT texels (a coarse map's surface is further off)
        self.shading = FrameShading(ctx, bundle, self.timer, self.sizes, cfg, cfg.epsilon)
        self.images, self.photos, self.leveler = self.shading.images, self.shading.photos, self.shading.leveler
        gpu_boxes = np.zeros((n, 2, 4), np.float32)
        ok = np.isfinite(boxes).all(axis=(1, 2))
        gpu_boxes[ok, :, :3] = boxes[ok]
        gpu_boxes[ok, 0, 3] = 1.0
        self._boxes_buf = ctx.buffer(gpu_boxes.tobytes())
        self._commands = ctx.buffer(reserve=20 * n)
        # (maps culled, triangles drawn), counted by the culling pass's atomics; read at each frame's
        # end from a copy in mapped host memory, so that the read waits for the culling pass only,
        # not for the whole frame (dmrt/gl/mapped.py)
        self._stats = ctx.buffer(reserve=8)
        self._stats_host = MappedBuffer(ctx, bytes(8))
        # gl_VertexID is an int: maps are drawn in groups whose vertex ranges stay below 2^31
        self.verts_per_map = 6 * (dims[0] - 1) * (dims[1] - 1)
        self.maps_per_draw = max(1, _MAX_VERTEX_ID // max(self.verts_per_map, 1))
        self._cull = load_program(ctx, "dmt_cull")
        self._pass = {k: load_program(ctx, "dmt_mesh", {"PASS": k}) for k in (1, 2)}
        self._vao = {k: ctx.vertex_array(p, []) for k, p in self._pass.items()}
        self._resolve = load_program(ctx, "dmt_resolve")
        self._size: tuple[int, int] | None = None
        self._fb: dict = {}
        self.gpu_bytes = {"depthmaps": dims[0] * dims[1] * n * 4,
                          "labels": dims[0] * dims[1] * n * (2 if ldtype == "i2" else 4),
                          **self.shading.nbytes, "draw": self._boxes_buf.size + self._commands.size + self._stats.size}

    @property
    def config(self) -> DMTConfig:
        """The configuration; fixed at construction (textures and programs are built from it)."""
        return self._config

    @config.setter
    def config(self, value) -> None:
        raise AttributeError("DMTRenderer.config is fixed at construction: make a new DMTRenderer")

    # -- public -------------------------------------------------------------------------------
    def render(self, camera: Camera, width: int | None = None, height: int | None = None,
               maps=None, readback: bool = True) -> dict:
        """Render one frame.

        Parameters
        ----------
        camera : Camera, world coordinates; any resolution.
        width, height : int, optional frame size (default the camera's; a missing side follows the
            camera's aspect ratio).
        maps : sequence of int, optional
            Draw only these depth maps (the others count as culled); default all.
        readback : bool
            False: only ``timings``, ``part_timings``, ``timings_lag``, ``cpu_ms`` and ``stats`` (as
            ``dmrt.runtime.renderer.Renderer.render``).

        Returns
        -------
        dict
            The frame contract of :mod:`dmrt.io.frames` - ``depth`` (h, w) float32 camera z (0 =
            background), ``label`` (h, w) int32 (-1 = none), ``color`` (h, w, 3) uint8, ``normal``
            (h, w, 3) float32 unit world normal facing the camera - plus ``depth_map`` (h, w) int32
            (the depth map that won the pixel, -1 = none), ``timings`` {stage: GPU ms} for
            :data:`STAGES` and ``timings_lag`` as DMRT's (an earlier frame's, NaN where
            unavailable: :meth:`dmrt.gl.GpuTimer.frame_timings`), ``cpu_ms`` {``status_read``,
            ``image_management``} as DMRT's, and ``stats`` {``maps``, ``maps_culled``,
            ``maps_drawn``, ``triangles_drawn`` (upper bound: triangles of the drawn maps, before
            the discontinuity drop)}.
        """
        cfg, ctx, timer = self.config, self.ctx, self.timer
        cam = camera.resized(width, height)
        w, h = cam.width, cam.height
        self._allocate(w, h)
        fb = self._fb
        n = len(self.cameras)
        vp = cam.gl_view_projection(cfg.near, self.far_plane(cam), self.origin)
        local = cam.relative_to(self.origin)
        cam_uniforms = camera_uniforms(local)
        vp_bytes = np.ascontiguousarray(vp.T, np.float32)  # GLSL reads column-major
        timer.reset()
        self.shading.begin_frame()

        with timer.section("culling"):
            fill_u32(ctx, self._stats, 0, 2)
            self._boxes_buf.bind_to_storage_buffer(abi.B_DMT_BOXES)
            self._commands.bind_to_storage_buffer(abi.B_DMT_COMMANDS)
            self._stats.bind_to_storage_buffer(abi.B_DMT_STATS)
            self.photos.bind_to_storage_buffer(abi.B_PHOTOS)
            set_uniforms(self._cull, u_vp=vp_bytes, u_count=n, u_maps_per_draw=self.maps_per_draw,
                         u_verts_per_map=self.verts_per_map)
            self._cull.run(groups(n, 64))
            self._stats_host.copy_from(self._stats, barriers=_BARRIER)
            if maps is not None:  # restrict on the CPU: zero the other maps' vertex counts
                keep = np.zeros(n, bool)
                keep[np.asarray(list(maps), np.int64)] = True
                cmds = np.frombuffer(self.shading.staging.read(self._commands), np.uint32).reshape(n, 5).copy()
                stats = np.frombuffer(self._stats_host.read(), np.uint32).copy()
                stats[0] += int(((cmds[:, 0] > 0) & ~keep).sum())
                stats[1] -= int(cmds[~keep, 0].sum() // 3)
                cmds[~keep, 0] = 0
                self._commands.write(cmds.tobytes())
                self._stats_host.write(stats.tobytes())

        mesh_uniforms = {"u_vp": vp_bytes, "u_eye": local.center.astype(np.float32),
                         "u_verts_per_map": self.verts_per_map, "u_threshold": float(cfg.discontinuity_threshold),
                         "u_min_cos": float(cfg.min_cos), "u_depthmaps": 0, "u_front": 1, "u_labels": 2,
                         "u_epsilon": float(cfg.epsilon)}
        self.depthmaps.use(0)
        self.labels.use(2)
        ctx.depth_func = "<"
        with timer.section("rasterization"):
            with fb["scope1"]:
                fb["fbo1"].clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
                self._draw(1, mesh_uniforms)
        with timer.section("stitching"):
            fb["front"].use(1)
            with fb["scope2"]:
                fb["fbo2"].clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
                self._draw(2, mesh_uniforms)
            fb["surface"].use(3)
            fb["ids"].use(4)
            fb["hits"].bind_to_storage_buffer(abi.B_HITS)
            fb["normals"].bind_to_storage_buffer(abi.B_NORMALS)
            set_uniforms(self._resolve, u_surface=3, u_ids=4, u_normals=int(readback), **cam_uniforms)
            self._resolve.run(groups(w, 8), groups(h, 8))
            ctx.memory_barrier(_BARRIER)

        # the end of the frame: DMRT's (dmrt.runtime.shading) on the DMT hits
        frame, hits = self.shading.finish(fb["hits"], fb["colors"], fb["normals"], self.depthmaps, cam_uniforms,
                                          STAGES, "rendering a DMT frame", readback)
        stats = np.frombuffer(self._stats_host.read(), np.uint32)
        if readback:
            frame["depth_map"] = hits["label"].copy()
        frame["stats"] = {"maps": n, "maps_culled": int(stats[0]), "maps_drawn": n - int(stats[0]),
                          "triangles_drawn": int(stats[1])}
        return frame

    def depth_at(self, x: int, y: int) -> float:
        """The last frame's camera z at pixel (x, y) (:class:`dmrt.runtime.protocol.GpuColorRenderer`)."""
        return hit_depth_at(self.shading.staging, self._fb["hits"], self._size[0], x, y)

    def gpu_colors(self) -> moderngl.Buffer:
        """The last frame's colours on the GPU (:class:`dmrt.runtime.protocol.GpuColorRenderer`)."""
        return self._fb["colors"]

    def flush_photos(self) -> int:
        """Wait for streamed photos and upload all the last frame wanted (as DMRT's Renderer)."""
        return self.shading.flush_photos()

    def release(self) -> None:
        """Free this renderer's GPU resources (cached programs stay with the context)."""
        self._release_frame()
        for vao in self._vao.values():
            vao.release()
        self.shading.release()
        self.timer.release()
        for obj in (self.depthmaps, self.labels, self._boxes_buf, self._commands, self._stats, self._stats_host):
            if obj is not None:
                obj.release()

    def far_plane(self, cam: Camera) -> float:
        """The far clipping plane of a frame of ``cam``: beyond the farthest corner of any depth
        map's box (camera z), metres. (The near plane is ``config.near``.)"""
        ok = np.isfinite(self.boxes).all(axis=(1, 2))
        if not ok.any():
            return 2 * self.config.near + 1.0
        z = cam.relative_to(self.origin).world_to_camera(box_corners(self.boxes[ok]).reshape(-1, 3))[:, 2]
        return float(max(z.max() * 1.01, 2 * self.config.near) + 1.0)

    # -- internals ----------------------------------------------------------------------------
    def _draw(self, k: int, uniforms: dict) -> None:
        prog, vao, n = self._pass[k], self._vao[k], len(self.cameras)
        self.photos.bind_to_storage_buffer(abi.B_PHOTOS)
        for base in range(0, n, self.maps_per_draw):
            set_uniforms(prog, u_map_base=base, **uniforms)
            vao.render_indirect(self._commands, moderngl.TRIANGLES, count=min(self.maps_per_draw, n - base),
                                first=base)


    def _allocate(self, w: int, h: int) -> None:
        if self._size == (w, h):
            return
        self._release_frame()
        ctx = self.ctx
        fb = {"front": ctx.texture((w, h), 1, dtype="f4"), "zbuf1": ctx.depth_texture((w, h)),
              "surface": ctx.texture((w, h), 4, dtype="f4"), "ids": ctx.texture((w, h), 4, dtype="f4"),
              "zbuf2": ctx.depth_texture((w, h)),
              "hits": ctx.buffer(reserve=HIT_DTYPE.itemsize * w * h), "normals": ctx.buffer(reserve=12 * w * h),
              "colors": ctx.buffer(reserve=4 * w * h)}
        for key in ("front", "surface", "ids"):
            fb[key].filter = (moderngl.NEAREST, moderngl.NEAREST)
        fb["fbo1"] = ctx.framebuffer([fb["front"]], fb["zbuf1"])
        fb["fbo2"] = ctx.framebuffer([fb["surface"], fb["ids"]], fb["zbuf2"])
        # one scope per target, reused (moderngl frees scopes only on release())
        fb["scope1"] = ctx.scope(fb["fbo1"], enable_only=moderngl.DEPTH_TEST)
        fb["scope2"] = ctx.scope(fb["fbo2"], enable_only=moderngl.DEPTH_TEST)
        self._fb = fb
        self._size = (w, h)
        self.gpu_bytes["frame"] = (4 + 4 + 16 + 16 + 4 + HIT_DTYPE.itemsize + 12 + 4) * w * h

    def _release_frame(self) -> None:
        for obj in self._fb.values():
            obj.release()
        self._fb = {}
        self._size = None
