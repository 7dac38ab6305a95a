"""Small buffers the CPU reads without a read-back: persistently mapped host memory and a fence.

Reading a GPU buffer through moderngl (``Buffer.read``: a synchronous map) waits for all the work
queued so far, not just for the writes to that buffer: on an H100 a 720p frame's read of a status
record written two frames earlier took ~1 ms, the GPU idling while the CPU then issued the next
frame. A :class:`MappedBuffer` instead lives in host
memory, mapped once for the buffer's lifetime (``GL_MAP_PERSISTENT_BIT | GL_MAP_COHERENT_BIT``,
GL 4.4); after the passes that write it, :meth:`MappedBuffer.written` places a fence, and
:meth:`MappedBuffer.read` waits for that fence only - the work queued after it runs on - and
copies the bytes from the mapping.

moderngl exposes neither buffer storage nor sync objects, so this module calls the few GL entry
points it needs through ctypes (their addresses from ``eglGetProcAddress``, or GLX's for a
windowed viewer) on the thread's current context: the one the buffer was made in.
"""

from __future__ import annotations

import ctypes
from functools import lru_cache

import moderngl

_SHADER_STORAGE_BUFFER = 0x90D2
_MAP_READ = 0x0001
_MAP_WRITE = 0x0002
_MAP_PERSISTENT = 0x0040
_MAP_COHERENT = 0x0080
_CLIENT_STORAGE = 0x0200
_SYNC_GPU_COMMANDS_COMPLETE = 0x9117
_SYNC_FLUSH_COMMANDS = 0x1
_ALREADY_SIGNALED, _TIMEOUT_EXPIRED, _CONDITION_SATISFIED, _WAIT_FAILED = 0x911A, 0x911B, 0x911C, 0x911D
_CLIENT_MAPPED_BUFFER_BARRIER = 0x4000
_WAIT_NS = 1_000_000_000  # one wait's timeout; a fence unsignalled after 60 of them is a hung GPU
_WAITS = 60

_u, _p, _sz = ctypes.c_uint, ctypes.c_void_p, ctypes.c_ssize_t
_SIGNATURES = {  # name: (result, arguments)
    "glCreateBuffers": (None, [ctypes.c_int, ctypes.POINTER(_u)]),
    "glNamedBufferStorage": (None, [_u, _sz, _p, _u]),
    "glMapNamedBufferRange": (_p, [_u, _sz, _sz, _u]),
    "glUnmapNamedBuffer": (ctypes.c_ubyte, [_u]),
    "glDeleteBuffers": (None, [ctypes.c_int, ctypes.POINTER(_u)]),
    "glBindBufferBase": (None, [_u, _u, _u]),
    "glFenceSync": (_p, [_u, _u]),
    "glClientWaitSync": (_u, [_p, _u, ctypes.c_uint64]),
    "glDeleteSync": (None, [_p]),
    "glCopyNamedBufferSubData": (None, [_u, _u, _sz, _sz, _sz]),
}


def _lib(*names: str):
    for name in names:
        try:
            return ctypes.CDLL(name)
        except OSError:
            continue
    return None


def _proc_address():
    """eglGetProcAddress when an EGL context is current (the suite's), else glXGetProcAddressARB
    (a windowed viewer's GLX context)."""
    egl = _lib("libEGL.so.1", "libEGL.so")
    if egl is not None:
        egl.eglGetCurrentContext.restype = _p
        if egl.eglGetCurrentContext():
            egl.eglGetProcAddress.restype = _p
            egl.eglGetProcAddress.argtypes = [ctypes.c_char_p]
            return egl.eglGetProcAddress
    glx = _lib("libGL.so.1", "libGL.so")
    if glx is None:
        raise RuntimeError("libEGL or libGL is needed to reach GL entry points")
    glx.glXGetProcAddressARB.restype = _p
    glx.glXGetProcAddressARB.argtypes = [ctypes.c_char_p]
    return glx.glXGetProcAddressARB


def entry_points(signatures: dict, need: str):
    """GL entry points as a namespace of ctypes functions.

    Parameters
    ----------
    signatures : {name: (result type, [argument types])}
    need : what the caller needs, for the message when the driver lacks one (``"GL 4.5 is
        needed for mapped buffers"``).
    """
    get = _proc_address()
    fns = {}
    for name, (res, args) in signatures.items():
        address = get(name.encode())
        if not address:
            raise RuntimeError(f"the GL driver lacks {name} ({need})")
        fns[name] = staticmethod(ctypes.CFUNCTYPE(res, *args)(address))
    return type("GL", (), fns)


@lru_cache(maxsize=None)  # once a process: glvnd's entry points dispatch to the current context
def _gl():
    """The GL entry points above."""
    return entry_points(_SIGNATURES, "GL 4.5 is needed for mapped buffers")


