"""The photos' depth maps and low-resolution copies on the GPU, for any number of photos.

Each photo's depth map (R32F) and low-resolution copy (RGB8) share a slot: a layer of two texture
arrays of ``n_slots`` layers. A texture array holds at most GL_MAX_ARRAY_TEXTURE_LAYERS layers (2048
on NVIDIA's driver and on Mesa), and 10,000 maps of 1024x684 are 28 GB. So:

* when every photo fits (at most that many layers, within ``budget_mb``), slot = photo index and
  the shaders index the arrays directly, as the paper does (the programs are unchanged);
* otherwise the slots are a cache. ``B_MAP_SLOTS`` gives each photo's slot (-1: not resident); the
  programs that read maps or low-resolution photos are compiled with :attr:`MapCache.defines`
  (``MAP_SLOTS``, ``shaders/dmrt_photos.glsl``) and flag in ``B_MAP_MISSING`` each photo whose map
  they wanted and did not find. After the frame the renderer reads the flags (:meth:`missing`),
  loads those maps (:meth:`ensure`: the least recently used photos make room) and renders the frame
  again: a frame never shows a missing map unless it needs more maps than the cache holds.

Which photos a frame used comes from its label histogram (labels and view-choice candidates): they
are the most recently used.
"""

from __future__ import annotations

import os
from concurrent.futures import ThreadPoolExecutor

import moderngl
import numpy as np

from dmrt.errors import ConfigError, InputError
from dmrt.gl import abi


class MapCache:
    """The depth maps and low-resolution photos of one renderer.

    Parameters
    ----------
    ctx : moderngl.Context
    bundle : dmrt.io.bundle.Bundle
    budget_mb : float
        GPU MiB for the two arrays; 0 = as many slots as one texture array holds.

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
    """

    def __init__(self, ctx: moderngl.Context, bundle, budget_mb: float = 0.0):
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
        self.depthmaps = ctx.texture_array((*self.dims, self.n_slots), 1, dtype="f4")
        self.depthmaps.filter = (moderngl.NEAREST, moderngl.NEAREST)
        self.low = ctx.texture_array((*self.low_dims, self.n_slots), 3)
        self.low.repeat_x = self.low.repeat_y = False
        self.slot_of = np.full(n, -1, np.int32)
        self._photo_in = np.full(self.n_slots, -1, np.int64)
        self._last_used = np.zeros(self.n_slots, np.int64)
        self._frame = 0
        self.loads = 0
        self.slots = ctx.buffer(reserve=4 * n)
        self.missing_flags = ctx.buffer(reserve=4 * (n + 1))  # [0]: any missing; [1 + j]: photo j's
        self.missing_flags.write(np.zeros(n + 1, np.uint32).tobytes())
        self._load(list(range(self.n_slots)), first={0: first}, low=low)
        self.loads = 0

    @property
    def nbytes(self) -> dict:
        """GPU bytes: ``depthmaps`` and ``images_low``."""
        return {"depthmaps": self.dims[0] * self.dims[1] * self.n_slots * 4,
                "images_low": self.low_dims[0] * self.low_dims[1] * self.n_slots * 3}

    def bind(self) -> None:
        """Bind the slot table and the missing flags (a frame's passes read and write them)."""
        self.slots.bind_to_storage_buffer(abi.B_MAP_SLOTS)
        self.missing_flags.bind_to_storage_buffer(abi.B_MAP_MISSING)

    def missing(self, counts: np.ndarray | None = None) -> np.ndarray:
        """After a frame (``partial`` only; waits for the GPU): the photos whose maps its passes
        wanted and did not find, as (m,) int64, and the flags cleared for the next frame. ``counts``
        (n_photos,), the frame's label histogram: the photos with a count were used now."""
        self._frame += 1
        if counts is not None:
            used = self.slot_of[np.flatnonzero(counts)]
            self._last_used[used[used >= 0]] = self._frame
        if not np.frombuffer(self.missing_flags.read(4), np.uint32)[0]:
            return np.zeros(0, np.int64)
        flags = np.frombuffer(self.missing_flags.read(), np.uint32)[1:]
        self.missing_flags.write(np.zeros(self.n_photos + 1, np.uint32).tobytes())
        return np.flatnonzero(flags)

    def ensure(self, photos) -> int:
        """Make ``photos`` resident (indices, most needed first; at most ``n_slots``), loading
        those that are not on threads; the least recently used others make room. Returns the
        number loaded."""
        want = [int(j) for j in dict.fromkeys(int(j) for j in photos)][:self.n_slots]
        for j in want:
            if self.slot_of[j] >= 0:
                self._last_used[self.slot_of[j]] = self._frame
        need = [j for j in want if self.slot_of[j] < 0]
        if not need:
            return 0
        keep = np.isin(self._photo_in, want)
        order = np.lexsort((self._last_used, self._photo_in >= 0))  # empty slots, then least recently used
        free = [int(s) for s in order if not keep[s]][:len(need)]
        for s in free:
            old = int(self._photo_in[s])
            if old >= 0:
                self.slot_of[old] = -1
                self._photo_in[s] = -1
        return self._load(need[:len(free)], slots=free)

    def _load(self, photos: list, slots: list | None = None, first: dict | None = None, low: dict | None = None) -> int:
        """Read ``photos``' maps (and low-resolution copies) on threads and write them into
        ``slots`` (default: slot = position in ``photos``)."""
        slots = list(range(len(photos))) if slots is None else slots
        first = first or {}

        def read(j):
            m = first.get(j)
            m = self.bundle.depth_map(j) if m is None else m
            if m.shape[0] > self.dims[1] or m.shape[1] > self.dims[0]:
                raise InputError(self.bundle.path("depthmaps", j), f"depth map {m.shape[1]}x{m.shape[0]} "
                                 f"larger than the first one's {self.dims[0]}x{self.dims[1]}")
            im = (low or {}).get(j)
            return m, (self.bundle.image(j, low=True) if im is None else im)

        with ThreadPoolExecutor(min(len(photos), os.cpu_count() or 2) or 1, thread_name_prefix="dmrt-maps") as pool:
            for j, s, (m, im) in zip(photos, slots, pool.map(read, photos)):
                self.depthmaps.write(np.ascontiguousarray(m, np.float32).tobytes(),
                                     viewport=(0, 0, s, m.shape[1], m.shape[0], 1))
                self.low.write(np.ascontiguousarray(im).tobytes(), viewport=(0, 0, s, im.shape[1], im.shape[0], 1))
                self.slot_of[j], self._photo_in[s], self._last_used[s] = s, j, self._frame
        self.slots.write(self.slot_of.tobytes())
        self.loads += len(photos)
        return len(photos)

    def release(self) -> None:
        for obj in (self.depthmaps, self.low, self.slots, self.missing_flags):
            obj.release()
