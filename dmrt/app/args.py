"""Command-line arguments: dataclass fields as options (each field of a configuration dataclass
becomes ``--field-name`` with the help, choices and bounds it declares) and the checks the ``dmrt``
command makes before any work, so that bad input fails at once and leaves nothing behind."""

from __future__ import annotations

import argparse
import dataclasses
import typing
from pathlib import Path

from dmrt.errors import ConfigError, InputError


# ----------------------------------------------------------------------------------------------
# Dataclass <-> argparse
# ----------------------------------------------------------------------------------------------
def add_config_args(parser: argparse.ArgumentParser, cls, skip=(), tuning=None, common=None) -> None:
    """Add one ``--option`` per field of dataclass ``cls``, with the help text, choices and default
    the field declares (:func:`dmrt.options.option`); defaults stay the dataclass's own.

    Parameters
    ----------
    parser : the (sub)command's parser.
    cls : the configuration dataclass.
    skip : field names the command gives options of its own.
    tuning : the argument group (``parser.add_argument_group(title)``) that takes the fields of
        level ``"tuning"``; ``--help`` lists groups in the order they were made, so make it after
        the command's own options. None: ``parser``'s main options.
    common : where the fields of level ``"common"`` go (an argument group; default ``parser``'s
        main options, listed first).
    """
    from dmrt.options import choices

    hints = typing.get_type_hints(cls)
    defaults = cls()
    groups = {"common": common or parser, "tuning": tuning or parser}
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        group = groups[f.metadata.get("level", "tuning")]
        opt = "--" + f.name.replace("_", "-")
        tp = hints[f.name]
        default = getattr(defaults, f.name)
        # argparse formats help with %: a literal % must be doubled
        text = (f.metadata.get("help", "") + ("" if default is None else f" (default: {default})")).replace("%", "%%")
        origin = typing.get_origin(tp)
        allowed = choices(tp)
        if tp is bool:
            group.add_argument(opt, dest=f.name, default=None, action=argparse.BooleanOptionalAction, help=text)
        elif allowed is not None:
            group.add_argument(opt, dest=f.name, default=None, choices=allowed, help=text)
        elif origin is tuple:
            args = typing.get_args(tp)
            group.add_argument(opt, dest=f.name, default=None, nargs=len(args), type=args[0],
                               metavar=f.name.upper(), help=text)
        else:
            base = next((a for a in typing.get_args(tp) if a is not type(None)), tp) if origin else tp
            group.add_argument(opt, dest=f.name, default=None, type=base, help=text)


def config_from_args(cls, args: argparse.Namespace, base=None):
    """An instance of ``cls`` from ``base`` (or the defaults) with the options the user gave."""
    base = base if base is not None else cls()
    given = {f.name: getattr(args, f.name) for f in dataclasses.fields(cls)
             if getattr(args, f.name, None) is not None}
    given = {k: tuple(v) if isinstance(v, list) else v for k, v in given.items()}
    return dataclasses.replace(base, **given)


# ----------------------------------------------------------------------------------------------
# Checks made before any work: bad input fails at once and leaves nothing behind
# ----------------------------------------------------------------------------------------------
FRAME_SUFFIXES = (".png", ".exr")
# Reference frames are ray cast on the CPU: no GL limit applies, but frames are compared with GPU
# frames, whose sides GL 4.5 guarantees up to 16384 pixels; larger only exhausts memory.
REFERENCE_MAX_SIDE = 16384


def check_positive(args, *names) -> None:
    """:class:`ConfigError` naming the first of ``--<names>`` that was given and is below 1."""
    for name in names:
        v = getattr(args, name, None)
        if v is not None and v < 1:
            raise ConfigError(name, f"must be >= 1, not {v}")


def check_output(path, option: str = "out", suffixes=None, folder: bool = False, what: str = "output") -> Path:
    """Refuse, before any work, an output that cannot be written as asked.

    Parameters
    ----------
    path : the file (or with ``folder``, the folder) the command will write.
    option : the option that named it, for the message.
    suffixes : the file suffixes allowed (lower case), or None.
    folder : the output is a folder, not a file.
    what : what it is (``"frame file"``), for the message.

    Raises
    ------
    ConfigError
        A suffix not in ``suffixes``; a folder where a file is asked for, or the reverse.
    InputError
        A parent of ``path`` is a file, or the nearest existing parent is not writable.
    """
    import errno
    import tempfile

    path = Path(path)
    if folder and path.exists() and not path.is_dir():
        raise ConfigError(option, f"{path} is a file; --{option} names a folder here")
    if not folder and path.is_dir():
        raise ConfigError(option, f"{path} is a folder; --{option} names a {what}")
    if suffixes is not None and path.suffix.lower() not in suffixes:
        raise ConfigError(option, f"{path}: a {what} ends in {' or '.join(suffixes)}, "
                                  + (f"not {path.suffix!r}" if path.suffix else "and this name has no suffix"))
    for parent in path.absolute().parents:
        if parent.exists():
            if not parent.is_dir():
                raise InputError(parent, f"is a file, so --{option} {path} cannot be written in it")
            # a file made and deleted at once: permission bits do not tell (root passes os.access
            # in /proc and on read-only mounts)
            try:
                tempfile.TemporaryFile(dir=parent).close()
            except OSError as exc:  # the reason where it says more than "not writable" (read-only, full)
                reason = f": {exc.strerror}" if exc.errno in (errno.EROFS, errno.ENOSPC, errno.EDQUOT) else ""
                raise InputError(parent, f"folder not writable (for --{option} {path}){reason}") from None
            break
    return path