class MappedBuffer:
    """A GPU-written, CPU-read buffer in persistently mapped host memory.

    Parameters
    ----------
    ctx : moderngl.Context
        The context the shaders that write the buffer run in (it must be current).
    data : bytes
        Initial contents; their length is the buffer's size.

    Usage: bind it like a moderngl buffer (:meth:`bind_to_storage_buffer`), call :meth:`written`
    after the pass that writes it, :meth:`read` when the CPU needs it. A read with no
    :meth:`written` since the last bind fences everything issued so far (correct, but it waits).
    """

    def __init__(self, ctx: moderngl.Context, data: bytes):
        # GL 4.4 buffer storage and 4.5 direct state access (drivers expose both to 4.3 contexts as
        # extensions: NVIDIA's; Mesa's contexts are 4.5)
        if ctx.version_code < 450 and not {"GL_ARB_buffer_storage", "GL_ARB_direct_state_access"} <= set(ctx.extensions):
            raise RuntimeError("the GL driver lacks GL 4.5 or GL_ARB_buffer_storage + GL_ARB_direct_state_access, "
                               "which the frame's status records need (persistently mapped buffers)")
        self.ctx, self.size = ctx, len(data)
        gl = self._gl = _gl()
        glo = _u(0)
        gl.glCreateBuffers(1, ctypes.byref(glo))
        self.glo = glo.value
        access = _MAP_READ | _MAP_WRITE | _MAP_PERSISTENT | _MAP_COHERENT
        gl.glNamedBufferStorage(self.glo, self.size, data, access | _CLIENT_STORAGE)
        self._ptr = gl.glMapNamedBufferRange(self.glo, 0, self.size, access)
        if not self._ptr:
            gl.glDeleteBuffers(1, ctypes.byref(glo))
            raise RuntimeError("the GL driver could not map a persistent read buffer")
        self._fence = None
        self._unfenced = False  # bound for writing since the last fence

    def bind_to_storage_buffer(self, binding: int) -> None:
        """Bind to ``binding`` for the passes issued next (as ``moderngl.Buffer``'s)."""
        self._gl.glBindBufferBase(_SHADER_STORAGE_BUFFER, binding, self.glo)
        self._unfenced = True

    def written(self, barriers: int = 0) -> None:
        """Mark the passes issued so far as the ones :meth:`read` waits for. ``barriers``: memory
        barrier bits the caller needs after those passes anyway, issued in the same barrier."""
        # the barrier makes shader writes to a persistently mapped buffer visible once the fence signals
        self.ctx.memory_barrier(barriers | _CLIENT_MAPPED_BUFFER_BARRIER)
        self._place_fence()

    def _place_fence(self) -> None:
        if self._fence:
            self._gl.glDeleteSync(self._fence)
        self._fence = self._gl.glFenceSync(_SYNC_GPU_COMMANDS_COMPLETE, 0)
        if not self._fence:
            raise RuntimeError("glFenceSync failed: the GL context is lost")
        self._unfenced = False

    def copy_from(self, src: moderngl.Buffer, nbytes: int | None = None, barriers: int = 0) -> None:
        """Copy the first ``nbytes`` (default: all of this buffer) of a GPU buffer into this one on
        the GPU, after the passes issued so far, and mark the copy as what :meth:`read` waits for.
        For what shaders build with atomics: GPU atomics belong in GPU memory, not across PCIe.
        ``barriers``: as :meth:`written`'s."""
        n = self.size if nbytes is None else int(nbytes)
        # the shaders' writes to src first
        self.ctx.memory_barrier(barriers | moderngl.BUFFER_UPDATE_BARRIER_BIT)
        self._gl.glCopyNamedBufferSubData(src.glo, self.glo, 0, 0, n)
        self._place_fence()  # a copy, not a shader write: the fence alone makes it visible

    def read(self, nbytes: int | None = None) -> bytes:
        """The contents (the first ``nbytes``, default all) once the passes up to the last
        :meth:`written` have run."""
        self._wait()
        return ctypes.string_at(self._ptr, self.size if nbytes is None else min(int(nbytes), self.size))

    def write(self, data: bytes) -> None:
        """Overwrite the start of the buffer from the CPU, once the passes up to the last
        :meth:`written` have run."""
        if len(data) > self.size:
            raise ValueError(f"{len(data)} bytes do not fit a mapped buffer of {self.size}")
        self._wait()
        ctypes.memmove(self._ptr, data, len(data))

    def _wait(self) -> None:
        if not self._ptr:
            raise RuntimeError("the mapped buffer was released")
        if self._unfenced:
            self.written()
        if self._fence:
            for _ in range(_WAITS):
                r = self._gl.glClientWaitSync(self._fence, _SYNC_FLUSH_COMMANDS, _WAIT_NS)
                if r in (_ALREADY_SIGNALED, _CONDITION_SATISFIED):
                    break
                if r != _TIMEOUT_EXPIRED:
                    raise RuntimeError(f"glClientWaitSync failed ({r:#x}): the GL context is lost")
            else:
                raise RuntimeError(f"the GPU did not finish the work before a buffer read in {_WAITS} s")
            self._gl.glDeleteSync(self._fence)
            self._fence = None

    def release(self) -> None:
        if self._ptr:
            if self._fence:
                self._gl.glDeleteSync(self._fence)
            self._gl.glUnmapNamedBuffer(self.glo)
            self._gl.glDeleteBuffers(1, ctypes.byref(_u(self.glo)))
            self._ptr = self._fence = None
