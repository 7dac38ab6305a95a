"""DMRT image management and texturing (paper Sections 5.2.2 and 5.2.3).

* Low-resolution copies of every photo (the bundle's ``images_low``, paper: 256x171) stay on the
  GPU in one RGBA8 texture array, one layer per photo: the fallback of every lookup.
* Full-resolution photos are cached in a second RGBA8 texture array of as many layers ("slots")
  as ``cache_mb`` holds. Relevance of a photo = the frequency of its label in the frame's final
  label buffer, counted on the GPU (``atomicAdd``; the readback is 4 bytes per photo). After each
  frame's labeling, the most relevant photos (count > 0, at most as many as there are slots) are
  made resident; a photo already resident keeps its slot, so a steady view uploads nothing, and a
  newcomer takes an empty slot, else that of the least recently wanted photo.
  Photos are decoded from disk on upload (the paper streams them out of core); :attr:`ImageCache.
  uploads` counts uploads. With ``cache_mb = 0`` everything is textured from the low-res copies.

The texturing pass then colours each pixel from its label's photo at the projection of its
raytraced point: from the cache when resident, else from the low-res copy (bilinear both).
"""

from __future__ import annotations

import numpy as np

from dmrt.bundle import Bundle
from dmrt.errors import InputError


def _rgba(image: np.ndarray) -> np.ndarray:
    h, w = image.shape[:2]
    out = np.full((h, w, 4), 255, np.uint8)
    out[..., :3] = image[..., :3]
    return out


class ImageCache:
    """The low-resolution photo array and the full-resolution cache of the most relevant photos.

    Parameters
    ----------
    ctx : moderngl.Context
    bundle : Bundle
    cache_mb : float
        GPU memory for full-resolution photos, MiB (paper: 1 GB). Each slot holds the largest
        photo's size in RGBA8.

    Attributes
    ----------
    low_sizes : list of (width, height) of the low-resolution copies.
    n_slots : int, number of full-resolution slots.
    slot_of : (n_photos,) int32, the cache slot of each photo, -1 = not resident.
    uploads : int, full-resolution uploads so far.
    """

    def __init__(self, ctx, bundle: Bundle, cache_mb: float):
        self.ctx, self.bundle = ctx, bundle
        n = len(bundle.cameras)
        low = [_rgba(bundle.image(i, low=True)) for i in range(n)]  # small: 0.13 MB each (paper)
        self.low_sizes = [(im.shape[1], im.shape[0]) for im in low]
        self.low_dims = (max(s[0] for s in self.low_sizes), max(s[1] for s in self.low_sizes))
        self.low = ctx.texture_array((*self.low_dims, n), 4)
        for i, im in enumerate(low):
            self.low.write(im.tobytes(), viewport=(0, 0, i, im.shape[1], im.shape[0], 1))
        self.full_dims = (max(c.width for c in bundle.cameras), max(c.height for c in bundle.cameras))
        slot_bytes = self.full_dims[0] * self.full_dims[1] * 4
        self.n_slots = int(min(n, max(0.0, cache_mb) * 2 ** 20 // slot_bytes))
        # a 1x1 stand-in keeps the sampler bound when the cache has no slot
        dims = (*self.full_dims, self.n_slots) if self.n_slots else (1, 1, 1)
        self.high = ctx.texture_array(dims, 4)
        self.slot_of = np.full(n, -1, np.int32)
        self._photo_in = np.full(max(self.n_slots, 1), -1, np.int64)
        self._last_used = np.zeros(max(self.n_slots, 1), np.int64)
        self._frame = 0
        self.slots = ctx.buffer(self.slot_of.tobytes())
        self.uploads = 0
        for tex in (self.low, self.high):
            tex.repeat_x = tex.repeat_y = False

    @property
    def nbytes(self) -> dict:
        """GPU bytes: ``images_low`` and ``image_cache``."""
        return {"images_low": self.low.width * self.low.height * self.low.layers * 4,
                "image_cache": self.high.width * self.high.height * self.high.layers * 4 if self.n_slots else 0}

    def update(self, counts: np.ndarray) -> int:
        """Make the most frequent labels resident. ``counts`` (n_photos,) uint32 label histogram.

        Returns the number of photos uploaded.
        """
        if self.n_slots == 0:
            return 0
        order = np.argsort(-counts.astype(np.int64), kind="stable")
        wanted = [int(j) for j in order[:self.n_slots] if counts[j] > 0]
        missing = [j for j in wanted if self.slot_of[j] < 0]
        wanted_set = set(wanted)
        self._frame += 1
        for j in wanted:
            if self.slot_of[j] >= 0:
                self._last_used[self.slot_of[j]] = self._frame
        # empty slots first, then the least recently wanted photos that this frame does not want
        free = sorted((s for s in range(self.n_slots) if int(self._photo_in[s]) not in wanted_set),
                      key=lambda s: (self._photo_in[s] >= 0, self._last_used[s]))
        for j, s in zip(missing, free):
            old = int(self._photo_in[s])
            if old >= 0:
                self.slot_of[old] = -1
            image = _rgba(self.bundle.image(j))
            h, w = image.shape[:2]
            cam = self.bundle.cameras[j]
            if (w, h) != (cam.width, cam.height):
                raise InputError(self.bundle.path("images", j), f"image is {w}x{h}, its camera {cam.width}x{cam.height}")
            self.high.write(image.tobytes(), viewport=(0, 0, s, w, h, 1))
            self._photo_in[s] = j
            self._last_used[s] = self._frame
            self.slot_of[j] = s
            self.uploads += 1
        if missing:
            self.slots.write(self.slot_of.tobytes())
        return len(missing)

    def release(self) -> None:
        for obj in (self.low, self.high, self.slots):
            obj.release()
