"""Tile-binned single-pass visibility stage (``RenderConfig.method = "tiles"``).

The k label layers of :mod:`dmrt.runtime.visibility` (layer 1 = nearest proxy-disc hit at the pixel
centre, layer i+1 = nearest hit behind layer i with another label; equal depths to the smallest
label) from one walk over the discs, the way tile rasterizers work: each pixel's layers are built in
registers, and global memory sees each disc a few times per frame rather than once per covered pixel
and layer (the compute and k-buffer paths' atomics). Per frame:

1. ``dmrt_tiles_bin`` (count): one thread per disc culls it and counts it into every 16x16-pixel
   screen tile its conservative pixel box overlaps (``atomicAdd`` per tile); a disc over many tiles
   goes to a list that a workgroup per disc bins (dispatch-indirect).
2. ``dmrt_tiles_scan``: exclusive prefix sum of the tile counts = each tile's slice of one list.
3. ``dmrt_tiles_bin`` (scatter): the same walk writes (near-depth key, disc index) into the slices.
4. ``dmrt_tiles_raster``: one workgroup per tile, one invocation per pixel: sorts the slice by near
   depth in shared memory (longer slices: sorted chunks merged on the fly), walks the discs in that
   order in batches loaded into shared memory, runs the ray-disc test of the other paths
   (``splat_depth_at``: the same depth bits), feeds the hits to the peeling rule in depth order
   through a short per-pixel list of pending hits, writes each layer once, and stops when every
   pixel of the tile has its k layers.

Where the layers can differ from compute peeling (``shaders/dmrt_tiles_raster.glsl`` has the details):

* a pixel whose pending list overflows (more hits than it holds between the near depth of the disc
  being walked and the k-th layer: overlapping splats of the nearest surfaces) drops its farthest
  hit, which can change the layers behind that hit. The list's length costs every pixel (2
  registers an entry: the raster pass took 5.5 / 6.9 / 8.8 ms at 4K with 8 / 16 / 32 entries on
  the paper preset, H200), and only ~0.1 % of the pixels need more than 8 there, so the pass runs
  with 8 (:data:`PENDING_LEVELS`) and lists each tile in which a pixel overflowed; a second pass
  with 32 entries walks the listed tiles again, in the same frame, without the CPU
  (``redo_tiles``). A frame whose listed tiles exceed :data:`REDO_SHARE` of its tiles moves the
  first pass to the next length for the following frames. Pixels that overflow even 32 entries
  keep the approximation (``overflow_pixels``). Measured on the ``tiny`` scene: 8 suffice for its
  splat radii (every layer equal to peeling), radii x 2.5 (the paper's worst case) take 32 (>=
  99.5 % of the pixels of every layer). With a fixed ``pending`` there is no second pass;
* a tile with more than 256 x ``sort_size`` (2048) discs is walked chunk after chunk (``long_tiles``;
  the merge needs windows of >= 4 keys per chunk in one sort).

The list's length is only known on the GPU. By default (``check="frame"``) the stage ends by reading
back 16 bytes of statistics, which waits for the stage (a CPU wait after its last pass, so its GPU
time is not stretched; the renderer waits once per frame anyway, for the label histogram): a frame
whose list outgrew the buffer is built again in a larger one (x 2, kept >= 25 % above the last
length). ``check="lagged"`` never waits (but on a
frame size's first frame): it adapts from the statistics of the frame two frames back, so a view
whose list grows by more than the headroom within two frames loses the discs past the buffer's end
in that frame (``dropped``).
"""

from __future__ import annotations

import moderngl
import numpy as np

from dmrt.gl import abi
from dmrt.gl.kernels import EMPTY_DISPATCH, fill_u32, groups, max_groups
from dmrt.gl.shaders import load_program, set_uniforms
from dmrt.gl.timer import timed

