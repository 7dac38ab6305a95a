"""The photo choice's ranking on the GPU: the photos with a non-zero count, most first, into a
status record (``shaders/dmrt_photo_compact.glsl`` then ``shaders/dmrt_photo_choice.glsl``; numpy
twin :func:`dmrt.runtime.texturing.choose_photos`). The photo cache ranks the label histogram
(:mod:`dmrt.runtime.shading`), the view-dependent choice its scores (:mod:`dmrt.runtime.view_choice`).

The photos with a count are compacted into a list first and only the list is ranked, so the cost
follows the frame's photos (a few hundred) and not the scene's (thousands). Both passes cover every
photo, so nothing is read back.
"""

from __future__ import annotations

import moderngl

from dmrt.gl import abi
from dmrt.gl.kernels import fill_u32, groups
from dmrt.gl.shaders import load_program, set_uniforms

_BARRIER = moderngl.SHADER_STORAGE_BARRIER_BIT


class PhotoRanking:
    """Ranks ``n_photos`` uint counts into the ``wanted`` list of a ``FrameStatus``-like record.

    Parameters
    ----------
    ctx : moderngl.Context
    n_photos : int
    counts_binding, status_binding : str
        The :mod:`dmrt.gl.abi` names the counts and the record are bound at (the label histogram
        and the frame status, or the view scores and the view candidates).
    """

    def __init__(self, ctx: moderngl.Context, n_photos: int, counts_binding: str = "B_COUNTS",
                 status_binding: str = "B_FRAME_STATUS"):
        self.ctx, self.n_photos = ctx, int(n_photos)
        self._counts_binding, self._status_binding = getattr(abi, counts_binding), getattr(abi, status_binding)
        self._compact = load_program(ctx, "dmrt_photo_compact", {"N_PHOTOS": self.n_photos,
                                                                 "COUNTS_BINDING": counts_binding})
        self._rank = load_program(ctx, "dmrt_photo_choice", {"STATUS_BINDING": status_binding})
        self.list = ctx.buffer(reserve=8 + 8 * self.n_photos)  # length + spare word, (count, photo) pairs

    @property
    def nbytes(self) -> int:
        """GPU bytes held (the compacted list)."""
        return self.list.size

    def run(self, counts: moderngl.Buffer, record: moderngl.Buffer, slots: int) -> None:
        """Write the at most ``slots`` (>= 1) photos of ``counts`` ((n_photos,) uint32) with a
        non-zero count, most first (ties: smaller index first), and their number into ``record``
        (``abi.STATUS_HEADER_WORDS`` uint, word 1 the number, then int32 photos); the record's
        other header words are left as they are. Issues the passes only; the caller puts the
        barrier before a pass that reads ``record``."""
        fill_u32(self.ctx, self.list, 0, 1)  # the list's length, cleared on the GPU each frame
        self.ctx.memory_barrier(_BARRIER)
        counts.bind_to_storage_buffer(self._counts_binding)
        self.list.bind_to_storage_buffer(abi.B_PHOTO_LIST)
        self._compact.run(groups(self.n_photos, 64))
        self.ctx.memory_barrier(_BARRIER)
        record.bind_to_storage_buffer(self._status_binding)
        set_uniforms(self._rank, u_slots=int(slots))
        self._rank.run(groups(self.n_photos, 64))

    def release(self) -> None:
        self.list.release()
