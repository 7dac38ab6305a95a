"""DMRT visibility stage (paper Section 5.1.1): the proxy splats P_LD in k label layers.

Layer 1 is the z-buffered nearest proxy disc per pixel (depth + label); layer i+1 is obtained by
splatting the proxies again and discarding, per pixel, disc hits whose label equals layer i's label
there or whose depth is <= layer i's depth (depth peeling, one geometry pass per layer as in the
paper). A disc "hits" a pixel when the ray through the pixel centre meets the oriented disc
(``shaders/splat_depth_common.glsl``, the same primitive as the depth maps); its depth is the camera z
of that intersection. Equal depths at a pixel resolve to the smallest label.

Two GPU paths write the same layer buffers (``RenderConfig.method``):

``"compute"`` (default)
    Per layer two compute passes: ``atomicMin`` on the float bits of z, then a resolve pass where
    discs whose z equals the stored one ``atomicMin`` their label. Portable (no 64-bit atomics,
    which Mesa llvmpipe lacks); discs larger than ``max_thread_pixels`` pixels are splatted by a
    whole workgroup each (dispatch-indirect), as in :mod:`dmrt.preprocess.depthmaps`.
``"kbuffer"``
    One splat pass for all k layers (the paper's future work): every disc hit is inserted into a
    per-pixel sorted list of its ``slots`` nearest fragments (32-bit keys: depth bits with the low
    bits holding the label, lock-free atomicMin cascade), then a resolve pass reads the layers off
    the list as peeling would (the first fragment of each run of equal labels, in depth order). It
    equals the peeled layers except (a) depths are truncated to 23 - label_bits mantissa bits
    (relative 2^-(23 - label_bits): 2e-6 for 12 photos, 3e-5 for 192) and ties within that break
    by label, (b) where more than ``slots`` fragments lie in front of the k-th layer
    (:meth:`VisibilityStage.read_overflow` counts those pixels; their deeper layers stay empty).
``"tiles"``
    One tile-binned walk for all k layers, the per-pixel layer lists in registers
    (:mod:`dmrt.runtime.tiles`, which says where it can differ from peeling).
``"raster"``
    The paper's way: GL_POINTS sprites (geometry-shader quads for discs larger than the largest
    sprite; the depth maps' raster programs with ``WITH_LABEL``) with the per-fragment ray-disc test and the peeling test in the fragment shader,
    z-buffered by a MIN blend on a float32 target (exact nearest z), then the same label resolve as
    a second draw; each target is copied into the layer buffers by a small compute pass.

Layer buffers (GPU): ``layer_depth`` k x h x w uint (float bits of camera z, 0xFFFFFFFF = empty) and
``layer_label`` k x h x w int32 (0x7FFFFFFF = empty), layer after layer, rows from the top.
"""

from __future__ import annotations

import moderngl
import numpy as np

from dmrt.gl import abi
from dmrt.gl.abi import EMPTY_BITS, EMPTY_LABEL, EMPTY_Z, PROXY_FLOATS
from dmrt.gl.kernels import EMPTY_DISPATCH, Staging, fill_u32, groups
from dmrt.gl.shaders import load_program, set_uniforms
from dmrt.gl.timer import timed
from dmrt.morton import morton_order
from dmrt.runtime.tiles import DEFAULT_BATCH, DEFAULT_TOP, TileVisibility

_BARRIER = moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT


def pack_proxies(proxy: dict) -> np.ndarray:
    """(n, 8) float32 rows ``x y z r nx ny nz label`` (label as int32 bits) of the labelled proxies,
    in Morton (Z-curve) order of their positions.

    Proxies with label -1 (seen by no photo) have no depth map to raytrace and are left out. The
    order does not change any result (ties resolve by label); neighbouring threads then splat
    neighbouring discs of similar screen size, which the GPU runs in lockstep (-25 % visibility
    time on an H200, bench/bench_visibility.py).
    """
    keep = np.asarray(proxy["labels"]) >= 0
    if keep.sum() > 1:
        idx = np.flatnonzero(keep)
        keep = idx[morton_order(np.asarray(proxy["positions"], np.float64)[idx])]
    n = int(keep.sum()) if keep.dtype == bool else len(keep)
    data = np.empty((n, PROXY_FLOATS), np.float32)
    data[:, 0:3] = np.asarray(proxy["positions"], np.float32)[keep]
    data[:, 3] = np.asarray(proxy["radii"], np.float32)[keep]
    data[:, 4:7] = np.asarray(proxy["normals"], np.float32)[keep]
    data[:, 7] = np.asarray(proxy["labels"], np.int32)[keep].view(np.float32)
    return data


