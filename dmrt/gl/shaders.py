"""Load GLSL programs: one ``shaders/<name>.glsl`` file per program, stages split by preprocessor guards.

A program file holds every stage of one program, each guarded the moderngl-window way::

    #if defined VERTEX_SHADER
    ...
    #elif defined FRAGMENT_SHADER
    ...
    #endif

The loader compiles the same text once per stage with that stage's macro defined. It also resolves
``#include "file.glsl"`` (relative to ``shaders/``, recursively, each file at most once per program),
puts ``#version 430`` first (or the file's own ``#version`` line) followed by ``#define KEY VALUE`` for
each entry of the GPU/Python ABI (:mod:`dmrt.gl.abi`: binding points, sentinels, sizes) and of ``defines``, and emits ``#line`` directives so that the driver's error positions read
``<source-string number>:<line>``; compile errors name the ``.glsl`` file and list those numbers.
A file that mentions ``COMPUTE_SHADER`` becomes a :class:`moderngl.ComputeShader`, any other a
:class:`moderngl.Program` (vertex + fragment, plus geometry when the file has that stage).
"""

from __future__ import annotations

import contextlib
import re
import weakref
from pathlib import Path

import moderngl

from dmrt.gl import abi
from shaders import SHADER_DIR

DEFAULT_VERSION = "#version 430"
STAGES = ("VERTEX_SHADER", "GEOMETRY_SHADER", "FRAGMENT_SHADER", "COMPUTE_SHADER")

_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"\s*(//.*)?$')
_VERSION = re.compile(r"^\s*#\s*version\b")
# a stage exists when a preprocessor conditional tests its macro (comments do not count)
_STAGE_TEST = re.compile(r"^\s*#\s*(?:if|elif|ifdef|ifndef)\b.*$", re.M)
_STAGE_NAME = re.compile(r"\b(VERTEX_SHADER|GEOMETRY_SHADER|FRAGMENT_SHADER|COMPUTE_SHADER)\b")

# ctx -> {(name, defines): program}; weak so that releasing a context frees its programs' cache entry.
_cache: "weakref.WeakKeyDictionary[moderngl.Context, dict]" = weakref.WeakKeyDictionary()
_recorders: list[list] = []  # recording_programs blocks now open


class ShaderError(RuntimeError):
    """A GLSL program failed to load, compile or link; the message names the ``.glsl`` file."""


def _path(name: str) -> Path:
    return SHADER_DIR / (name if name.endswith(".glsl") else f"{name}.glsl")


def resolve_source(name: str) -> tuple[str | None, str, list[Path]]:
    """Read ``shaders/<name>.glsl`` with its includes inlined.

    Returns
    -------
    version : str or None
        The top-level file's own ``#version`` line, if it has one.
    body : str
        The program text, includes inlined, with ``#line <n> <file number>`` directives.
    files : list of Path
        The files in source-string-number order (``files[0]`` is the program file).
    """
    files: list[Path] = []
    version: list[str] = []

    def expand(path: Path, parent: Path | None, parent_line: int) -> list[str]:
        if path in files:  # include-once: a second #include of the same file expands to nothing
            return []
        if not path.is_file():
            where = f"{parent.name}:{parent_line}: " if parent else ""
            raise ShaderError(f"{path}: {where}shader file not found")
        files.append(path)
        number = len(files) - 1
        out = [f"#line 1 {number}"]
        for lineno, line in enumerate(path.read_text().splitlines(), start=1):
            m = _INCLUDE.match(line)
            if m:
                out += expand((SHADER_DIR / m.group(1)).resolve(), path, lineno)
                out.append(f"#line {lineno + 1} {number}")  # back in this file, after the include
            elif _VERSION.match(line):
                if parent is not None:
                    raise ShaderError(f"{path}:{lineno}: an included file must not have a #version line")
                version.append(line.strip())
                out.append("")  # keep line numbers aligned
            else:
                out.append(line)
        return out

    lines = expand(_path(name).resolve(), None, 0)
    return (version[0] if version else None), "\n".join(lines) + "\n", files


def _format_define(key: str, value) -> str:
    if isinstance(value, bool):
        text = "1" if value else "0"
    elif isinstance(value, int):
        text = str(value)
    elif isinstance(value, float):
        text = repr(value)
        if text in ("inf", "-inf", "nan"):
            raise ShaderError(f"#define {key}: {value} has no GLSL literal")
        if not any(c in text for c in ".e"):
            text += ".0"
    else:
        text = str(value)
    return f"#define {key} {text}"


