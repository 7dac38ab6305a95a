"""Small GPU kernels every stage uses: workgroup counts and a buffer fill that stays on the GPU."""

from __future__ import annotations

import moderngl

from dmrt.gl import abi
from dmrt.gl.shaders import load_program, set_uniforms


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