class ProxySplats:
    """The proxies on the GPU and the per-frame list of large discs, shared by the splat passes.

    Parameters
    ----------
    ctx : moderngl.Context
    proxy : dict
        ``positions`` (n, 3) float32 scene-origin-relative metres, ``normals`` (n, 3) float32,
        ``radii`` (n,) float32 metres, ``labels`` (n,) int32 (as :attr:`dmrt.io.bundle.Bundle.proxy`).
    max_thread_pixels : int
        Compute passes: discs whose pixel box exceeds this go to the workgroup-per-disc pass.
    """

    def __init__(self, ctx: moderngl.Context, proxy: dict, max_thread_pixels: int = 256):
        self.ctx = ctx
        self.data = pack_proxies(proxy)
        self.n = len(self.data)
        self.max_thread_pixels = int(max_thread_pixels)
        self.buffer = ctx.buffer(self.data.tobytes() if self.n else b"\0" * 32)
        self.large = ctx.buffer(reserve=16 + 4 * max(self.n, 1))
        self._built = False

    @property
    def nbytes(self) -> int:
        return self.buffer.size + self.large.size

    def begin_frame(self) -> None:
        """Forget the previous camera's large-disc list (the next compute pass rebuilds it)."""
        self.large.write(EMPTY_DISPATCH)
        self._built = False

    def run(self, name: str, defines: dict, uniforms: dict, bindings: dict) -> None:
        """One compute splat pass of program ``name`` over every proxy (both entry points).

        ``bindings`` maps storage-buffer binding points to buffers (``abi.B_PROXIES`` and
        ``abi.B_LARGE`` are the proxies' own).
        """
        d = {**defines, "MAX_THREAD_PIXELS": self.max_thread_pixels}
        small = load_program(self.ctx, name, {**d, "LARGE": 0})
        large = load_program(self.ctx, name, {**d, "LARGE": 1})
        self.buffer.bind_to_storage_buffer(abi.B_PROXIES)
        self.large.bind_to_storage_buffer(abi.B_LARGE)
        for binding, buf in bindings.items():
            buf.bind_to_storage_buffer(binding)
        set_uniforms(small, u_count=self.n, u_build_list=int(not self._built), **uniforms)
        small.run(groups(self.n, 64))
        self.ctx.memory_barrier(_BARRIER)
        self._built = True
        set_uniforms(large, **uniforms)
        large.run_indirect(self.large)
        self.ctx.memory_barrier(_BARRIER)

    def release(self) -> None:
        self.buffer.release()
        self.large.release()


