"""View-dependent photo choice (an addition to the paper; ``RenderConfig.photo_choice="view"``).

The paper textures each pixel from the photo fixed per proxy in preprocessing (the closest, most
orthogonal one). On real photos - not Lambertian, geometry not exact - the photo whose viewing
direction is closest to the view's agrees far better with what a camera there sees: the ranking of
view-dependent texture mapping and unstructured lumigraph rendering (Debevec et al. 1996; Buehler et
al. 2001). DMRT holds every photo's depth map on the GPU, so it can test at each pixel, with one
fetch a photo, which photos see the raytraced point. Per frame, after the final labels:

1. ``scores`` (``shaders/dmrt_view_scores.glsl``): about :data:`SAMPLES` pixels of the frame on a
   grid, each tested against every photo; a photo that sees a sample adds 1 / its penalty. The
   ``candidates`` best (``shaders/dmrt_photo_choice.glsl``, as the photo cache ranks its histogram)
   are the photos every pixel tests: a bounded per-pixel cost whatever the number of photos. With
   every map resident (the paper's scenes) every photo is scored; with a partial map cache the
   renderer passes a short list (the photos nearest the camera and those the last frame used) and
   only those are scored, so the cost follows the list and not the scene;
2. ``choice`` (``shaders/dmrt_view_choice.glsl``): per pixel, its final label and those candidates
   ranked by penalty = the angle between the view ray and the photo's ray to the point, plus
   ``distance_weight`` per octave by which the photo's distance to the point differs from the
   view's, plus ``turn_weight`` times the angle between the photo's optical axis and the view's;
   the best that see the point (depth map within ``tolerance``) are kept, the first becomes the
   final label (histogram, photo cache and leveling follow it) and with ``blend`` > 1 the texturing
   pass mixes the ``blend`` best with unstructured-lumigraph weights, which fall smoothly to 0 as a
   photo is overtaken (no popping seams as the camera moves). Where two frame pixels span at most a
   texel of the finest depth map (:func:`quads`: 3840x2160 over the paper's maps), one choice serves
   a 2x2 quad of one surface.

``reference.twins.view_scores`` and ``reference.twins.view_choice`` are the numpy twins.
"""

from __future__ import annotations

import math

import moderngl
import numpy as np

from dmrt.gl import abi
from dmrt.gl.abi import STATUS_HEADER_WORDS
from dmrt.gl.kernels import Staging, fill_u32, groups
from dmrt.gl.shaders import load_program, set_uniforms
from dmrt.runtime.ranking import PhotoRanking

_BARRIER = moderngl.SHADER_STORAGE_BARRIER_BIT
# Samples of the frame scored against every photo: enough that a photo covering a 2 % corner of the
# view is sampled ~80 times, few enough that 10,000 photos cost 40M cheap tests.
SAMPLES = 4096
MAX_BLEND = 4  # the blend record holds four photos (abi.B_VIEW_BLEND)


