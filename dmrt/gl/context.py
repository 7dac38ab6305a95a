"""Headless OpenGL 4.3+ contexts over EGL (Mesa llvmpipe in CI, the NVIDIA driver on the GPU machines).

Everything GL in the suite runs in one standalone context per process (:func:`get_context`); moderngl
objects are tied to the context that made them, so sharing one avoids accidental cross-context use.
"""

from __future__ import annotations

import moderngl

from dmrt.errors import ConfigError

_INSTALL_HINT = (
    "a headless OpenGL {major}.{minor} context over EGL is required. On Debian/Ubuntu install the "
    "system packages 'libegl1 libegl-mesa0 libgl1-mesa-dri' (Mesa llvmpipe, CPU) or an NVIDIA driver "
    "with its EGL vendor library; if the NVIDIA driver is present but not found, set "
    "__EGL_VENDOR_LIBRARY_FILENAMES=/usr/share/glvnd/egl_vendor.d/10_nvidia.json "
    "(or the driver's own copy of that file)."
)

_SOFTWARE_RENDERERS = ("llvmpipe", "softpipe", "swrast", "lavapipe", "software rasterizer")

_shared: moderngl.Context | None = None


def create_context(require: int = 430) -> moderngl.Context:
    """Create a new standalone (windowless) EGL context.

    Parameters
    ----------
    require : int
        Minimum OpenGL version times 100 (430 = 4.3: compute shaders, SSBOs, image atomics).

    Raises
    ------
    RuntimeError
        When EGL or a GL >= ``require`` driver is missing; the message names the packages to install.
    """
    hint = _INSTALL_HINT.format(major=require // 100, minor=require % 100 // 10)
    try:
        ctx = moderngl.create_standalone_context(backend="egl", require=require)
    except Exception as exc:  # glcontext raises plain Exceptions whose text varies by platform
        raise RuntimeError(f"cannot create an OpenGL context ({exc}): {hint}") from exc
    if ctx.version_code < require:  # some drivers hand out a lower version than requested
        version = ctx.info.get("GL_VERSION", "?")
        ctx.release()
        raise RuntimeError(f"OpenGL {version} is too old: {hint}")
    return ctx


def get_context(require: int = 430) -> moderngl.Context:
    """The process-wide shared context, created on first use (see :func:`create_context`)."""
    global _shared
    if _shared is None:
        _shared = create_context(require)
    elif _shared.version_code < require:
        raise RuntimeError(f"the shared context is GL {_shared.version_code}, {require} was requested")
    return _shared


def renderer_info(ctx: moderngl.Context) -> dict:
    """Describe the driver behind ``ctx``.

    Returns
    -------
    dict
        ``vendor``, ``renderer``, ``version`` (the driver's strings) and ``is_software`` (True for
        Mesa's CPU rasterizers, whose GPU timings are meaningless and which lack int64 atomics).
    """
    info = ctx.info
    renderer = str(info.get("GL_RENDERER", ""))
    return {
        "vendor": str(info.get("GL_VENDOR", "")),
        "renderer": renderer,
        "version": str(info.get("GL_VERSION", "")),
        "is_software": any(s in renderer.lower() for s in _SOFTWARE_RENDERERS),
    }


# glGetIntegerv names of the free video memory, KiB: NVIDIA's (GL_NVX_gpu_memory_info's
# CURRENT_AVAILABLE_VIDMEM) and AMD/Mesa's (GL_ATI_meminfo's TEXTURE_FREE_MEMORY: 4 integers, the
# first the pool's free total)
_FREE_MEMORY = {"GL_NVX_gpu_memory_info": (0x9049, 1), "GL_ATI_meminfo": (0x87FC, 4)}


def free_memory_mb(ctx: moderngl.Context) -> float | None:
    """GPU memory free now, MiB, where the driver tells it (``GL_NVX_gpu_memory_info`` or
    ``GL_ATI_meminfo``; ``ctx`` current, no GL error pending: the read clears the flag); None
    elsewhere (Mesa's CPU rasterizers among them).
    A texture's memory may count only once it is used: on an H200 (driver 580) the figure stayed
    143,140 MiB before and after a 4 GiB texture array with one layer written."""
    import ctypes

    from dmrt.gl.mapped import entry_points

    for extension, (name, count) in _FREE_MEMORY.items():
        if extension in ctx.extensions:
            # advisory: a driver that lists the extension but refuses the query (or a loader
            # without the entry point) gives None, not an error; call it with no GL error pending
            try:
                get = entry_points({"glGetIntegerv": (None, [ctypes.c_uint, ctypes.POINTER(ctypes.c_int)])},
                                   f"{extension} is read with glGetIntegerv").glGetIntegerv
            except RuntimeError:
                return None
            values = (ctypes.c_int * count)()
            get(name, values)
            if ctx.error != "GL_NO_ERROR":
                return None
            return values[0] / 1024.0 if values[0] > 0 else None
    return None


def check_gl(ctx: moderngl.Context, what: str) -> None:
    """Raise if the GL error flag is set: an invalid call, exhausted GPU memory or a lost context
    (a driver reset after a dispatch ran too long) leave buffers stale, and a frame read back from
    them would look like a result.

    Raises
    ------
    RuntimeError
        Naming ``what`` and the GL error (``GL_OUT_OF_MEMORY``, ``GL_CONTEXT_LOST``, ...).
    """
    error = ctx.error  # glGetError: a flag the driver keeps, no wait for the GPU
    if error != "GL_NO_ERROR":
        raise RuntimeError(f"OpenGL error {error} while {what}: the GPU results are invalid "
                           "(out of GPU memory, or a lost context after a pass that ran too long?)")


def check_fits(ctx: moderngl.Context, option: str, what: str) -> None:
    """After allocating (and filling) ``what`` on the GPU: the driver sets GL_OUT_OF_MEMORY when it
    does not fit, and every later frame would be invalid; say so now, naming the budget ``option``
    that sets its size. (The flag is cleared by the read: call :func:`check_gl` before allocating,
    so that an earlier error is not blamed on this.)

    Raises
    ------
    ConfigError
        Naming ``option``, on GL_OUT_OF_MEMORY.
    RuntimeError
        On any other GL error (:func:`check_gl`).
    """
    error = ctx.error
    if error == "GL_OUT_OF_MEMORY":
        raise ConfigError(option, f"{what}: more than this GPU's memory holds (GL_OUT_OF_MEMORY); set a "
                                  "smaller budget")
    if error != "GL_NO_ERROR":
        raise RuntimeError(f"OpenGL error {error} while allocating {what}")