class VisibilityStage:
    """Extracts k label layers into the caller's layer buffers.

    Parameters
    ----------
    ctx : moderngl.Context
    splats : ProxySplats
    method : ``"compute"``, ``"kbuffer"``, ``"tiles"`` or ``"raster"``
    int64 : bool
        Compute path: one pass per layer with 64-bit atomics (see module doc).
    tile_check : ``"frame"`` or ``"lagged"``, the tiles path's list check (:class:`TileVisibility`)
    status : dmrt.runtime.status.FrameStatus, optional
        The renderer's status records, which the tiles path writes its list length into and reads
        (the caller begins each frame's); None: the tiles path keeps its own.
    hit_masks, tile_batch, tile_top, tile_walk, tile_split : the tiles path's ``hit_masks``, ``batch``,
        ``top``, ``walk`` and ``split_min`` (:class:`TileVisibility`)
    """

    def __init__(self, ctx: moderngl.Context, splats: ProxySplats, method: str = "compute", int64: bool = False,
                 slots: int = 16, n_labels: int = 256, tile_check: str = "frame", status=None,
                 hit_masks: bool = True, tile_batch: int = DEFAULT_BATCH, tile_top: int = DEFAULT_TOP,
                 tile_walk: str = "auto", tile_split: int = 0, map_defines: dict | None = None):
        if method not in ("compute", "raster", "kbuffer", "tiles"):
            raise ValueError(f"RenderConfig.method must be 'compute', 'kbuffer', 'tiles' or 'raster', not {method!r}")
        self.ctx, self.splats, self.method = ctx, splats, method
        self.int64 = bool(int64) and method == "compute"
        self._size = None
        self._packed = None
        self.tiles = (TileVisibility(ctx, splats, batch=tile_batch, top=tile_top, check=tile_check, status=status,
                                     hit_masks=hit_masks, walk=tile_walk, split_min=tile_split,
                                     map_defines=map_defines)
                      if method == "tiles" else None)
        if method == "kbuffer":
            label_bits = max(1, int(n_labels - 1).bit_length())
            if label_bits > 16:
                raise ValueError(f"the k-buffer packs labels into 16 bits at most, not {n_labels} photos")
            self.slots = int(slots)
            self._kdefines = {"SLOTS": self.slots, "LABEL_BITS": label_bits}
            self._resolve = load_program(ctx, "dmrt_kbuffer_resolve", self._kdefines)
            self._kbuf = None
            self._overflow = ctx.buffer(reserve=4)
            self._staging = Staging(ctx)  # read_overflow's: the counter stays in GPU memory (Staging: why)
        if self.int64:
            self._unpack = load_program(ctx, "dmrt_layer_unpack")
        if method == "raster":
            # the depth maps' raster programs, with labels and the peeling fragment stage
            self._points = load_program(ctx, "splat_depth_raster", {"WITH_LABEL": 1})
            self._quads = load_program(ctx, "splat_depth_raster_large", {"WITH_LABEL": 1})
            self._copy = load_program(ctx, "dmrt_layer_copy")
            layout = [(splats.buffer, "3f 1f 3f 1i", "in_position", "in_radius", "in_normal", "in_label")]
            self._vao_points = ctx.vertex_array(self._points, layout)
            self._vao_quads = ctx.vertex_array(self._quads, layout)
            self.max_point_size = float(ctx.info["GL_POINT_SIZE_RANGE"][1])

    def run(self, uniforms: dict, size: tuple[int, int], layers: int, layer_depth, layer_label,
            timer=None) -> None:
        """Fill ``layers`` label layers for the camera in ``uniforms`` (u_R, u_t, u_K, u_size),
        timed as the ``visibility`` stage (its parts for ``tiles``) on ``timer`` if given."""
        if self.tiles is not None:  # writes every layer of every pixel: nothing to clear
            self.tiles.run(uniforms, size, layers, layer_depth, layer_label, timer)
            return
        with timed(timer, "visibility"):
            self._peel(uniforms, size, layers, layer_depth, layer_label)

    def _peel(self, uniforms: dict, size: tuple[int, int], layers: int, layer_depth, layer_label) -> None:
        w, h = size
        fill_u32(self.ctx, layer_depth, EMPTY_BITS, layers * w * h)
        fill_u32(self.ctx, layer_label, EMPTY_LABEL, layers * w * h)
        self.ctx.memory_barrier(_BARRIER)
        if self.method == "kbuffer":
            self._kbuffer(uniforms, size, layers, layer_depth, layer_label)
            return
        if self.int64:
            if self._packed is None or self._packed.size < 8 * w * h:
                if self._packed is not None:
                    self._packed.release()
                self._packed = self.ctx.buffer(reserve=8 * w * h)
            fill_u32(self.ctx, self._packed, EMPTY_BITS, 2 * w * h)
            self.ctx.memory_barrier(_BARRIER)
        for layer in range(layers):
            if self.int64:
                self.splats.run("dmrt_visibility", {"INT64": 1}, {**uniforms, "u_layer": layer},
                                {abi.B_LAYER_DEPTH: layer_depth, abi.B_LAYER_LABEL: layer_label, abi.B_VKEY: self._packed})
                for binding, buf in ((abi.B_LAYER_DEPTH, layer_depth), (abi.B_LAYER_LABEL, layer_label),
                                     (abi.B_VKEY, self._packed)):
                    buf.bind_to_storage_buffer(binding)
                set_uniforms(self._unpack, u_size=size, u_layer=layer)
                self._unpack.run(groups(w, 8), groups(h, 8))
                self.ctx.memory_barrier(_BARRIER)
            elif self.method == "compute":
                for resolve in (0, 1):
                    self.splats.run("dmrt_visibility", {"RESOLVE": resolve}, {**uniforms, "u_layer": layer},
                                    {abi.B_LAYER_DEPTH: layer_depth, abi.B_LAYER_LABEL: layer_label})
            else:
                self._raster_layer(uniforms, size, layer, layer_depth, layer_label)

    # -- k-buffer path ----------------------------------------------------------------------
    def _kbuffer(self, uniforms, size, layers, layer_depth, layer_label) -> None:
        w, h = size
        n = w * h * self.slots
        if self._kbuf is None or self._kbuf.size < 4 * n:
            if self._kbuf is not None:
                self._kbuf.release()
            self._kbuf = self.ctx.buffer(reserve=4 * n)
        fill_u32(self.ctx, self._kbuf, EMPTY_BITS, n)
        fill_u32(self.ctx, self._overflow, 0, 1)
        self.ctx.memory_barrier(_BARRIER)
        self.splats.run("dmrt_visibility_kbuffer", self._kdefines, uniforms, {abi.B_KBUFFER: self._kbuf})
        for binding, buf in ((abi.B_KBUFFER, self._kbuf), (abi.B_LAYER_DEPTH, layer_depth),
                             (abi.B_LAYER_LABEL, layer_label), (abi.B_OVERFLOW, self._overflow)):
            buf.bind_to_storage_buffer(binding)
        set_uniforms(self._resolve, u_size=size, u_layers=layers)
        self._resolve.run(groups(w, 8), groups(h, 8))
        self.ctx.memory_barrier(_BARRIER)

    def read_overflow(self) -> int:
        """Pixels of the last k-buffer frame whose list ran out before the k-th layer (tiles: pixels
        that may differ from peeling, :meth:`dmrt.runtime.tiles.TileVisibility.read_overflow`)."""
        if self.tiles is not None:
            return self.tiles.read_overflow()
        return int(np.frombuffer(self._staging.read(self._overflow), np.uint32)[0]) if self.method == "kbuffer" else 0

    @property
    def nbytes(self) -> int:
        """GPU bytes of the stage's own buffers (the k-buffer list; the tiles path's buffers)."""
        if self.tiles is not None:
            return self.tiles.nbytes
        kbuf = getattr(self, "_kbuf", None)
        return kbuf.size if kbuf is not None else 0

    # -- raster path ------------------------------------------------------------------------
    def _targets(self, size):
        if self._size != size:
            self._release_targets()
            self._tex = self.ctx.texture(size, 1, dtype="f4")
            self._fbo = self.ctx.framebuffer([self._tex])
            self._scope = self.ctx.scope(self._fbo, enable_only=moderngl.BLEND | moderngl.PROGRAM_POINT_SIZE)
            self._size = size

    def _raster_layer(self, uniforms, size, layer, layer_depth, layer_label) -> None:
        ctx = self.ctx
        self._targets(size)
        n = self.splats.n
        for program in (self._points, self._quads):
            set_uniforms(program, u_layer=layer, u_max_point_size=self.max_point_size, **uniforms)
        set_uniforms(self._copy, u_layer=layer, u_size=size, u_src=0)
        layer_depth.bind_to_storage_buffer(abi.B_LAYER_DEPTH)
        layer_label.bind_to_storage_buffer(abi.B_LAYER_LABEL)
        for resolve in (0, 1):
            self._fbo.clear(EMPTY_Z, 0.0, 0.0, 0.0)
            if n:
                for program in (self._points, self._quads):
                    set_uniforms(program, u_resolve=resolve)
                with self._scope:
                    # MIN blend on float32: the stored value is the exact smallest z (or label)
                    ctx.blend_equation = moderngl.MIN
                    try:
                        self._vao_points.render(moderngl.POINTS, vertices=n)
                        self._vao_quads.render(moderngl.POINTS, vertices=n)
                    finally:
                        ctx.blend_equation = moderngl.FUNC_ADD
            self._tex.use(0)
            set_uniforms(self._copy, u_resolve=resolve)
            self._copy.run(groups(size[0], 8), groups(size[1], 8))
            ctx.memory_barrier(_BARRIER)

    def _release_targets(self) -> None:
        for name in ("_scope", "_fbo", "_tex"):
            obj = self.__dict__.pop(name, None)
            if obj is not None:
                obj.release()
        self._size = None

    def release(self) -> None:
        self._release_targets()
        if self.tiles is not None:
            self.tiles.release()
        for name in ("_vao_points", "_vao_quads", "_packed", "_kbuf", "_overflow", "_staging"):
            obj = self.__dict__.pop(name, None)
            if obj is not None:
                obj.release()
