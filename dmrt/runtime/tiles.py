"""Tile-binned visibility stage (``RenderConfig.method = "tiles"``).

The k label layers of :mod:`dmrt.runtime.visibility` (layer 1 = nearest proxy-disc hit at the pixel
centre, layer i+1 = nearest hit behind layer i with another label; equal depths to the smallest
label) from the discs binned into screen tiles, the way tile rasterizers work: each pixel's layers are
built in registers, and global memory sees each disc a few times per frame rather than once per
covered pixel and layer (the compute and k-buffer paths' atomics). Per frame:

1. ``dmrt_tiles_bin`` (count): one thread per disc culls it and counts it into every 16x16-pixel
   screen tile its conservative pixel box overlaps (``atomicAdd`` per tile); a disc over many tiles
   goes to a list that a workgroup per disc bins (dispatch-indirect).
2. ``dmrt_tiles_scan``: exclusive prefix sum of the tile counts = each tile's slice of one list.
3. ``dmrt_tiles_bin`` (scatter): the same walk writes the disc indices into the slices.
4. ``dmrt_tiles_raster``: one workgroup per tile, one invocation per pixel: each layer is the
   smallest (depth bits, label) among the pixel's hits behind the layer before with another label.
   The workgroup walks its tile's discs (held in shared memory) once, each invocation keeping its
   nearest hits (12 by default) sorted by depth in registers, and the peeling rule applied to them in order
   gives the pixel's first layers exactly (all k for most pixels, unless two of them have equal
   depths: their order is the label's); a pixel still lacking layers walks again
   per layer, keeping the minimum that passes the filter and testing only the discs that hit it
   (a bit mask). The ray-disc test is the other paths' (``splat_depth_at``), so every
   layer equals compute peeling's to the bit; no order among the discs is needed and nothing is
   approximated.
5. ``dmrt_tiles_split``, with ``split_min`` > 0 (the renderer's default): between the count and the scan, a
   plan takes each tile whose list is longer than ``split_min`` out of the lists (the raster and
   labeling passes see it empty) and the scatter writes its discs into a buffer of their own; per
   layer, after the raster, a workgroup per slice of ``batch`` of its discs finds each pixel's
   smallest over its slice, then a workgroup per split tile takes the smallest of its slices', so
   the layers are again peeling's (the labeling pass likewise). A tile is one workgroup: where
   distant discs pile up in a few tiles (a street receding to its vanishing point: thousands of
   discs a tile), the frame otherwise waits for those tiles alone. The scan counts the long lists
   into the frame's status record, and a frame runs the split (plan, scatter into the split buffer,
   passes) only while one of the last ``split_hold`` frames read back had one: a view without long
   lists does not pay for it.

The list's length is only known on the GPU: the scan writes it into the frame's status record
(:mod:`dmrt.runtime.status`), the frame's one read-back. By default (``check="frame"``) every
frame's length is checked: in a renderer, late in the frame (the renderer reads the record when it
updates the photo cache, by when the GPU has long finished this stage and has the passes issued
since to work on: no idle gap), and a frame whose list outgrew the buffer is rendered again with a
larger one (:meth:`TileVisibility.end_frame`); used alone, and on a frame size's first frame
(whose list the last size's does not bound), the stage reads the record at its end and builds the
list again (x 2, kept >= 25 % above the last length). ``check="lagged"`` never waits (but on a frame
size's first frame): it reads the record of two frames back and sizes the list from its length, so
a view whose list grows by more than the headroom within two frames loses the discs past the
buffer's end in that frame (``dropped``); the photo cache then follows the choice that record
holds, three frames old.
"""

from __future__ import annotations

import moderngl
import numpy as np

from dmrt.gl import abi
from dmrt.gl.kernels import EMPTY_DISPATCH, Staging, fill_u32, groups
from dmrt.gl.shaders import load_program, set_uniforms
from dmrt.gl.timer import timed
from dmrt.runtime.status import RING, FrameStatus