_BARRIER = moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT
ENTRY_BYTES = 8  # (near key, disc index) uint pair
STATUS_FIELDS = ("entries", "overflow_pixels", "long_tiles", "redo_tiles")  # Status in dmrt_tiles_raster.glsl
PENDING_LEVELS = (8, 16, 32)  # pending-list lengths of the first pass; the second pass takes the last
# tiles walked again (share of the frame's) past which the first pass takes the next length: a tile
# walked again costs a 32-entry pass (~1.6x an 8-entry one), a 16-entry first pass +25 % on every tile
REDO_SHARE = 0.15
_RING = 3  # status buffers in flight: the one read back was written two frames before


class TileVisibility:
    """The visibility stage's ``"tiles"`` path, with the interface of
    :class:`dmrt.runtime.visibility.VisibilityStage` (which delegates to it).

    Parameters
    ----------
    ctx : moderngl.Context
    splats : dmrt.runtime.visibility.ProxySplats
        The proxies on the GPU (``buffer``: n x 8 float32, ``n``).
    tile : int
        Tile side, pixels; a workgroup has tile^2 invocations (16: 256).
    pending : int, optional
        Fixed pending-list length (hits per pixel kept until final; 2 registers each). Default:
        adaptive, starting at ``PENDING_LEVELS[0]`` (see module doc).
    sort_size : int
        Keys sorted at once in shared memory (power of two, 8 bytes each): a tile slice up to this
        long takes one sort, a longer one is merged from chunks of it.
    max_thread_tiles : int
        Discs over more tiles are binned by a workgroup each instead of one thread.
    check : ``"frame"`` or ``"lagged"``
        When the statistics that size the list and the pending list are read back (module doc).

    Attributes
    ----------
    capacity : int
        Entries the list buffer holds.
    pending : int
        The pending-list length in use.
    dropped_frames : int
        Frames whose list outgrew the buffer (``check="frame"``: built again).
    """

    def __init__(self, ctx: moderngl.Context, splats, tile: int = 16, pending: int | None = None,
                 sort_size: int = 2048, max_thread_tiles: int = 16, check: str = "frame"):
        if sort_size < 2 or sort_size & (sort_size - 1):
            raise ValueError(f"sort_size must be a power of two >= 2, not {sort_size}")
        if not 1 <= tile <= 32:
            raise ValueError(f"tile must be 1..32 (tile^2 invocations per workgroup), not {tile}")
        if pending is not None and pending < 1:
            raise ValueError(f"pending must be >= 1, not {pending}")
        if check not in ("frame", "lagged"):
            raise ValueError(f"check must be 'frame' or 'lagged', not {check!r}")
        self.ctx, self.splats = ctx, splats
        self.tile, self.check = int(tile), check
        self.adaptive = pending is None
        self.pending = PENDING_LEVELS[0] if pending is None else int(pending)
        self._defines = {"TILE": self.tile}
        self._raster_defines = {**self._defines, "SORT_SIZE": int(sort_size)}
        self._bin = {(scatter, large): load_program(ctx, "dmrt_tiles_bin", {**self._defines, "SCATTER": scatter,
                                                                            "LARGE": large,
                                                                            "MAX_THREAD_TILES": max_thread_tiles})
                     for scatter in (0, 1) for large in (0, 1)}
        self._scan = load_program(ctx, "dmrt_tiles_scan")
        for redo in (False, True):  # compile errors now, not in the first frame
            self._raster_program(redo)
        n = max(splats.n, 1)
        # large-disc list: dispatch-indirect header (groups x, y, z), its length, proxy indices
        self.large = ctx.buffer(reserve=16 + 4 * n)
        self._status = [ctx.buffer(reserve=16) for _ in range(_RING)]
        # what the frame that wrote each status buffer ran with: list capacity, pending length, pixels
        self._status_run = [(0, 0, 0)] * _RING
        self._frame = 0
        self._grid: tuple[int, int] | None = None
        self.counts = self.offsets = self._redo_list = None
        self._max_groups = max_groups(ctx)
        # a first guess (two tiles per disc); sized from the real length on the first frame
        self.capacity = max(2 * n, 4096)
        self.entries = ctx.buffer(reserve=ENTRY_BYTES * self.capacity)
        self.dropped_frames = 0
        self._grow_to = 0  # list length to make room for at the next frame (this one's list is kept)

    # -- sizes ------------------------------------------------------------------------------
    def _raster_program(self, redo: bool = False):
        pending = PENDING_LEVELS[-1] if redo else self.pending
        return load_program(self.ctx, "dmrt_tiles_raster", {**self._raster_defines, "PENDING": pending,
                                                              "REDO": int(redo)})

    @property
    def _second_pass(self) -> bool:
        """Whether tiles with an overflowing pixel are walked again with the longest list."""
        return self.adaptive and self.pending < PENDING_LEVELS[-1]

    def _allocate_tiles(self, grid: tuple[int, int]) -> None:
        for buf in (self.counts, self.offsets, self._redo_list):
            if buf is not None:
                buf.release()
        n = grid[0] * grid[1]
        self.counts = self.ctx.buffer(reserve=4 * n)
        self.offsets = self.ctx.buffer(reserve=4 * (n + 1))
        self._redo_list = self.ctx.buffer(reserve=16 + 4 * n)  # header, then the tiles walked again
        self._grid = grid

    def _fit(self, total: int) -> None:
        """Grow the list to twice ``total`` entries when less than 25 % headroom is left."""
        if total * 1.25 <= self.capacity:
            return
        self.capacity = 2 * total
        self.entries.release()
        self.entries = self.ctx.buffer(reserve=ENTRY_BYTES * self.capacity)

    def _adapt(self, redone: int, pending: int, tiles: int) -> None:
        """Step the first pass to the next list length after a frame (run with ``pending``) that
        walked more than REDO_SHARE of its ``tiles`` again."""
        if not self.adaptive or redone <= REDO_SHARE * tiles or pending != self.pending:
            return
        longer = [p for p in PENDING_LEVELS if p > self.pending]
        if longer:
            self.pending = longer[0]

    def _read_status(self, slot: int) -> np.ndarray:
        return np.frombuffer(self._status[slot].read(), np.uint32)

    @staticmethod
    def _bind(**buffers) -> None:
        points = {"proxies": abi.B_PROXIES, "layer_depth": abi.B_LAYER_DEPTH, "layer_label": abi.B_LAYER_LABEL,
                  "large": abi.B_LARGE, "entries": abi.B_TILE_ENTRIES,
                  "counts": abi.B_TILE_COUNTS, "offsets": abi.B_TILE_OFFSETS,
                  "status": abi.B_TILE_STATUS, "redo": abi.B_TILE_REDO}
        for name, buf in buffers.items():
            buf.bind_to_storage_buffer(points[name])

    # -- the frame --------------------------------------------------------------------------
    def run(self, uniforms: dict, size: tuple[int, int], layers: int, layer_depth, layer_label,
            timer=None) -> None:
        """Fill ``layers`` label layers for the camera in ``uniforms``; with ``timer``, timed as the
        parts ``visibility:tile_lists`` (bin, scan, scatter), ``visibility:tile_raster`` and
        ``visibility:redo`` (what a frame that outgrew the list did again).

        Parameters
        ----------
        uniforms : dict
            ``u_R`` (9,) float32 world->camera rotation, column-major; ``u_t`` (3,) metres,
            scene-origin-relative; ``u_K`` (fx, fy, cx, cy) pixels; ``u_size`` (w, h).
        size : (w, h) int, pixels
        layers : int
            k >= 1.
        layer_depth, layer_label : moderngl.Buffer
            At least k x h x w uint32 each, written whole (no clearing needed): depth = float bits
            of camera z (metres), ``abi.EMPTY_BITS`` = empty; label int32, ``abi.EMPTY_LABEL`` =
            empty; layer after layer, rows from the top.
        """
        w, h = size
        grid = (-(-w // self.tile), -(-h // self.tile))
        self._fit(self._grow_to)
        first = grid != self._grid
        if first:
            self._allocate_tiles(grid)
        if self.check == "lagged" and self._frame >= _RING - 1:
            # the frame two back has finished by now (the renderer read its label histogram since)
            back = (self._frame - (_RING - 1)) % _RING
            capacity, pending, tiles = self._status_run[back]
            status = self._read_status(back)
            self.dropped_frames += int(status[0]) > capacity
            self._fit(int(status[0]))
            self._adapt(int(status[3]), pending, tiles)
        slot = self._frame % _RING
        status = self._status[slot]
        tile_uniforms = {**uniforms, "u_tiles": grid, "u_count": self.splats.n, "u_tile_count": grid[0] * grid[1]}
        raster = (tile_uniforms, layers, layer_depth, layer_label, status)

        with timed(timer, "visibility:tile_lists"):
            self._build_list(tile_uniforms, status, size_after_scan=first and self.check == "lagged")
        pending = self.pending  # the first pass's list length (_redo may step it for the next frames)
        with timed(timer, "visibility:tile_raster"):
            self._raster_pass(*raster)
        if self.check == "frame" or first:
            # wait for the stage (its GPU time is not stretched: nothing is issued after it) and redo
            # the frame if it outgrew the list
            self._redo(tile_uniforms, raster, status, slot, timer)
        self._status_run[slot] = (self.capacity, pending, grid[0] * grid[1])
        self._frame += 1

    def _redo(self, tile_uniforms, raster, status, slot, timer) -> None:
        """Wait for the frame's status and build the list again, larger, if it outgrew its buffer;
        adapt the first pass's list length. The wait is outside any timed section: a section open
        while the CPU waits would count the idle GPU."""
        while True:
            words = self._read_status(slot)
            total = int(words[0])
            if total <= self.capacity:
                break
            self.dropped_frames += 1
            self._fit(total)
            with timed(timer, "visibility:redo"):
                self._build_list(tile_uniforms, status, size_after_scan=False)
                self._raster_pass(*raster)
        self._adapt(int(words[3]), self.pending, self._grid[0] * self._grid[1])
        # headroom for the next frames, made then: the labeling pass still walks this list
        self._grow_to = total

    def _build_list(self, tile_uniforms: dict, status, size_after_scan: bool) -> None:
        """Bin (count), scan, bin (scatter): each tile's slice of the list, unsorted."""
        ctx = self.ctx
        n_tiles = tile_uniforms["u_tile_count"]
        fill_u32(ctx, self.counts, 0, n_tiles)
        self.large.write(EMPTY_DISPATCH)
        ctx.memory_barrier(_BARRIER)
        self._bin_pass(0, tile_uniforms)
        self._bind(status=status, counts=self.counts, offsets=self.offsets)
        set_uniforms(self._scan, u_tile_count=n_tiles)
        self._scan.run(1)
        ctx.memory_barrier(_BARRIER)
        if size_after_scan:
            self._fit(int(self._read_status(self._status.index(status))[0]))
        self._bin_pass(1, tile_uniforms)

    def _bin_pass(self, scatter: int, tile_uniforms: dict) -> None:
        for large in (0, 1):
            program = self._bin[scatter, large]
            self._bind(proxies=self.splats.buffer, large=self.large, entries=self.entries, counts=self.counts,
                       offsets=self.offsets)
            set_uniforms(program, u_capacity=self.capacity, **tile_uniforms)
            if large:
                program.run_indirect(self.large)
            elif self.splats.n:
                program.run(groups(self.splats.n, 64))
            self.ctx.memory_barrier(_BARRIER)

    def _raster_pass(self, tile_uniforms: dict, layers: int, layer_depth, layer_label, status) -> None:
        """The raster pass over every tile, then (:attr:`_second_pass`) the one with the longest list
        over the tiles the first listed (dispatch-indirect: the list is only known on the GPU)."""
        second = self._second_pass
        self._redo_list.write(EMPTY_DISPATCH)
        for redo in ((False, True) if second else (False,)):
            program = self._raster_program(redo)
            self._bind(proxies=self.splats.buffer, layer_depth=layer_depth, layer_label=layer_label, status=status,
                       entries=self.entries, offsets=self.offsets, redo=self._redo_list)
            set_uniforms(program, u_capacity=self.capacity, u_layers=int(layers), u_redo=int(second),
                         u_max_groups=self._max_groups, **tile_uniforms)
            if redo:
                program.run_indirect(self._redo_list)
            else:
                program.run(*self._grid)
            self.ctx.memory_barrier(_BARRIER)

    def label_pass(self, uniforms: dict, hits, key, vlabel, packed: bool) -> None:
        """The labeling pass on this frame's tile lists (``shaders/dmrt_tiles_labeling.glsl``): the
        labels of ``dmrt_labeling.glsl`` without splatting the proxies again.

        Parameters
        ----------
        uniforms : dict, the frame's camera (as :meth:`run`'s, at the same size).
        hits : moderngl.Buffer, the frame's ``Hit`` records (read: each pixel's raytraced depth).
        key, vlabel : moderngl.Buffer, written for every pixel in the layout
            ``dmrt_label_finalize.glsl`` reads: ``packed`` - ``key`` (h x w) uvec2 (label, distance
            bits); else ``key`` (h x w) uint distance bits and ``vlabel`` (h x w) int label.
        """
        program = load_program(self.ctx, "dmrt_tiles_labeling", {**self._defines, "PACKED_LABELS": int(packed)})
        self._bind(proxies=self.splats.buffer, entries=self.entries, offsets=self.offsets)
        hits.bind_to_storage_buffer(abi.B_HITS)
        key.bind_to_storage_buffer(abi.B_KEY)
        if not packed:
            vlabel.bind_to_storage_buffer(abi.B_VLABEL)
        set_uniforms(program, u_capacity=self.capacity, u_tiles=self._grid, **uniforms)
        program.run(*self._grid)
        self.ctx.memory_barrier(_BARRIER)

    # -- diagnostics ------------------------------------------------------------------------
    def stats(self) -> dict:
        """The last frame's list and approximations (waits for the GPU).

        Returns
        -------
        dict
            ``entries`` (list length: disc-tile overlaps), ``capacity`` (entries the buffer held),
            ``dropped`` (bool: the list outgrew the buffer, entries past it were lost),
            ``overflow_pixels`` (pixels whose pending list overflowed in the pass that wrote them
            last), ``pending`` (the first pass's list length), ``redo_tiles`` (tiles walked again
            with the longest list), ``long_tiles`` (tiles walked chunk by chunk).
        """
        if self._frame == 0:
            return {"entries": 0, "capacity": self.capacity, "dropped": False, "overflow_pixels": 0,
                    "pending": self.pending, "long_tiles": 0, "redo_tiles": 0}
        slot = (self._frame - 1) % _RING
        out = {name: int(v) for name, v in zip(STATUS_FIELDS, self._read_status(slot))}
        out["capacity"], out["pending"], _ = self._status_run[slot]
        out["dropped"] = out["entries"] > out["capacity"]
        return out

    def read_overflow(self) -> int:
        """Pixels of the last frame that may differ from peeling: those whose pending list
        overflowed (every pixel if the frame's list was cut short)."""
        s = self.stats()
        if s["dropped"]:
            return self._grid[0] * self._grid[1] * self.tile * self.tile
        return s["overflow_pixels"]

    @property
    def nbytes(self) -> int:
        """GPU bytes of the path's own buffers (list, tile counts and offsets, large list, status)."""
        bufs = [self.entries, self.large, self.counts, self.offsets, self._redo_list, *self._status]
        return sum(b.size for b in bufs if b is not None)

    def release(self) -> None:
        for name in ("entries", "large", "counts", "offsets", "_redo_list"):
            buf = getattr(self, name)
            if buf is not None:
                buf.release()
                setattr(self, name, None)
        for buf in self._status:
            buf.release()
        self._status = []