def sample_grid(width: int, height: int, samples: int = SAMPLES) -> tuple[int, tuple[int, int]]:
    """The frame's score samples: pixel ``(i * stride + stride // 2, j * stride + stride // 2)``
    (clamped to the frame) for ``i < columns``, ``j < rows``.

    Returns
    -------
    stride : int, pixels between samples
    (columns, rows) : the grid's size
    """
    stride = max(1, math.ceil(math.sqrt(width * height / samples)))
    return stride, (-(-width // stride), -(-height // stride))


def quads(frame_focal: float, map_focal: float) -> bool:
    """Whether a frame of focal length ``frame_focal`` (pixels) chooses once per 2x2 quad of one
    surface: where two of its pixels span at most a texel of the finest depth map (focal length
    ``map_focal`` texels), which cannot tell them apart (``shaders/dmrt_view_choice.glsl``)."""
    return frame_focal >= 2.0 * map_focal


class ViewChoice:
    """The view-dependent photo choice of one renderer.

    Parameters
    ----------
    ctx : moderngl.Context
    n_photos : int
    candidates : int
        Photos each pixel tests besides its own label (the frame's best-scored).
    blend : int
        Photos mixed per pixel, 1 (the best alone) to :data:`MAX_BLEND`.
    distance_weight : float
        Radians of penalty per octave by which a photo's distance to the point differs from the view's.
    turn_weight : float
        Radians of penalty per radian the photo's optical axis turns from the view's.
    tolerance : float
        Metres: a photo whose depth map differs by more from the point's depth does not see it.
    map_focal : float
        The finest depth map's focal length, texels (the largest ``fx`` of the photos' maps): a frame
        whose focal length is at least twice it chooses once per 2x2 quad of one surface
        (:func:`quads`).
    map_defines : dict, optional
        :attr:`dmrt.runtime.maps.MapCache.defines`.

    Attributes
    ----------
    blend_buffer : moderngl.Buffer or None
        After :meth:`run` with ``blend`` > 1: (h, w) ivec4 records of ``shaders/dmrt_view_choice.glsl``.
    listed : np.ndarray or None
        (m,) int32 the photos the last :meth:`run` scored; None: every photo.
    """

    def __init__(self, ctx: moderngl.Context, n_photos: int, candidates: int, blend: int,
                 distance_weight: float, turn_weight: float, tolerance: float, map_focal: float,
                 map_defines: dict | None = None):
        self.ctx, self.n_photos, self.blend = ctx, int(n_photos), int(blend)
        self.map_focal = float(map_focal)
        self.n_candidates = int(candidates)
        self._uniforms = {"u_distance_weight": float(distance_weight), "u_turn_weight": float(turn_weight),
                          "u_view_tol": float(tolerance)}
        self.scores = ctx.buffer(reserve=4 * self.n_photos)
        self.candidates = ctx.buffer(reserve=4 * (STATUS_HEADER_WORDS + max(self.n_candidates, 1)))
        self.candidates.write(np.zeros(STATUS_HEADER_WORDS, np.uint32).tobytes())  # no candidates
        # the scores test every (listed) photo: a map not resident is no candidate, not a miss
        scores_defines = {**map_defines, "MAP_FLAGS": 0} if map_defines else {}
        self._scores = load_program(ctx, "dmrt_view_scores", scores_defines or None)
        # a partial map cache's renderer passes a short list every frame (run's photo_list)
        self._scores_listed = (load_program(ctx, "dmrt_view_scores", {**scores_defines, "PHOTO_LIST": 1})
                               if map_defines else None)
        self._list = ctx.buffer(reserve=4 * 64)  # B_VIEW_LIST, grown to the longest list
        self.listed: np.ndarray | None = None
        self._rank = PhotoRanking(ctx, self.n_photos, "B_VIEW_SCORES", "B_VIEW_CANDIDATES")
        self._choice = load_program(ctx, "dmrt_view_choice", {"BLEND": self.blend, "CANDIDATES": self.n_candidates,
                                                              **(map_defines or {})})
        self.blend_buffer: moderngl.Buffer | None = None
        self._staging = Staging(ctx)  # the read_ diagnostics': the buffers stay in GPU memory (Staging: why)

    @property
    def nbytes(self) -> int:
        """GPU bytes held (scores, candidates, the photo list, their ranking's list, the blend records
        of the last frame size)."""
        blend = self.blend_buffer.size if self.blend_buffer else 0
        return self.scores.size + self.candidates.size + self._list.size + self._rank.nbytes + blend

    def run(self, timer, hits: moderngl.Buffer, photos: moderngl.Buffer, depthmaps, cam_uniforms: dict,
            photo_list=None) -> None:
        """Choose the photos of every pixel of a frame whose ``Hit`` records (with final labels) are
        in ``hits``: their ``final_label`` is overwritten, and with ``blend`` > 1 :attr:`blend_buffer`
        written. ``depthmaps``: the renderer's depth-map texture array (bound to unit 0).

        ``photo_list``: None scores every photo (n_photos workgroup rows); else (m,) int photo
        indices without repeats, and only those are scored (m rows: the cost follows the list), the
        others' scores left 0, so only listed photos can become candidates."""
        ctx = self.ctx
        w, h = cam_uniforms["u_size"]
        if self.blend > 1 and (self.blend_buffer is None or self.blend_buffer.size != 16 * w * h):
            if self.blend_buffer is not None:
                self.blend_buffer.release()
            self.blend_buffer = ctx.buffer(reserve=16 * w * h)
        hits.bind_to_storage_buffer(abi.B_HITS)
        photos.bind_to_storage_buffer(abi.B_PHOTOS)
        depthmaps.use(0)
        with timer.section("image_management:view_candidates"):
            if self.n_candidates:
                stride, grid = sample_grid(w, h)
                fill_u32(ctx, self.scores, 0, self.n_photos)
                ctx.memory_barrier(_BARRIER)
                self.scores.bind_to_storage_buffer(abi.B_VIEW_SCORES)
                program, rows, self.listed = self._scores, self.n_photos, None
                if photo_list is not None:
                    program = self._scores_listed or load_program(ctx, "dmrt_view_scores", {"PHOTO_LIST": 1})
                    rows = self._upload_list(photo_list)
                for photo0 in range(0, rows, 65535):  # a dispatch holds 65535 rows at most
                    set_uniforms(program, u_samples=grid, u_stride=stride, u_photo0=photo0, u_depthmaps=0,
                                 **self._uniforms, **cam_uniforms)
                    program.run(groups(grid[0] * grid[1], 64), min(rows - photo0, 65535))
                ctx.memory_barrier(_BARRIER)
                self._rank.run(self.scores, self.candidates, self.n_candidates)
                ctx.memory_barrier(_BARRIER)
        with timer.section("image_management:view_choice"):
            self.candidates.bind_to_storage_buffer(abi.B_VIEW_CANDIDATES)
            if self.blend_buffer is not None:
                self.blend_buffer.bind_to_storage_buffer(abi.B_VIEW_BLEND)
            step = 2 if quads(cam_uniforms["u_K"][0], self.map_focal) else 1
            set_uniforms(self._choice, u_depthmaps=0, u_quads=step == 2, **self._uniforms, **cam_uniforms)
            self._choice.run(groups(-(-w // step), 8), groups(-(-h // step), 8))
            ctx.memory_barrier(_BARRIER)

    def _upload_list(self, photo_list) -> int:
        """``photo_list`` into the list buffer (grown if needed), bound at ``abi.B_VIEW_LIST``, and
        :attr:`listed`; returns its length."""
        self.listed = np.ascontiguousarray(photo_list, np.int32)
        if self.listed.nbytes > self._list.size:
            self._list.release()
            self._list = self.ctx.buffer(reserve=self.listed.nbytes)
        if self.listed.size:
            self._list.write(self.listed.tobytes())
        self._list.bind_to_storage_buffer(abi.B_VIEW_LIST)
        return int(self.listed.size)

    def read_candidates(self) -> np.ndarray:
        """(m,) int32 the last frame's candidates, best-scored first (waits for the GPU)."""
        words = np.frombuffer(self._staging.read(self.candidates), np.int32)
        return words[STATUS_HEADER_WORDS:STATUS_HEADER_WORDS + words[1]].copy()

    def read_blend(self, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
        """The last frame's blend (``blend`` > 1; waits for the GPU).

        Returns
        -------
        others : (h, w, 3) int32, the 2nd to 4th photo of each pixel, -1 = none
        weights : (h, w, 4) float32, the weights of the 1st (the final label) to 4th photo, 8-bit
            quantised (sum ~1; 0 for background pixels and unused entries)
        """
        rec = np.frombuffer(self._staging.read(self.blend_buffer, 16 * width * height), np.int32).reshape(
            height, width, 4)
        packed = rec[..., 3].view(np.uint32)
        weights = np.stack([(packed >> (8 * i)) & 0xFF for i in range(4)], -1).astype(np.float32) / 255.0
        return rec[..., :3].copy(), weights

    def release(self) -> None:
        for obj in (self.scores, self.candidates, self._list, self._rank, self.blend_buffer, self._staging):
            if obj is not None:
                obj.release()