_BARRIER = moderngl.SHADER_STORAGE_BARRIER_BIT | moderngl.COMMAND_BARRIER_BIT
ENTRY_BYTES = 8  # a disc index and its box in the tile per disc-tile overlap (dmrt_tiles_bin.glsl)
LAG = RING - 1  # check="lagged" reads the record of the frame this many frames back
MASK_DISCS = 256  # the raster's hit masks cover a tile's first 256 discs (dmrt_tiles_common.glsl)
# The raster's defaults, chosen by timing (TileVisibility's batch says how; RenderConfig.tile_batch
# and tile_hits set them for another GPU)
DEFAULT_BATCH = 288
DEFAULT_TOP = 12
# walk="auto" walks a frame's tiles sparsely (each pixel only the discs whose box holds it) when the
# last known list held more discs than this a tile on average (dmrt_tiles_raster.glsl, SPARSE_WALK:
# H200, ~180 discs a tile sparse 0.35 ms against 0.50, ~63 a tile 1.78 against 1.72)
SPARSE_MIN = 100


# RenderConfig.tile_split's default, which bench/split_run.sh compares with 0 (four batches: between
# a tile's usual ~63-180 discs and the thousands where a frame waits for one tile; reports/many-photos).
SPLIT_MIN = 4 * DEFAULT_BATCH
# Slices the split buffer holds at most (2 KB of partial results each at 16 x 16 pixels: 32 MB); a
# tile whose slices or discs do not fit stays in the lists, walked by the raster alone.
SPLIT_SLOTS_MAX = 16384
# the split buffer's two dispatch-indirect headers: slices (x, y, z, slices reserved), split tiles
# (x, y, z, discs reserved)
SPLIT_HEADER = EMPTY_DISPATCH + EMPTY_DISPATCH
# Frames the split keeps running after the last one read back with a long list (split_hold). On an
# H200, session 28's walk along the `many` block (reports/many-photos, split-walk120-961f858) had
# its frames without a long list take 1.79 ms at 1280x720 and 5.29 at 3840x2160 with the split
# against 1.77 and 4.93 without (its plan, the scatter's reads of it, its passes); a frame that
# turns to a long list walks it with the raster alone until its record is read (a frame or two, as
# slow as the split's absence: 5.1 against 2.4 ms there). 30 frames: half a second at 60 fps.
SPLIT_HOLD = 30


SCAN_THREADS, SCAN_ROUNDS = 1024, 8  # dmrt_tiles_scan.glsl: its workgroup, the most quads a thread holds