def _build(name: str, defines: dict | None) -> tuple[dict[str, str], list[Path]]:
    version, body, files = resolve_source(name)
    found = {n for line in _STAGE_TEST.findall(body) for n in _STAGE_NAME.findall(line)}
    stages = ["COMPUTE_SHADER"] if "COMPUTE_SHADER" in found else sorted(found, key=STAGES.index)
    head = [version or DEFAULT_VERSION]
    head += [_format_define(k, v) for k, v in {**abi.DEFINES, **(defines or {})}.items()]
    sources = {s: "\n".join([head[0], f"#define {s} 1", *head[1:], body]) for s in stages}
    return sources, files


def stage_sources(name: str, defines: dict | None = None) -> dict[str, str]:
    """The complete source of each stage the program file has, keyed by stage macro name."""
    return _build(name, defines)[0]


def load_program(ctx: moderngl.Context, name: str, defines: dict | None = None):
    """Compile (or fetch from the per-context cache) the program in ``shaders/<name>.glsl``.

    Parameters
    ----------
    ctx : moderngl.Context
    name : str
        File stem under ``shaders/`` (``"splat_depth_compute"``); a trailing ``.glsl`` is accepted.
    defines : dict, optional
        ``{KEY: value}`` inserted as ``#define KEY value`` after the version line. Booleans become
        1/0; floats keep a decimal point so GLSL reads them as floats.

    Returns
    -------
    moderngl.ComputeShader or moderngl.Program
        Cached per ``(ctx, name, defines)``: callers must not ``release()`` it.

    Raises
    ------
    ShaderError
        Missing file or include, or a compile/link error; the message starts with the file's path.
    """
    for calls in _recorders:
        calls.append((name, dict(defines or {})))
    key = (str(SHADER_DIR), name, tuple(sorted((str(k), repr(v)) for k, v in (defines or {}).items())))
    programs = _cache.setdefault(ctx, {})
    if key in programs:
        return programs[key]
    sources, files = _build(name, defines)
    legend = ", ".join(f"{i} = {f.name}" for i, f in enumerate(files))
    if not sources or ("COMPUTE_SHADER" not in sources and "VERTEX_SHADER" not in sources):
        raise ShaderError(f"{files[0]}: no '#if defined VERTEX_SHADER' or COMPUTE_SHADER stage found")
    try:
        if "COMPUTE_SHADER" in sources:
            program = ctx.compute_shader(sources["COMPUTE_SHADER"])
        else:
            program = ctx.program(
                vertex_shader=sources["VERTEX_SHADER"],
                geometry_shader=sources.get("GEOMETRY_SHADER"),
                fragment_shader=sources.get("FRAGMENT_SHADER"),
            )
    except moderngl.Error as exc:
        raise ShaderError(
            f"{files[0]}: GLSL program {name!r} failed to compile or link "
            f"(source-string numbers in the log: {legend}):\n{exc}"
        ) from None
    programs[key] = program
    return program


@contextlib.contextmanager
def recording_programs():
    """Collect ``(name, defines)`` of every :func:`load_program` call made inside the block (cached
    or compiled), in call order: what a renderer builds, for tools that measure its programs
    (``bench/occupancy.py``)."""
    calls: list[tuple[str, dict]] = []
    _recorders.append(calls)
    try:
        yield calls
    finally:
        _recorders.remove(calls)


def set_uniforms(program, **values) -> None:
    """Set uniforms by name, skipping names the compiler optimised away (moderngl raises on those).

    Values are Python scalars/tuples, or numpy arrays written as raw bytes (floats as float32,
    integers as int32; a matrix must already be flattened column-major, e.g. ``R.T.ravel()``).
    A value equal to the one this function last set on the program is not written again: a
    program keeps its uniforms, and a DMRT frame sets ~100, most as the frame before did, each a
    GL call the CPU makes while a light frame's GPU waits for it. Set uniforms only through here.
    """
    last = program.__dict__.setdefault("_dmrt_uniforms", {})
    for name, value in values.items():
        if hasattr(value, "dtype"):
            value = value.astype("f4" if value.dtype.kind == "f" else "i4").tobytes()
        if name in last and last[name] == value:
            continue
        try:
            member = program[name]
        except KeyError:
            continue
        if isinstance(value, bytes):
            member.write(value)
        else:
            member.value = value
        last[name] = value
