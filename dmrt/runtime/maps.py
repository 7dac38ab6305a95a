"""The photos' depth maps and low-resolution copies on the GPU, for any number of photos.

Each photo's depth map (R32F) and low-resolution copy (RGB8) share a slot: a layer of two texture
arrays of ``n_slots`` layers. A texture array holds at most GL_MAX_ARRAY_TEXTURE_LAYERS layers (2048
on NVIDIA's driver and on Mesa), and 10,000 maps of 1024x684 are 28 GB. So:

* when every photo fits (at most that many layers, within ``budget_mb``), slot = photo index and
  the shaders index the arrays directly, as the paper does (the programs are unchanged);
* otherwise the slots are a cache. ``B_MAP_SLOTS`` gives each photo's slot (-1: not resident); the
  programs that read maps or low-resolution photos are compiled with :attr:`MapCache.defines`
  (``MAP_SLOTS``, ``shaders/dmrt_photos.glsl``) and flag in ``B_MAP_MISSING`` each photo whose map
  they wanted and did not find, and each resident one they read. Each frame's flags are copied into
  a ring of records in mapped host memory (as :mod:`dmrt.runtime.status`'s) and cleared
  (:meth:`end_frame`). A frame that is read back reads its own record (a wait for the frame), loads
  the missing maps (:meth:`ensure`: the least recently used photos make room) and is rendered
  again: it never shows a missing map unless it needs more maps than the cache holds. A frame left
  on the GPU (a viewer's, the benchmarks' sustained frames) reads the record of two frames back,
  whose passes are done: no wait. Its missing maps are loaded at once, or with ``asynchronous``
  read on background threads and uploaded by later frames, at most ``max_loads`` a frame, so that
  no frame waits for a disk read: a newly needed map shows as a hole (the next layer, or the hole
  fill) until then. The camera flying through a scene faster than the disk delivers its maps shows
  holes; a walk's steady frames load nothing.

The photos a frame used are those whose maps its passes read and those its photo cache wanted (its
label histogram's most frequent, view-choice candidates included): they become the most recently
used.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor

import moderngl
import numpy as np

from dmrt.errors import ConfigError, InputError
from dmrt.gl import abi
from dmrt.gl.context import check_fits, check_gl
from dmrt.gl.kernels import fill_u32
from dmrt.gl.mapped import MappedBuffer

MAP_MISSING, MAP_USED = 1, 2  # a photo's flag (shaders/dmrt_photos.glsl)
# maps read ahead and not uploaded yet, at most (2.8 MB each at 1024x684): beyond, the least
# recently requested are dropped
MAX_PENDING = 64
RING = 3  # flag records in flight: a frame left on the GPU reads the one written two frames before


class MapCache:
    """The depth maps and low-resolution photos of one renderer.

    Parameters
    ----------
    ctx : moderngl.Context
    bundle : dmrt.io.bundle.Bundle
    budget_mb : float
        GPU MiB for the two arrays; 0 = as many slots as one texture array holds.
    asynchronous : bool
        With a partial cache: frames left on the GPU read their missing maps on background threads
        (see the module doc); False: every load is done before :meth:`ensure` returns.
    max_loads : int
        Asynchronous uploads per frame at most; 0 = no bound.

    Attributes
    ----------
    n_slots : int
    partial : bool, True when the slots are a cache (fewer than the photos)
    defines : dict, the shader defines of programs that read the arrays (empty unless ``partial``)
    depthmaps, low : moderngl.TextureArray, (w, h, n_slots) R32F camera z, RGB8 photos; each map
        and photo fills its layer's top-left corner
    dims : (w, h), the depth arrays' layer size; low_dims the low arrays'
    depth_sizes, low_sizes : list of (w, h), each photo's map and low-resolution copy
    slot_of : (n_photos,) int32, each photo's slot, -1 = not resident
    loads : int, maps loaded after the first fill (misses and prefetches)
    pending : int, maps being read on background threads or read and not uploaded yet
    """

    def __init__(self, ctx: moderngl.Context, bundle, budget_mb: float = 0.0, asynchronous: bool = False,
                 max_loads: int = 0):
        self.ctx, self.bundle = ctx, bundle
        n = self.n_photos = len(bundle.cameras)
        sizes = bundle.meta.get("depthmap_sizes")
        first = bundle.depth_map(0)
        if sizes is None:  # an older bundle: every map read once for its size
            sizes = [first.shape[::-1]] + [bundle.depth_map(i).shape[::-1] for i in range(1, n)]
        self.depth_sizes = [tuple(int(v) for v in s) for s in sizes]
        # maps share one width; heights follow each photo's aspect (dmrt.preprocess.depthmaps rule)
        w0 = first.shape[1]
        self.dims = (w0, max([first.shape[0]] + [int(round(w0 * c.height / c.width)) for c in bundle.cameras]))
        # every low-resolution copy read once for its size (0.13 MB each in the paper); the first
        # fill's kept
        layers = ctx.info["GL_MAX_ARRAY_TEXTURE_LAYERS"]
        low, self.low_sizes = {}, []
        for i in range(n):
            im = bundle.image(i, low=True)
            self.low_sizes.append((im.shape[1], im.shape[0]))
            if i < layers:
                low[i] = im
        self.low_dims = (max(s[0] for s in self.low_sizes), max(s[1] for s in self.low_sizes))
        slot_bytes = self.dims[0] * self.dims[1] * 4 + self.low_dims[0] * self.low_dims[1] * 3
        fit = int(max(0.0, budget_mb) * 2 ** 20 // slot_bytes) if budget_mb > 0 else n
        self.n_slots = min(n, fit, layers)
        if self.n_slots < 1:
            raise ConfigError("map_cache_mb", f"{budget_mb} MiB holds no photo's depth map and low-resolution copy "
                                              f"({slot_bytes / 2 ** 20:.2f} MiB)")
        self.partial = self.n_slots < n
        self.defines = {"MAP_SLOTS": 1} if self.partial else {}
        check_gl(ctx, "before the depth maps' allocation")
        self.depthmaps = ctx.texture_array((*self.dims, self.n_slots), 1, dtype="f4")
        self.depthmaps.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.low = ctx.texture_array((*self.low_dims, self.n_slots), 3)
        self.low.repeat_x = self.low.repeat_y = False
        self.slot_of = np.full(n, -1, np.int32)
        self._photo_in = np.full(self.n_slots, -1, np.int64)
        self._last_used = np.zeros(self.n_slots, np.int64)
        self._frame = 0
        self.loads = 0
        self.max_loads = int(max_loads)
        self._pool = (ThreadPoolExecutor(os.cpu_count() or 2, thread_name_prefix="dmrt-maps")
                      if asynchronous and self.partial else None)
        # photo -> the read of its map and low-resolution copy, least recently requested first
        self._pending: OrderedDict[int, Future] = OrderedDict()
        self._frame_loads = 0  # asynchronous uploads since the last end_frame
        self.slots = ctx.buffer(reserve=4 * n)
        zeros = np.zeros(n + 1, np.uint32).tobytes()  # [0]: any map missing; [1 + j]: photo j's flag
        self.flags = ctx.buffer(zeros)
        self._records = [MappedBuffer(ctx, zeros) for _ in range(RING)] if self.partial else []
        gb = (self.nbytes["depthmaps"] + self.nbytes["images_low"]) / 1e9
        what = (f"{self.n_slots} depth maps of {self.dims[0]}x{self.dims[1]} and their low-resolution copies "
                f"({gb:.2f} GB)")
        try:
            check_fits(ctx, "map_cache_mb", what)  # before reading thousands of maps for nothing
            self._load(list(range(self.n_slots)), first={0: first}, low=low)
            check_fits(ctx, "map_cache_mb", what)  # a driver may allocate on the first write
        except Exception:
            self.release()
            raise
        self.loads = 0

    @property
    def nbytes(self) -> dict:
        """GPU bytes: ``depthmaps`` and ``images_low``."""
        return {"depthmaps": self.dims[0] * self.dims[1] * self.n_slots * 4,
                "images_low": self.low_dims[0] * self.low_dims[1] * self.n_slots * 3}

    @property
    def pending(self) -> int:
        return len(self._pending)

    def bind(self) -> None:
        """Bind the slot table and the flags (a frame's passes read and write them)."""
        self.slots.bind_to_storage_buffer(abi.B_MAP_SLOTS)
        self.flags.bind_to_storage_buffer(abi.B_MAP_MISSING)

    def end_frame(self, used, wait: bool) -> np.ndarray:
        """After a frame's passes (``partial`` only): its flags into the ring, cleared for the next.

        Parameters
        ----------
        used : photo indices the frame used besides those whose maps it read (they become the most
            recently used)
        wait : bool
            True: read this frame's own flags (waits for the frame); False: those of the frame two
            before, whose passes are done (no wait).

        Returns
        -------
        (m,) int64, the photos whose maps that frame wanted and did not find
        """
        self._frame += 1
        self._frame_loads = 0
        record = self._records[self._frame % RING]
        record.copy_from(self.flags, barriers=moderngl.SHADER_STORAGE_BARRIER_BIT)
        fill_u32(self.ctx, self.flags, 0, self.n_photos + 1)
        self._touch(np.asarray(used, np.int64))
        back = 0 if wait else RING - 1
        if self._frame - back < 1:  # no frame that far back
            return np.zeros(0, np.int64)
        flags = np.frombuffer(self._records[(self._frame - back) % RING].read(), np.uint32)[1:]
        self._touch(np.flatnonzero(flags == MAP_USED))
        return np.flatnonzero(flags == MAP_MISSING)

    def ensure(self, photos, block: bool = True) -> int:
        """Make ``photos`` resident (indices, most needed first; at most ``n_slots``); the least
        recently used others make room.

        With ``block`` (or without ``asynchronous``) the missing ones are read on threads and
        uploaded before this returns; otherwise those read already are uploaded (at most
        ``max_loads``) and the others' reads start in the background. Returns the number uploaded.
        """
        want = list(dict.fromkeys(int(j) for j in photos))[:self.n_slots]
        self._touch(np.asarray(want, np.int64))
        need = [j for j in want if self.slot_of[j] < 0]
        if not need:
            return 0
        if not block and self._pool is not None:
            for j in reversed(need):  # the most needed requested last: the freshest
                if j in self._pending:
                    self._pending.move_to_end(j)
                else:
                    self._pending[j] = self._pool.submit(self._read, j)
            excess = len(self._pending) - MAX_PENDING
            for j in list(self._pending):  # least recently requested first
                if excess <= 0:
                    break
                if self._pending[j].cancel() or self._pending[j].done():  # a read under way stays
                    del self._pending[j]
                    excess -= 1
            budget = self.max_loads - self._frame_loads if self.max_loads else len(need)
            need = [j for j in need if j in self._pending and self._pending[j].done()][:max(0, budget)]
            if not need:
                return 0
            self._frame_loads += len(need)
        keep = np.isin(self._photo_in, want)
        order = np.lexsort((self._last_used, self._photo_in >= 0))  # empty slots, then least recently used
        free = [int(s) for s in order if not keep[s]][:len(need)]
        for s in free:
            old = int(self._photo_in[s])
            if old >= 0:
                self.slot_of[old] = -1
                self._photo_in[s] = -1
        return self._load(need[:len(free)], slots=free)

    def _touch(self, photos: np.ndarray) -> None:
        """The resident ones of ``photos`` (int64 indices) become the most recently used."""
        slots = self.slot_of[photos]
        self._last_used[slots[slots >= 0]] = self._frame

    def _read(self, j: int, first: dict | None = None, low: dict | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Photo ``j``'s depth map (h, w) float32 and low-resolution copy (h', w', 3) uint8, from
        ``first`` / ``low`` when they hold it, else from the bundle's files."""
        m = (first or {}).get(j)
        m = self.bundle.depth_map(j) if m is None else m
        if m.shape[0] > self.dims[1] or m.shape[1] > self.dims[0]:
            raise InputError(self.bundle.path("depthmaps", j), f"depth map {m.shape[1]}x{m.shape[0]} "
                             f"larger than the first one's {self.dims[0]}x{self.dims[1]}")
        im = (low or {}).get(j)
        return np.ascontiguousarray(m, np.float32), (self.bundle.image(j, low=True) if im is None else im)

    def _load(self, photos: list, slots: list | None = None, first: dict | None = None, low: dict | None = None) -> int:
        """Write ``photos``' maps (and low-resolution copies) into ``slots`` (default: slot =
        position in ``photos``): those read in the background already, the others read now on
        threads."""
        slots = list(range(len(photos))) if slots is None else slots
        ready = {j: self._pending.pop(j) for j in photos if j in self._pending}
        rest = [j for j in photos if j not in ready]
        with ThreadPoolExecutor(min(len(rest), os.cpu_count() or 2) or 1, thread_name_prefix="dmrt-maps") as pool:
            reads = pool.map(lambda j: self._read(j, first, low), rest)  # in ``rest``'s order, each written as it comes
            for j, s in zip(photos, slots):
                m, im = ready[j].result() if j in ready else next(reads)
                self.depthmaps.write(m.tobytes(), viewport=(0, 0, s, m.shape[1], m.shape[0], 1))
                self.low.write(np.ascontiguousarray(im).tobytes(), viewport=(0, 0, s, im.shape[1], im.shape[0], 1))
                self.slot_of[j], self._photo_in[s], self._last_used[s] = s, j, self._frame
        self.slots.write(self.slot_of.tobytes())
        self.loads += len(photos)
        return len(photos)

    def release(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        for obj in (self.depthmaps, self.low, self.slots, self.flags, *self._records):
            obj.release()
