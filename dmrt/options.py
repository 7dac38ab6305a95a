"""Configuration fields declared once: a stage's configuration is one dataclass whose fields carry
their help text, choices (``Literal`` types) and bounds. The ``dmrt`` command turns every field into
``--field-name`` with that help (``dmrt.app.args.add_config_args``), and :func:`validate` turns a bad
value into a :class:`~dmrt.errors.ConfigError` that names the option.

    @dataclass
    class RenderConfig:
        layers: int = option(5, "Number of label layers k.", minimum=1, level="common")
        method: Literal["kbuffer", "compute"] = option("kbuffer", "Visibility stage.")

        def __post_init__(self):
            validate(self)
"""

from __future__ import annotations

import dataclasses
import typing

from dmrt.errors import ConfigError


Level = typing.Literal["common", "tuning"]


def option(default, help: str, *, minimum=None, maximum=None, level: Level = "tuning"):
    """A dataclass field with its ``--help`` text, inclusive bounds (numbers, or each element of
    a tuple; None = unbounded) and ``level``: ``"common"`` for an option most users need, listed
    first in ``--help``; ``"tuning"`` for a knob, listed in a group of its own after them."""
    if level not in typing.get_args(Level):
        raise ValueError(f"option level must be one of {typing.get_args(Level)}, not {level!r}")
    return dataclasses.field(default=default, metadata={"help": help, "min": minimum, "max": maximum,
                                                        "level": level})


def choices(tp) -> tuple | None:
    """The allowed values of a ``Literal[...]`` (or ``Literal[...] | None``) type, else None."""
    if typing.get_origin(tp) is typing.Literal:
        return typing.get_args(tp)
    for arg in typing.get_args(tp):
        if typing.get_origin(arg) is typing.Literal:
            return typing.get_args(arg)
    return None


def validate(config) -> None:
    """Check every field of dataclass instance ``config`` against its ``Literal`` choices and its
    bounds; raises :class:`ConfigError` naming the first bad option."""
    hints = typing.get_type_hints(type(config))
    for f in dataclasses.fields(config):
        value = getattr(config, f.name)
        if value is None:
            continue
        allowed = choices(hints[f.name])
        if allowed is not None and value not in allowed:
            raise ConfigError(f.name, f"must be one of {', '.join(map(repr, allowed))}, not {value!r}")
        lo, hi = f.metadata.get("min"), f.metadata.get("max")
        for v in (value if isinstance(value, tuple) else (value,)):
            if isinstance(v, (int, float)) and not isinstance(v, bool):
                if lo is not None and v < lo:
                    raise ConfigError(f.name, f"must be >= {lo}, not {value}")
                if hi is not None and v > hi:
                    raise ConfigError(f.name, f"must be <= {hi}, not {value}")
