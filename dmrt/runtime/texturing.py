"""DMRT image management and texturing (paper Sections 5.2.2 and 5.2.3).

* Low-resolution copies of every photo (the bundle's ``images_low``, paper: 256x171) stay on the
  GPU in one RGB8 texture array, one layer per photo: the fallback of every lookup. DMRT keeps
  them with the depth maps (:class:`dmrt.runtime.maps.MapCache`: beyond one texture array's
  layers they are cached with them).
* Full-resolution photos are cached in a second texture array (RGB8 in RGBA8 texels) of as many layers ("slots")
  as ``cache_mb`` holds (by default sized from the GPU's free memory: :func:`auto_cache_mb`).
  Relevance of a photo = the frequency of its label in the frame's final
  label buffer, counted on the GPU, and the most relevant photos (count > 0, at most as many as
  there are slots, most frequent first: :func:`choose_photos`) are chosen on the GPU too
  (``shaders/dmrt_photo_choice.glsl``); the CPU reads only the choice, with the frame's one
  status read (:mod:`dmrt.runtime.status`). The chosen photos are made resident; a photo already
  resident keeps its slot, so a steady view uploads nothing, and a newcomer takes an empty slot,
  else that of the least recently wanted photo. :attr:`ImageCache.uploads` counts uploads.
  ``cache_mb = 0``: low-res copies only.
* Streaming (the paper streams photos out of core [8]). Photos are decoded from the bundle's
  files into a CPU-side LRU of ``cpu_cache_mb``. With ``asynchronous`` the decoding runs on
  background threads: a wanted photo whose decode is not finished is uploaded by a later frame
  (the low-res copy stands in meanwhile), so no frame waits for a disk read or a PNG decode.
  ``max_uploads`` bounds the uploads of one frame (0 = no bound). Synchronous and unbounded, a
  frame's cache is exactly its most frequent labels (what the tests check). :meth:`ImageCache.preload`
  makes a known set of photos resident at once (the benchmark warms the cache with it).

The texturing pass then colours each pixel from its label's photo at the projection of its
raytraced point: from the cache when resident, else from the low-res copy (bilinear both), times
the photo's photometric gain (:mod:`dmrt.preprocess.photometric`, :func:`gains_buffer_data`).
"""

from __future__ import annotations

import os
from collections import OrderedDict
from concurrent.futures import Future, ThreadPoolExecutor, wait

import numpy as np

from dmrt.io.bundle import Bundle
from dmrt.errors import InputError
from dmrt.gl import abi
from dmrt.gl.context import check_fits, check_gl, free_memory_mb
from dmrt.gl.shaders import load_program, set_uniforms
from dmrt.runtime.view_choice import MAX_BLEND


