"""The one small record a frame reads back (``FrameStatus`` of :mod:`dmrt.gl.abi`).

Two things a frame decides on the GPU need the CPU: the tile-binned visibility stage's list length
(the CPU sizes the list buffer, :mod:`dmrt.runtime.tiles`) and the photos the full-resolution cache
should hold (the CPU decodes and uploads them, :mod:`dmrt.runtime.texturing`). Both go into one
record of ``4 + wanted_max`` uint32 words: ``tile_total``, ``n_wanted``, ``long_tiles`` (the tiles
whose list is longer than the split's minimum: the tiles path splits them while frames have them),
a spare word, then ``wanted`` - the photos the label histogram ranks first, most frequent first
(``shaders/dmrt_photo_choice.glsl``).

Three records turn in a ring, in persistently mapped host memory (:class:`dmrt.gl.mapped.MappedBuffer`):
a read waits for a fence placed after the pass that wrote the record, never for the rest of the
work queued (a plain buffer read drained the whole queue: the GPU then idled while the CPU issued
the next frame). Frame N's visibility stage writes ``tile_total`` into record N; frame N's photo
choice writes the ``wanted`` list into record N + 1, so one read of record N after frame N's
visibility stage returns both its list length and the previous frame's choice. A frame reads one
record (the tiles path's first frame of a size reads its list length once more, right after its
raster; diagnostics such as ``TileVisibility.stats`` read one too):

* with ``tile_check="frame"`` the renderer reads record N when it updates the photo cache, after
  issuing everything up to the label histogram: the read waits for frame N's tile lists, which the
  GPU has finished by then or soon after; the tiles path then checks the list length it holds (a
  frame that outgrew it is rendered again);
* with ``tile_check="lagged"`` it reads record N - 2 at the start of frame N, whose writes the GPU
  has finished: no wait (the photo cache then follows frame N - 3's choice);
* the other visibility paths read record N when the photo cache is updated; the last write to it
  was the previous frame's choice, long done;
* only with synchronous photos (``async_photos`` off, the tests' deterministic mode) a frame also
  reads its own choice (record N + 1), which waits for the frame so far.
"""

from __future__ import annotations

import moderngl
import numpy as np

from dmrt.gl.abi import STATUS_HEADER_WORDS
from dmrt.gl.mapped import MappedBuffer

RING = 3


class FrameStatus:
    """The ring of ``FrameStatus`` records and what was read from it.

    Parameters
    ----------
    ctx : moderngl.Context
    wanted_max : int
        Photos the ``wanted`` list holds at most (the photo cache's slots; 0: no list).

    Attributes
    ----------
    frame : int
        The frame being rendered (-1 before the first :meth:`begin`).
    reads : int
        Records read back so far (the benchmarks count them per frame).
    long_frame : int
        The last frame whose record, read back, counted a tile list longer than the split's
        minimum (``long_tiles``); 0 before any (the tiles path splits the first frames).
    """

    def __init__(self, ctx: moderngl.Context, wanted_max: int = 0):
        self.wanted_max = max(int(wanted_max), 0)
        zeros = np.zeros(STATUS_HEADER_WORDS + self.wanted_max, np.uint32).tobytes()
        # in mapped host memory: a read waits for the fence of the pass that wrote the record, not
        # for all the work queued (dmrt/gl/mapped.py); zeros: frame 0 wants no photo yet
        self.records = [MappedBuffer(ctx, zeros) for _ in range(RING)]
        self.frame = -1
        self.reads = 0
        self.long_frame = 0
        self._this: dict[int, tuple[int, np.ndarray]] = {}  # this frame's reads: back -> (total, wanted)
        self._last: np.ndarray | None = None  # the wanted list of this frame's last read

    def begin(self) -> MappedBuffer:
        """Start the next frame; its record (the visibility stage binds it as ``B_FRAME_STATUS``)."""
        self.frame += 1
        self._this, self._last = {}, None
        return self.record(0)

    def record(self, back: int = 0) -> MappedBuffer:
        """The record of frame ``frame - back``; ``back=-1``: the next frame's, which this frame's
        photo choice writes. A pass that writes it binds it (``bind_to_storage_buffer``) and then
        calls its ``written()``: a read waits for that pass and what was issued before it only."""
        return self.records[(self.frame - back) % RING]

    def read(self, back: int = 0) -> tuple[int, np.ndarray]:
        """Read the record of frame ``frame - back`` (waits for the pass that wrote it last).

        Returns
        -------
        tile_total : int, the list length its frame's tiles path wrote (entries)
        wanted : (n_wanted,) int64 photo indices, most frequent first, of the choice it holds
        """
        raw = np.frombuffer(self.record(back).read(), np.uint32)
        self.reads += 1
        if back >= 0 and raw[2]:  # the next frame's record (back -1) holds an older frame's count
            self.long_frame = max(self.long_frame, self.frame - back)
        n = min(int(raw[1]), self.wanted_max)
        wanted = raw[STATUS_HEADER_WORDS:STATUS_HEADER_WORDS + n].astype(np.int64)
        self._this[back] = (int(raw[0]), wanted)
        self._last = wanted
        return int(raw[0]), wanted

    def wanted(self) -> np.ndarray:
        """The photo choice of the record read last in this frame, else of this frame's record
        (the previous frame's choice): what the photo cache follows this frame."""
        return self._last if self._last is not None else self.read(0)[1]

    def total(self) -> int:
        """This frame's tile list length: from its record if read in this frame, else read now."""
        return self._this[0][0] if 0 in self._this else self.read(0)[0]

    @property
    def nbytes(self) -> int:
        return sum(r.size for r in self.records)

    def release(self) -> None:
        for r in self.records:
            r.release()
        self.records = []
