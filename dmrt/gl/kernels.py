"""Small GPU kernels every stage uses: workgroup counts and a buffer fill that stays on the GPU."""

from __future__ import annotations

import moderngl
import numpy as np

from dmrt.gl import abi
from dmrt.gl.shaders import load_program, set_uniforms


# The header of a GPU work list: a dispatch-indirect command of no workgroups (x, y, z = 0, 1, 1),
# then the list's length, 0. The kernels that append an item raise both (shaders/dmrt_raytrace.glsl).
EMPTY_DISPATCH = np.array([0, 1, 1, 0], np.uint32).tobytes()


def max_groups(ctx: moderngl.Context) -> int:
    """The most workgroups a dispatch may have along x (``GL_MAX_COMPUTE_WORK_GROUP_COUNT[0]``)."""
    return int(ctx.info["GL_MAX_COMPUTE_WORK_GROUP_COUNT"][0])


def groups(n: int, size: int) -> int:
    """Workgroups of ``size`` invocations covering ``n`` items, at least 1 and at most 65535 (GL's
    guaranteed grid size; kernels that may see more items stride over them)."""
    return max(1, min(-(-int(n) // size), 65535))


def fill_u32(ctx: moderngl.Context, buf: moderngl.Buffer, value: int, count: int) -> None:
    """Set the first ``count`` uint32 words of ``buf`` to ``value`` on the GPU
    (``shaders/fill_u32.glsl``; moderngl's ``Buffer.clear`` builds the pattern on the CPU)."""
    program = load_program(ctx, "fill_u32")
    buf.bind_to_storage_buffer(abi.B_FILL)
    set_uniforms(program, u_value=int(value), u_count=int(count))
    program.run(groups(count, 256))


class Staging:
    """Reads GPU buffers back through a copy into a buffer of its own.

    The NVIDIA driver moves a buffer that the CPU reads back often into host memory, and every pass
    that then writes or reads it goes over PCIe: the label histogram's atomics took 1.4 ms a 4K
    frame there against 0.07 ms in GPU memory (H200, session 8). Reading through a copy keeps the
    buffers the passes use in GPU memory; only the staging buffer, which just the copy writes,
    moves. One staging buffer serves every read (each read waits for its copy), grown as needed.
    """

    def __init__(self, ctx: moderngl.Context):
        self.ctx = ctx
        self._buffer: moderngl.Buffer | None = None

    def read(self, src: moderngl.Buffer, nbytes: int | None = None, offset: int = 0) -> bytes:
        """``nbytes`` bytes of ``src`` from byte ``offset`` (default: all of it); waits for the GPU."""
        n = src.size - offset if nbytes is None else int(nbytes)
        if self._buffer is None or self._buffer.size < n:
            self.release()
            self._buffer = self.ctx.buffer(reserve=n)
        self.ctx.memory_barrier(moderngl.BUFFER_UPDATE_BARRIER_BIT)
        self.ctx.copy_buffer(self._buffer, src, n, read_offset=offset)
        return self._buffer.read(n)

    def release(self) -> None:
        if self._buffer is not None:
            self._buffer.release()
            self._buffer = None