# Per-pixel buffers are bound whole, and addressed with 32-bit signed byte offsets: one of 2^31
# bytes or more cannot be used, whatever the GPU's memory. Measured on Mesa llvmpipe, which reports
# GL_MAX_SHADER_STORAGE_BLOCK_SIZE 128 MiB yet renders larger buffers correctly: a 4096x2731 frame
# with 47 k-buffer slots (2.10e9 bytes) runs, with 48 (2.15e9 bytes) the process segfaults.
# A driver that reports a block size above 2^31 - 1 is believed.
MAX_BUFFER_BYTES = (1 << 31) - 1


def max_frame_side(ctx=None) -> int:
    """The largest frame width or height this GL context renders, pixels: the smallest of
    GL_MAX_TEXTURE_SIZE, GL_MAX_VIEWPORT_DIMS and the framebuffer and renderbuffer limits."""
    if ctx is None:
        from dmrt.gl import get_context

        ctx = get_context()
    info = ctx.info
    return min(int(info["GL_MAX_TEXTURE_SIZE"]), *(int(v) for v in info["GL_MAX_VIEWPORT_DIMS"]),
               *(int(info.get(k, 1 << 30)) for k in ("GL_MAX_FRAMEBUFFER_WIDTH", "GL_MAX_FRAMEBUFFER_HEIGHT",
                                                      "GL_MAX_RENDERBUFFER_SIZE")))


def check_frame_size(width: int, height: int, bytes_per_pixel: int = 4, what: str = "", ctx=None,
                     prefer: str = "width") -> None:
    """:class:`ConfigError` naming ``--width`` or ``--height`` when a ``width`` x ``height`` frame
    is more than the GPU can render, before anything is allocated: a side above
    :func:`max_frame_side`, or a per-pixel buffer of ``bytes_per_pixel`` (the largest record, e.g.
    ``4 * layers`` for DMRT's layer buffers; ``what`` says whose, for the message) larger than
    :data:`MAX_BUFFER_BYTES` (or the driver's larger GL_MAX_SHADER_STORAGE_BLOCK_SIZE).
    ``prefer`` is the option named when both sides are too large (the one the user gave)."""
    if ctx is None:
        from dmrt.gl import get_context

        ctx = get_context()
    side = max_frame_side(ctx)
    sides = (("width", width), ("height", height))
    for option, v in sides if prefer == "width" else sides[::-1]:
        if v > side:
            raise ConfigError(option, f"a {width}x{height} frame is larger than this GPU renders: at most "
                                      f"{side} pixels a side (GL_MAX_TEXTURE_SIZE, GL_MAX_VIEWPORT_DIMS)")
    limit = max(MAX_BUFFER_BYTES, int(ctx.info.get("GL_MAX_SHADER_STORAGE_BLOCK_SIZE", 0)))
    need = width * height * bytes_per_pixel
    if need > limit:
        raise ConfigError(prefer, f"a {width}x{height} frame{what} needs a {need / 2**30:.1f} GiB per-pixel "
                                   f"buffer; GPU buffers are addressed up to {limit / 2**30:.1f} GiB: give a "
                                   f"smaller --width/--height")


def check_reference_size(width: int, height: int) -> None:
    """:class:`ConfigError` for a reference frame above :data:`REFERENCE_MAX_SIDE` a side."""
    for option, v in (("width", width), ("height", height)):
        if v > REFERENCE_MAX_SIDE:
            raise ConfigError(option, f"a {width}x{height} reference frame: at most {REFERENCE_MAX_SIDE} "
                                      f"pixels a side")


def check_render_size(width: int, height: int, args) -> None:
    """:func:`check_frame_size` for what ``dmrt render``'s options ask of the GPU: DMRT's k label
    layers (and with ``--visibility kbuffer`` its fragment slots) per pixel, or DMT's hit records."""
    from dmrt.gl.abi import HIT_DTYPE

    prefer = "height" if args.height is not None and args.width is None else "width"
    if args.renderer == "dmt":  # hit records, and RGBA float32 frame textures
        return check_frame_size(width, height, max(HIT_DTYPE.itemsize, 16), prefer=prefer)
    from dmrt.runtime.renderer import RenderConfig

    config = config_from_args(RenderConfig, args)
    if args.visibility:
        config = dataclasses.replace(config, method=args.visibility)
    per_pixel, what = 4 * config.layers, f" with {config.layers} layers"
    if config.method == "kbuffer":
        slots = config.kbuffer_slots or 6 * config.layers + 2
        per_pixel, what = max(per_pixel, 4 * slots), f" with {slots} k-buffer slots"
    check_frame_size(width, height, max(per_pixel, HIT_DTYPE.itemsize, 8), what, prefer=prefer)