def _padded(tiles: int) -> int:
    """``tiles`` rounded up to a multiple of four (dmrt_tiles_scan.glsl reads and writes uvec4s)."""
    return -(-tiles // 4) * 4


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
    batch : int
        Discs the raster pass holds in shared memory (36 bytes each): a tile's list up to this long
        is loaded once for all layers, a longer one in batches of it for each layer. The default
        with ``top``: what bounds the raster is the workgroups resident on an SM, set by its
        registers (``top``) and its shared memory (``batch``), so its time moves in steps. H200, 5
        layers (reports/frame-h200, session 15): with 12 hits, 256-320 discs run it in 1.73 ms at
        3840x2160 and 0.51-0.54 ms at 1280x720, 352-384 in 1.98 / 0.52 ms; with 16 hits, 384-448
        discs in 1.91 / 0.50-0.52 ms, 320 in 2.54 / 0.60 ms; 8 hits and 288 discs 1.84 / 0.55 ms
        (a 720p tile holds ~180 discs, a 4K one ~63).
    top : int
        Nearest hits each pixel keeps sorted in registers during the raster's first walk: 4, 8,
        12 or 16 (a pixel whose layers are not all among them walks the list again; see batch).
    max_thread_tiles : int
        Discs over more tiles are binned by a workgroup each instead of one thread.
    check : ``"frame"`` or ``"lagged"``
        When the list length that sizes the list buffer is read back (module doc).
    status : dmrt.runtime.status.FrameStatus, optional
        The renderer's status records (the renderer begins each frame's); None: a ring of its own,
        whose frames :meth:`run` begins.
    hit_masks : bool
        The raster writes each pixel's hit bits for :meth:`label_pass` (32 bytes a pixel, 16 x 16
        tiles only); False for a renderer without the labeling pass.
    walk : ``"auto"``, ``"linear"`` or ``"sparse"``
        How the raster finds a pixel's discs (``SPARSE_WALK`` in ``dmrt_tiles_raster.glsl``): every
        disc in turn with its box tested (linear: fastest for short lists), or only the discs whose
        box holds the pixel (sparse: for long ones); auto: sparse for a frame when the last list
        length known held more than ``SPARSE_MIN`` discs a tile on average. The layers are the same.
    warp_blocks : bool
        Each 32 invocations of the raster and labeling passes cover an 8 x 4 pixel block of the tile
        instead of two rows (``tile_local_pixel`` in ``dmrt_tiles_common.glsl``; tile a multiple
        of 8; H100: raster 8 % faster at 1280x720, 4 % at 3840x2160); the layers are the same
        either way.
    split_min : int
        A tile whose list holds more discs than this is walked by a workgroup per ``batch`` discs
        (module doc, step 5), where the split buffer (as many discs as the list buffer) has room;
        0: never (here the default; the renderer's is ``SPLIT_MIN``, ``RenderConfig.tile_split``).
        The layers are the same either way.
    split_hold : int
        With ``split_min``: a frame splits while one of the last ``split_hold`` frames (>= 1: a
        renderer reads a frame's record after its visibility stage) whose status record was read
        back had a long list (the first ``split_hold`` frames split); else its long lists, if any,
        are walked by the raster alone (and counted, so that the next frames split). Their discs
        are then in the list buffer, sized by frames whose long lists were not: with
        ``check="lagged"`` such a frame may outgrow it and lose discs, as any view whose list grows
        past the headroom within two frames.

    Attributes
    ----------
    tile, batch, top, check, walk, split_min, split_hold : the parameters above
    capacity : int
        Entries the list buffer holds.
    dropped_frames : int
        Frames whose list outgrew the buffer (``check="frame"``: built again).
    split_frames : int
        Frames that split (``split_min``, ``split_hold``).
    """

    def __init__(self, ctx: moderngl.Context, splats, tile: int = 16, batch: int = DEFAULT_BATCH, top: int = DEFAULT_TOP,
                 max_thread_tiles: int = 16, check: str = "frame", status: FrameStatus | None = None,
                 hit_masks: bool = True, warp_blocks: bool = True, walk: str = "auto", split_min: int = 0,
                 split_hold: int = SPLIT_HOLD, map_defines: dict | None = None):
        if not 1 <= tile <= 32:
            raise ValueError(f"tile must be 1..32 (tile^2 invocations per workgroup), not {tile}")
        if batch < 1:
            raise ValueError(f"batch must be >= 1, not {batch}")
        if top not in (4, 8, 12, 16):
            raise ValueError(f"top must be 4, 8, 12 or 16, not {top}")
        if check not in ("frame", "lagged"):
            raise ValueError(f"check must be 'frame' or 'lagged', not {check!r}")
        if walk not in ("auto", "linear", "sparse"):
            raise ValueError(f"walk must be 'auto', 'linear' or 'sparse', not {walk!r}")
        if split_min < 0:
            raise ValueError(f"split_min must be >= 0 (0: never), not {split_min}")
        if split_hold < 1:
            raise ValueError(f"split_hold must be >= 1, not {split_hold}")
        self.ctx, self.splats = ctx, splats
        self.tile, self.check, self.batch, self.top = int(tile), check, int(batch), int(top)
        self.hit_masks = bool(hit_masks) and self.tile * self.tile == MASK_DISCS
        self._defines = {"TILE": self.tile, "BATCH": int(batch), "HIT_MASKS": int(self.hit_masks),
                         "WARP_BLOCKS": int(bool(warp_blocks)), **(map_defines or {})}
        # (scatter, large, split): the scatter into the split buffer only in frames that split
        self._bin = {(scatter, large, split): load_program(ctx, "dmrt_tiles_bin", {
                         **self._defines, "SCATTER": scatter, "LARGE": large, "SPLIT": split,
                         "MAX_THREAD_TILES": max_thread_tiles})
                     for scatter in (0, 1) for large in (0, 1) for split in ((0, 1) if scatter and split_min > 0 else (0,))}
        self.walk, self.split_min, self.split_hold = walk, int(split_min), int(split_hold)
        self._splits = self.split_min > 0
        self._split_now = False  # this frame splits (split_hold)
        self.split_frames = 0
        self._split_counted = -1  # the last frame counted in split_frames (a frame may run again)
        self._rasters = {sparse: load_program(ctx, "dmrt_tiles_raster", {**self._defines, "TOP": int(top),
                                                                          "SPARSE_WALK": int(sparse)})
                         for sparse in (0, 1) if walk == "auto" or sparse == (walk == "sparse")}
        # the plan, the slices, the merge (dmrt_tiles_split.glsl's STEP)
        self._split_steps = [load_program(ctx, "dmrt_tiles_split", {**self._defines, "STEP": step})
                             for step in (0, 1, 2)] if self._splits else None
        self._last_total = 0  # the last list length read back (walk="auto" decides by it)
        self.split: moderngl.Buffer | None = None  # the long lists' discs, slices, partials (split_min > 0)
        # the split buffer's headers, copied out once a frame: the split passes dispatch from the
        # copy. Dispatched from the 4-28 MB split buffer, which stats() then read back directly,
        # every later frame's split passes cost 4 ms at 1280x720 and 22 ms at 3840x2160 on an
        # H200, whether anything was split or not (reports/many-photos)
        self.split_args: moderngl.Buffer | None = ctx.buffer(reserve=len(SPLIT_HEADER)) if split_min > 0 else None
        self._split_uniforms: dict = {}  # its size, for the programs that read it
        self._staging: Staging | None = None  # stats()'s read-backs
        n = max(splats.n, 1)
        # large-disc list: dispatch-indirect header (groups x, y, z), its length, proxy indices
        self.large = ctx.buffer(reserve=16 + 4 * n)
        self._own_status = status is None
        self.status = FrameStatus(ctx) if status is None else status
        self._first_frame = self.status.frame + 1
        self._capacity_of: dict[int, int] = {}  # the list capacity of each recent frame
        self._grid: tuple[int, int] | None = None
        # the raster's hit bits of each pixel's first 256 discs (32 bytes a pixel), which the
        # labeling pass reads instead of testing those discs again (dmrt_tiles_labeling.glsl)
        self.masks: moderngl.Buffer | None = None
        self.counts = self.offsets = None
        # a first guess (two tiles per disc); sized from the real length on the first frame
        self.capacity = max(2 * n, 4096)
        self.entries = ctx.buffer(reserve=ENTRY_BYTES * self.capacity)
        self.dropped_frames = 0
        self._grow_to = 0  # list length to make room for at the next frame (this one's list is kept)

    # -- sizes ------------------------------------------------------------------------------
    def _allocate_tiles(self, grid: tuple[int, int]) -> None:
        for buf in (self.counts, self.offsets):
            if buf is not None:
                buf.release()
        n = grid[0] * grid[1]
        self.counts = self.ctx.buffer(reserve=4 * _padded(n))  # the scan reads four counts at a time
        self.offsets = self.ctx.buffer(reserve=4 * (_padded(n) + 4))  # the scan writes four at a time
        # the scan's shared memory holds only the rounds the grid needs (one at 1280x720)
        rounds = min(SCAN_ROUNDS, -(-_padded(n) // (4 * SCAN_THREADS)))
        self._scan = load_program(self.ctx, "dmrt_tiles_scan", {"ROUNDS": rounds, "SCAN_THREADS": SCAN_THREADS,
                                                                "SPLIT": int(self._splits)})
        self._grid = grid

    def _fit(self, total: int) -> None:
        """Grow the list to twice ``total`` entries when less than 25 % headroom is left."""
        if total * 1.25 <= self.capacity:
            return
        self.capacity = 2 * total
        self.entries.release()
        self.entries = self.ctx.buffer(reserve=ENTRY_BYTES * self.capacity)

    @staticmethod
    def _bind(**buffers) -> None:
        points = {"proxies": abi.B_PROXIES, "layer_depth": abi.B_LAYER_DEPTH, "layer_label": abi.B_LAYER_LABEL,
                  "large": abi.B_LARGE, "entries": abi.B_TILE_ENTRIES,
                  "counts": abi.B_TILE_COUNTS, "offsets": abi.B_TILE_OFFSETS, "masks": abi.B_TILE_MASKS,
                  "status": abi.B_FRAME_STATUS, "split": abi.B_TILE_SPLIT}
        for name, buf in buffers.items():
            if buf is not None:  # no hit masks without the labeling pass or with tiles other than 16 x 16
                buf.bind_to_storage_buffer(points[name])

    # -- the frame --------------------------------------------------------------------------
    def run(self, uniforms: dict, size: tuple[int, int], layers: int, layer_depth, layer_label,
            timer=None) -> None:
        """Fill ``layers`` label layers for the camera in ``uniforms``; with ``timer``, timed as the
        parts ``visibility:tile_lists`` (bin, scan, scatter), ``visibility:tile_raster``,
        ``visibility:tile_split`` (the split passes, in a frame that splits) and
        ``visibility:redo`` (what a frame that outgrew the list did again).

        Parameters
        ----------
        uniforms : dict
            ``u_R`` (9,) float32 world->camera rotation, column-major (or its bytes); ``u_t`` (3,) metres,
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
        if self._own_status:
            self.status.begin()
        frame = self.status.frame
        self._fit(self._grow_to)
        first = grid != self._grid
        if first:
            self._allocate_tiles(grid)
        if self.hit_masks and (self.masks is None or self.masks.size != 32 * w * h):
            if self.masks is not None:
                self.masks.release()
            self.masks = self.ctx.buffer(reserve=32 * w * h)
        if self.check == "lagged" and frame - LAG in self._capacity_of:
            # the GPU has finished the frame two back by now (or the read waits for it, not for this one)
            total = self.status.read(LAG)[0]
            self._last_total = total
            self.dropped_frames += total > self._capacity_of[frame - LAG]
            self._fit(total)
        # the first frames split: those of a status ring shared with frames before this stage's
        self._split_now = self._splits and frame - max(self.status.long_frame, self._first_frame) <= self.split_hold
        if self._split_now and self._split_counted != frame:
            self.split_frames += 1
            self._split_counted = frame
        status = self.status.record(0)
        tile_uniforms = {**uniforms, "u_tiles": grid, "u_count": self.splats.n, "u_tile_count": grid[0] * grid[1]}
        raster = (tile_uniforms, layers, layer_depth, layer_label)

        passes = timer if timer is not None and timer.passes else None  # each pass a part of its own
        with timed(None if passes else timer, "visibility:tile_lists"):
            self._build_list(tile_uniforms, status, passes)
        with timed(timer, "visibility:tile_raster"):
            self._raster_pass(*raster)
        if self._split_now:
            with timed(timer, "visibility:tile_split"):
                self._split_passes(*raster)
        if (self.check == "frame" and self._own_status) or first:
            # wait for the stage (its GPU time is not stretched: nothing is issued after it) and redo
            # the list if it outgrew its buffer; a renderer's frames are checked by end_frame but on
            # a new size, whose list the last size's does not bound
            self._redo(tile_uniforms, raster, status, timer)
        self._capacity_of[frame] = self.capacity
        self._capacity_of.pop(frame - RING, None)

    def end_frame(self) -> bool:
        """With ``check="frame"`` in a renderer: this frame's list length, from the record the
        renderer read this frame (else read now); True if the list outgrew its buffer, which is
        grown: the renderer must render the frame again (its discs past the end were lost)."""
        if self.check != "frame" or self._own_status:
            return False
        return self._outgrown(self.status.total())

    def _sparse(self) -> bool:
        """Whether this frame's raster walks sparsely (``walk``)."""
        if self.walk != "auto":
            return self.walk == "sparse"
        return self._grid is not None and self._last_total > SPARSE_MIN * self._grid[0] * self._grid[1]

    def _allocate_split(self) -> None:
        """The split buffer (abi.B_TILE_SPLIT), (re)made when the list or the grid outgrew it: room
        for as many discs as the list buffer and for their slices (each tile longer than
        ``split_min`` at most ``count / batch + 1``), at most ``SPLIT_SLOTS_MAX``."""
        tiles = self._grid[0] * self._grid[1]
        slots = min(SPLIT_SLOTS_MAX, self.capacity // self.batch + self.capacity // self.split_min + 1)
        words = len(SPLIT_HEADER) // 4 + 8 * slots + 3 * tiles + 2 * self.tile * self.tile * slots + 2 * self.capacity
        if self.split is not None and self.split.size == 4 * words:
            return
        if self.split is not None:
            self.split.release()
        self.split = self.ctx.buffer(reserve=4 * words)
        self._split_uniforms = {"u_slots": slots, "u_split_entries": self.capacity, "u_split_min": self.split_min}

    def _outgrown(self, total: int) -> bool:
        """Whether a list of ``total`` entries outgrew the buffer; if so the buffer is grown now,
        else headroom for the next frames is made at the next frame (the labeling pass still walks
        this list)."""
        self._last_total = total
        if total <= self.capacity:
            self._grow_to = total
            return False
        self.dropped_frames += 1
        self._fit(total)
        return True

    def _redo(self, tile_uniforms, raster, status, timer) -> None:
        """Wait for the frame's list length and build the list again, larger, if it outgrew its
        buffer. The wait is outside any timed section: a section open while the CPU waits would
        count the idle GPU."""
        while self._outgrown(self.status.read(0)[0]):
            with timed(timer, "visibility:redo"):
                self._build_list(tile_uniforms, status)
                self._raster_pass(*raster)
                if self._split_now:
                    self._split_passes(*raster)

    def _build_list(self, tile_uniforms: dict, status, timer=None) -> None:
        """Bin (count), scan, bin (scatter): each tile's slice of the list, unsorted. With ``timer``,
        each pass timed as a part ``visibility:lists_*`` (:attr:`dmrt.gl.timer.GpuTimer.passes`)."""
        ctx = self.ctx
        n_tiles = tile_uniforms["u_tile_count"]
        with timed(timer, "visibility:lists_clear"):
            fill_u32(ctx, self.counts, 0, _padded(n_tiles))
            self.large.write(EMPTY_DISPATCH)
            ctx.memory_barrier(_BARRIER)
        self._bin_pass(0, tile_uniforms, timer)
        if self._split_now:
            with timed(timer, "visibility:lists_split_plan"):
                self._allocate_split()
                self.split.write(SPLIT_HEADER)  # no slices yet
                self._bind(counts=self.counts, split=self.split)
                plan = self._split_steps[0]
                set_uniforms(plan, **self._split_uniforms, **tile_uniforms)
                plan.run(groups(n_tiles, 64))
                ctx.memory_barrier(_BARRIER)
        with timed(timer, "visibility:lists_scan"):
            self._bind(status=status, counts=self.counts, offsets=self.offsets,
                       split=self.split if self._split_now else None)
            set_uniforms(self._scan, u_tile_count=n_tiles, u_planned=int(self._split_now),
                         u_split_min=self.split_min if self._splits else abi.EMPTY_BITS)
            self._scan.run(1)
            status.written(_BARRIER)  # reading the list length waits for the scan, not the whole frame
        self._bin_pass(1, tile_uniforms, timer)

    def _bin_pass(self, scatter: int, tile_uniforms: dict, timer=None) -> None:
        for large in (0, 1):
            with timed(timer, f"visibility:lists_{('count', 'scatter')[scatter]}{('', '_large')[large]}"):
                program = self._bin[scatter, large, int(scatter and self._split_now)]
                self._bind(proxies=self.splats.buffer, large=self.large, entries=self.entries,
                           counts=self.counts, offsets=self.offsets, split=self.split if self._split_now else None)
                set_uniforms(program, u_capacity=self.capacity, **self._split_uniforms, **tile_uniforms)
                if large:
                    program.run_indirect(self.large)
                elif self.splats.n:
                    program.run(groups(self.splats.n, 64))
                self.ctx.memory_barrier(_BARRIER)

    def _raster_pass(self, tile_uniforms: dict, layers: int, layer_depth, layer_label) -> None:
        self._bind(proxies=self.splats.buffer, layer_depth=layer_depth, layer_label=layer_label,
                   entries=self.entries, offsets=self.offsets, masks=self.masks)
        program = self._rasters[int(self._sparse())]
        set_uniforms(program, u_capacity=self.capacity, u_layers=int(layers), **tile_uniforms)
        program.run(*self._grid)
        self.ctx.memory_barrier(_BARRIER)

    def _split_passes(self, tile_uniforms: dict, layers: int, layer_depth, layer_label) -> None:
        """The layers of the tiles the plan took out of the lists (module doc, step 5), over the
        raster's empty ones: per layer (each reads the one before) the slices, then the merge of
        each tile's slices."""
        self.ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT)  # the plan's header writes
        self.ctx.copy_buffer(self.split_args, self.split, size=len(SPLIT_HEADER))
        self._bind(proxies=self.splats.buffer, layer_depth=layer_depth, layer_label=layer_label, split=self.split)
        for i in range(int(layers)):
            for step in (1, 2):
                program = self._split_steps[step]
                set_uniforms(program, u_layer=i, **self._split_uniforms, **tile_uniforms)
                program.run_indirect(self.split_args, offset=16 * (step - 1))  # the slices' header, then the tiles'
                self.ctx.memory_barrier(_BARRIER)

    def label_pass(self, uniforms: dict, hits, key=None, vlabel=None, packed: bool = False,
                   finalize: dict | None = None) -> None:
        """The labeling pass on this frame's tile lists (``shaders/dmrt_tiles_labeling.glsl``): the
        labels of ``dmrt_labeling.glsl`` without splatting the proxies again.

        Parameters
        ----------
        uniforms : dict, the frame's camera (as :meth:`run`'s, at the same size).
        hits : moderngl.Buffer, the frame's ``Hit`` records (read: each pixel's raytraced depth).
        key, vlabel : moderngl.Buffer, written for every pixel in the layout
            ``dmrt_label_finalize.glsl`` reads: ``packed`` - ``key`` (h x w) uvec2 (label, distance
            bits); else ``key`` (h x w) uint distance bits and ``vlabel`` (h x w) int label.
        finalize : dict, optional
            The label check's uniforms (``u_label_check``, ``u_visibility_tol``, ``u_depthmaps``):
            then the pass writes each pixel's final label into its ``Hit`` record itself, as
            ``dmrt_label_finalize.glsl`` would from ``key`` (not written), with the photos and the
            depth maps bound by the caller.
        """
        defines = {**self._defines, "PACKED_LABELS": int(packed), "FINALIZE": int(finalize is not None)}
        split = self._split_now  # the long lists, out of the tile lists, are labelled by slices after
        program = load_program(self.ctx, "dmrt_tiles_labeling", defines)
        self._bind(proxies=self.splats.buffer, entries=self.entries, offsets=self.offsets, masks=self.masks,
                   split=self.split if split else None)
        hits.bind_to_storage_buffer(abi.B_HITS)
        if finalize is None:
            key.bind_to_storage_buffer(abi.B_KEY)
            if not packed:
                vlabel.bind_to_storage_buffer(abi.B_VLABEL)
        values = {"u_capacity": self.capacity, "u_tiles": self._grid, **self._split_uniforms, **uniforms,
                  **(finalize or {})}
        set_uniforms(program, **values)
        program.run(*self._grid)
        self.ctx.memory_barrier(_BARRIER)
        for split_pass in (1, 2) if split else ():  # the slices, then each split tile's merge
            program = load_program(self.ctx, "dmrt_tiles_labeling", {**defines, "SPLIT_PASS": split_pass})
            set_uniforms(program, **values)
            program.run_indirect(self.split_args, offset=16 * (split_pass - 1))
            self.ctx.memory_barrier(_BARRIER)

    # -- diagnostics ------------------------------------------------------------------------
    def stats(self) -> dict:
        """The last frame's list (waits for the GPU).

        Returns
        -------
        dict
            ``entries`` (list length: disc-tile overlaps), ``capacity`` (entries the buffer held),
            ``dropped`` (bool: the list outgrew the buffer, entries past it were lost), ``large``
            (discs over more than ``max_thread_tiles`` tiles, binned by a workgroup each),
            ``longest`` (the longest tile's entries: one workgroup runs through them alone, so a
            frame whose discs pile up in a few tiles waits for those, unless they are split),
            ``split_tiles``, ``split_slices`` and ``split_discs`` (the tiles whose lists the split
            passes walked instead, their slices: workgroups of ``batch`` discs, and their discs,
            reserved: those of a tile that then found no room for its slices included; 0 without
            the split, or in a frame that did not split: ``split_hold``). ``entries`` and
            ``longest`` are the tile lists', without the split tiles.
        """
        if self.status.frame not in self._capacity_of:
            return {"entries": 0, "capacity": self.capacity, "dropped": False, "large": 0, "longest": 0,
                    "split_tiles": 0, "split_slices": 0, "split_discs": 0}
        entries, capacity = self.status.read(0)[0], self._capacity_of[self.status.frame]
        if self._staging is None:  # the buffers read stay in GPU memory (Staging: why)
            self._staging = Staging(self.ctx)
        read = self._staging.read
        large = int(np.frombuffer(read(self.large, 16), np.uint32)[3])  # the list's header: groups x, y, z, length
        tiles = self._grid[0] * self._grid[1]
        offsets = np.frombuffer(read(self.offsets, 4 * (tiles + 1)), np.uint32)  # exclusive prefix sum + total
        split_tiles = split_slices = split_discs = 0
        if self._split_now:  # the two dispatch headers (abi.B_TILE_SPLIT), as the split passes took them
            split_slices, _, _, _, split_tiles, _, _, split_discs = (
                int(v) for v in np.frombuffer(read(self.split_args, 32), np.uint32))
        return {"entries": entries, "capacity": capacity, "dropped": entries > capacity, "large": large,
                "longest": int(np.diff(offsets).max()) if tiles else 0,
                "split_tiles": split_tiles, "split_slices": split_slices, "split_discs": split_discs}

    def read_overflow(self) -> int:
        """Pixels of the last frame that may differ from peeling: every pixel if the frame's list
        was cut short (``check="lagged"``), else none."""
        if self.stats()["dropped"]:
            return self._grid[0] * self._grid[1] * self.tile * self.tile
        return 0

    @property
    def nbytes(self) -> int:
        """GPU bytes of the path's own buffers (list, tile counts and offsets, large list, hit masks,
        split slices and their dispatch headers, status records if its own; not the statistics'
        read-back copy, which :meth:`stats` alone makes)."""
        bufs = [self.entries, self.large, self.counts, self.offsets, self.masks, self.split, self.split_args]
        return sum(b.size for b in bufs if b is not None) + (self.status.nbytes if self._own_status else 0)

    def release(self) -> None:
        for name in ("entries", "large", "counts", "offsets", "masks", "split", "split_args"):
            buf = getattr(self, name)
            if buf is not None:
                buf.release()
                setattr(self, name, None)
        if self._staging is not None:
            self._staging.release()
        if self._own_status:
            self.status.release()