class ImageCache:
    """The low-resolution photo array and the full-resolution cache of the most relevant photos.

    Parameters
    ----------
    ctx : moderngl.Context
    bundle : Bundle
    cache_mb : float or None
        GPU memory for full-resolution photos, MiB (paper: 1 GB). Each slot holds the largest
        photo's size in RGBA8. None: :func:`auto_cache_mb` of the memory free now.
    max_uploads : int
        Full-resolution uploads per frame at most; 0 = unbounded.
    asynchronous : bool
        Decode photos on background threads (see the module doc).
    cpu_cache_mb : float
        Decoded photos kept in CPU memory, MiB (least recently used dropped first).
    maps : dmrt.runtime.maps.MapCache, optional
        Where the low-resolution copies live (DMRT's); None: a texture array of its own.

    Attributes
    ----------
    budget_mb : float, the cache's budget, MiB (``cache_mb``, or what None chose).
    low_sizes : list of (width, height) of the low-resolution copies.
    defines : dict, the shader defines of programs that read ``low`` (:attr:`MapCache.defines`)
    n_slots : int, number of full-resolution slots.
    slot_of : (n_photos,) int32, the cache slot of each photo, -1 = not resident.
    slots : moderngl.Buffer, ``slot_of`` on the GPU.
    uploads : int, full-resolution uploads so far.
    decodes : int, photo decodes started so far (a walkthrough that starts none and uploads none
        leaves the cache as it found it).
    pending : int, photos whose background decode has started and is not yet in the CPU cache.
    wanted : tuple of int, the photos the last frame wanted.
    """

    # bytes a texel of a cache slot: RGBA8, the 4th byte unused. An RGB8 upload is widened by the
    # driver on the CPU (H100: ~2.2 ms a 1024x684 photo, on the frame's thread); an RGBA8 one is a
    # copy, and the GPU stores RGB8 in 4 bytes a texel either way.
    SLOT_TEXEL_BYTES = 4

    def __init__(self, ctx, bundle: Bundle, cache_mb: float | None, max_uploads: int = 0, asynchronous: bool = False,
                 cpu_cache_mb: float = 1024.0, maps=None):
        self.ctx, self.bundle = ctx, bundle
        n = len(bundle.cameras)
        self._maps = maps
        self.defines = maps.defines if maps is not None else {}
        if maps is not None:  # the low-resolution copies live with the depth maps
            self.low, self.low_sizes, self.low_dims = maps.low, maps.low_sizes, maps.low_dims
        else:
            low = [bundle.image(i, low=True) for i in range(n)]  # small: 0.13 MB each (paper)
            self.low_sizes = [(im.shape[1], im.shape[0]) for im in low]
            self.low_dims = (max(s[0] for s in self.low_sizes), max(s[1] for s in self.low_sizes))
            self.low = ctx.texture_array((*self.low_dims, n), 3)
            for i, im in enumerate(low):
                self.low.write(np.ascontiguousarray(im).tobytes(), viewport=(0, 0, i, im.shape[1], im.shape[0], 1))
        self.full_dims = (max(c.width for c in bundle.cameras), max(c.height for c in bundle.cameras))
        slot_bytes = self.full_dims[0] * self.full_dims[1] * self.SLOT_TEXEL_BYTES
        check_gl(ctx, "before the photo cache's allocation")
        self.budget_mb = auto_cache_mb(free_memory_mb(ctx)) if cache_mb is None else max(0.0, cache_mb)
        self.n_slots = int(min(n, self.budget_mb * 2 ** 20 // slot_bytes, ctx.info["GL_MAX_ARRAY_TEXTURE_LAYERS"]))
        # a 1x1 stand-in keeps the sampler bound when the cache has no slot
        self.high = ctx.texture_array((*self.full_dims, self.n_slots) if self.n_slots else (1, 1, 1),
                                      self.SLOT_TEXEL_BYTES)
        try:
            check_fits(ctx, "cache_mb", f"the photo cache's {self.n_slots} photos of {self.full_dims[0]}x"
                                        f"{self.full_dims[1]} ({self.n_slots * slot_bytes / 1e9:.2f} GB)")
        except Exception:
            for tex in (self.high,) if self._maps is not None else (self.low, self.high):
                tex.release()
            raise
        for tex in (self.low, self.high):
            tex.repeat_x = tex.repeat_y = False
        self.slot_of = np.full(n, -1, np.int32)
        self.slots = ctx.buffer(self.slot_of.tobytes())
        self.uploads = 0
        self.decodes = 0
        self.max_uploads = int(max_uploads)
        self._photo_in = np.full(max(self.n_slots, 1), -1, np.int64)
        self._last_used = np.zeros(max(self.n_slots, 1), np.int64)
        self._frame = 0
        self._wanted: list[int] = []
        self._pool = ThreadPoolExecutor(2, thread_name_prefix="dmrt-photos") if asynchronous else None
        self._pending: dict[int, Future] = {}
        self._decoded: OrderedDict[int, np.ndarray] = OrderedDict()
        self._cpu_budget = max(0.0, cpu_cache_mb) * 2 ** 20
        self._decoded_bytes = 0  # of the photos in _decoded (kept, not summed per insert: thousands of small photos)

    @property
    def wanted(self) -> tuple[int, ...]:
        """The photos the last frame wanted, most relevant first (:meth:`update`)."""
        return tuple(self._wanted)

    @property
    def pending(self) -> int:
        """Photos whose background decode has started and is not yet in the CPU cache."""
        return len(self._pending)

    @property
    def nbytes(self) -> dict:
        """GPU bytes: ``images_low`` and ``image_cache``."""
        return {"images_low": 0 if self._maps is not None else self.low.width * self.low.height * self.low.layers * 3,
                "image_cache": self.high.width * self.high.height * self.high.layers * self.SLOT_TEXEL_BYTES
                if self.n_slots else 0}

    def update(self, wanted) -> int:
        """Make ``wanted`` resident: (m,) photo indices, most relevant first, m <= ``n_slots``
        (:func:`choose_photos`, or its GPU twin's list).

        Returns the number of photos uploaded.
        """
        if self.n_slots == 0:
            return 0
        self._want(wanted)
        return self._upload(self.max_uploads, block=self._pool is None)

    def flush(self) -> int:
        """Finish the pending decodes and upload every photo the last frame wanted."""
        if self._pending:
            wait(list(self._pending.values()))
        return self._upload(0, block=True) if self.n_slots else 0

    def preload(self, photos) -> int:
        """Make ``photos`` resident now (indices, most relevant first; the first ``n_slots``), decoded
        on a thread per CPU core: for a viewer that knows which photos a walkthrough will want (the
        benchmark's warm-up). Returns the number uploaded."""
        if self.n_slots == 0:
            return 0
        self._want(photos)
        with ThreadPoolExecutor(os.cpu_count() or 2, thread_name_prefix="dmrt-preload") as pool:
            for j in self._wanted:
                if self.slot_of[j] < 0 and j not in self._decoded and j not in self._pending:
                    self._pending[j] = pool.submit(self._decode, j)
                    self.decodes += 1
            return self._upload(0, block=True)

    def _want(self, photos) -> None:
        """A new frame wants ``photos`` (the first ``n_slots``): the resident ones' slots count as
        used now."""
        self._wanted = list(dict.fromkeys(int(j) for j in photos))[:self.n_slots]
        self._frame += 1
        for j in self._wanted:
            if self.slot_of[j] >= 0:
                self._last_used[self.slot_of[j]] = self._frame

    def _upload(self, limit: int, block: bool) -> int:
        self._harvest()
        missing = [j for j in self._wanted if self.slot_of[j] < 0]
        if not missing:  # the steady state: nothing to sort
            return 0
        free = None  # the slots to fill, in order: found once a decoded photo is ready
        done = 0
        for j in missing:
            if limit and done >= limit:
                break
            image = self._image(j, block)
            if image is None:  # still decoding: a later frame uploads it
                continue
            if free is None:
                free = self._free_slots()
            if not free:
                break
            s = free.pop(0)
            old = int(self._photo_in[s])
            if old >= 0:
                self.slot_of[old] = -1
            h, w = image.shape[:2]
            self.high.write(image, viewport=(0, 0, s, w, h, 1))
            self._photo_in[s], self._last_used[s], self.slot_of[j] = j, self._frame, s
            done += 1
        if done:
            self.uploads += done
            self.slots.write(self.slot_of.tobytes())
        if self._pool is not None:  # prefetch what is still missing
            for j in missing:
                if self.slot_of[j] < 0:
                    self._image(j, False)
        return done

    def _free_slots(self) -> list[int]:
        """The slots that hold no photo the frame wants: empty ones first, then the least recently
        wanted (equal: the smaller slot first)."""
        photo = self._photo_in[:self.n_slots]
        slots = np.flatnonzero(~np.isin(photo, self._wanted))
        return slots[np.lexsort((self._last_used[slots], photo[slots] >= 0))].tolist()

    def _harvest(self) -> None:
        """Move the finished background decodes of photos this frame does not want into the CPU
        cache, as its least recent (the wanted ones are :meth:`_image`'s): a decode that one frame
        started and no later frame wanted stayed pending for good (its photo held in memory outside
        ``cpu_cache_mb``, and ``pending`` never 0: likely why the 10,240-photo walk's warm-up at
        3840x2160 never settled, reports/many-photos). One that failed is dropped: a frame that
        wants its photo decodes it again and reports the error."""
        wanted = set(self._wanted)
        for j in [j for j, fut in self._pending.items() if fut.done() and j not in wanted]:
            fut = self._pending.pop(j)
            if fut.exception() is None:
                self._keep(j, fut.result(), recent=False)

    def _keep(self, j: int, image: np.ndarray, recent: bool = True) -> None:
        """Photo ``j`` decoded, the most (or least) recent in the CPU cache, whose least recent are
        dropped past ``cpu_cache_mb``."""
        old = self._decoded.get(j)
        self._decoded_bytes += image.nbytes - (old.nbytes if old is not None else 0)
        self._decoded[j] = image
        self._decoded.move_to_end(j, last=recent)
        while len(self._decoded) > 1 and self._decoded_bytes > self._cpu_budget:
            self._decoded_bytes -= self._decoded.popitem(last=False)[1].nbytes

    def _image(self, j: int, block: bool) -> np.ndarray | None:
        """Photo ``j`` decoded (h, w, 4) uint8 RGBA (alpha unused), or None while its background decode
        runs."""
        if j in self._decoded:
            self._decoded.move_to_end(j)
            return self._decoded[j]
        fut = self._pending.get(j)
        if fut is None and self._pool is not None and not block:
            self._pending[j] = self._pool.submit(self._decode, j)
            self.decodes += 1
            return None
        if fut is not None and not (block or fut.done()):
            return None
        if fut is None:
            self.decodes += 1
        image = fut.result() if fut is not None else self._decode(j)
        self._pending.pop(j, None)
        self._keep(j, image)
        return image

    def _decode(self, j: int) -> np.ndarray:
        image = self.bundle.image(j)
        cam = self.bundle.cameras[j]
        if image.shape[:2] != (cam.height, cam.width):
            raise InputError(self.bundle.path("images", j), f"image is {image.shape[1]}x{image.shape[0]}, "
                                                            f"its camera {cam.width}x{cam.height}")
        rgba = np.empty((*image.shape[:2], 4), np.uint8)  # widened here: on a decoding thread when streamed
        rgba[..., :3] = image
        rgba[..., 3] = 255
        return rgba

    def release(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(wait=True, cancel_futures=True)
        for obj in (self.high, self.slots) if self._maps is not None else (self.low, self.high, self.slots):
            obj.release()


# auto_cache_mb's rule: the paper's 1 GB at least; a quarter of the memory the driver says is free
# when the cache is made, after the depth maps (the rest for frame buffers, DMT's maps, other
# programs, and maps the driver has not counted yet: free_memory_mb), never more than half
PAPER_CACHE_MB = 1024.0
AUTO_CACHE_SHARE, AUTO_CACHE_MAX_SHARE = 0.25, 0.5


def auto_cache_mb(free_mb: float | None) -> float:
    """The photo cache's default budget, MiB, from the GPU memory free (MiB; None: unknown).

    A walk's photos should fit: with thousands of photos, the paper's 1 GB (383 photos of 1024x684)
    reloads photos every frame (reports/many-photos: 3.2x the frame time of a 3 GB cache on an
    H200). So a quarter of the free memory, at least 1 GB but at most half of it; 1 GB where the
    driver does not tell (the slots stay bounded by the photos and one texture array's layers).
    """
    if free_mb is None:
        return PAPER_CACHE_MB
    return min(max(PAPER_CACHE_MB, AUTO_CACHE_SHARE * free_mb), AUTO_CACHE_MAX_SHARE * free_mb)


def choose_photos(counts: np.ndarray, n_slots: int) -> np.ndarray:
    """The photos the cache should hold (the numpy twin of ``shaders/dmrt_photo_choice.glsl``).

    Parameters
    ----------
    counts : (n_photos,) integer pixels per label in the frame (the label histogram)
    n_slots : int, the cache's slots

    Returns
    -------
    (m,) int64 photo indices with count > 0, most pixels first (equal counts: smaller index
    first), m <= n_slots
    """
    counts = np.asarray(counts).astype(np.int64)
    order = np.argsort(-counts, kind="stable")[:max(int(n_slots), 0)]
    return order[counts[order] > 0]


def gains_buffer_data(gains: np.ndarray | None, n_photos: int) -> np.ndarray:
    """(n_photos, 4) float32 rows of the ``photo_gains`` buffer (``shaders/dmrt_photo_color.glsl``):
    RGB gain and 1; ``gains`` (n_photos, 3) or None (all 1)."""
    out = np.ones((n_photos, 4), np.float32)
    if gains is not None:
        out[:, :3] = np.asarray(gains, np.float32).reshape(n_photos, 3)
    return out


def texture_frame(ctx, timer, images: ImageCache, wanted: np.ndarray, hits, colors, photos, cam_uniforms: dict,
                  gains=None, blend=None) -> float:
    """Image management after the label histogram, then the texturing pass; shared by the DMRT and
    DMT renderers (both write the ``Hit`` records of ``shaders/dmrt_frame.glsl``).

    Parameters
    ----------
    ctx : moderngl.Context
    timer : dmrt.gl.GpuTimer, sections ``image_management`` (uploads) and ``texturing``
    images : ImageCache
    wanted : (m,) photo indices to make resident, most relevant first (:meth:`ImageCache.update`)
    hits, colors : moderngl.Buffer, the frame's ``Hit`` records and packed RGBA8 colours (written)
    photos : moderngl.Buffer, the ``Photo`` records (``dmrt.runtime.shading.photo_params``)
    cam_uniforms : dict, ``u_R, u_t, u_K, u_size`` of the frame
    gains : moderngl.Buffer, the photos' gains (:func:`gains_buffer_data`), bound to
        ``abi.B_PHOTO_GAINS``; None keeps what is bound there
    blend : moderngl.Buffer, optional
        The view-dependent choice's per-pixel blend records (:class:`dmrt.runtime.view_choice.ViewChoice`
        with ``blend`` > 1): each pixel mixes its photos

    Returns
    -------
    float, wall ms of choosing, decoding and uploading photos (CPU time)
    """
    import time

    import moderngl

    t1 = time.perf_counter()
    with timer.section("image_management:photo_uploads"):
        images.update(wanted)
    t2 = time.perf_counter()
    w, h = cam_uniforms["u_size"]
    program = load_program(ctx, "dmrt_texturing", {**images.defines, **({"BLEND": MAX_BLEND} if blend is not None else {})})
    with timer.section("texturing"):
        hits.bind_to_storage_buffer(abi.B_HITS)
        photos.bind_to_storage_buffer(abi.B_PHOTOS)
        images.slots.bind_to_storage_buffer(abi.B_SLOTS)
        colors.bind_to_storage_buffer(abi.B_COLORS)
        if gains is not None:
            gains.bind_to_storage_buffer(abi.B_PHOTO_GAINS)
        if blend is not None:
            blend.bind_to_storage_buffer(abi.B_VIEW_BLEND)
        images.low.use(1)
        images.high.use(2)
        set_uniforms(program, u_low=1, u_high=2, u_low_dims=images.low_dims,
                     u_high_dims=(images.high.width, images.high.height), **cam_uniforms)
        program.run(-(-w // 8), -(-h // 8))
        ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT | moderngl.SHADER_STORAGE_BARRIER_BIT)
    return (t2 - t1) * 1e3
