"""The suite's errors: every failure a user can cause is a :class:`DMRTError`, which the ``dmrt``
command prints as one line (``dmrt: error: <message>``) and answers with exit status 2."""

from __future__ import annotations

from pathlib import Path


class DMRTError(Exception):
    """Base of every user-facing error; ``str(err)`` is one line that says what to fix."""


class InputError(DMRTError, ValueError):
    """Malformed or inconsistent input.

    ``str(err)`` reads ``"<path>: <what is wrong>"`` so a user can go straight to the file.
    """

    def __init__(self, path, message: str):
        self.path = Path(path) if path is not None else None
        self.message = message
        super().__init__(f"{self.path}: {message}" if self.path is not None else message)

    def __reduce__(self):  # picklable (raised in a Dask task, re-raised in the client)
        if type(self).__init__ is not InputError.__init__:
            return super().__reduce__()  # a subclass with its own arguments
        return type(self), (self.path, self.message)


class ConfigError(DMRTError, ValueError):
    """An option out of range or of an unknown choice; the message names the option
    (``--layers: must be >= 1, not 0``)."""

    def __init__(self, option: str, message: str):
        self.option, self.message = option, message
        super().__init__(f"--{option.replace('_', '-')}: {message}")

    def __reduce__(self):  # picklable (raised in a Dask task, re-raised in the client)
        if type(self).__init__ is not ConfigError.__init__:
            return super().__reduce__()  # a subclass with its own arguments
        return type(self), (self.option, self.message)


class MissingDependencyError(DMRTError, ImportError):
    """An optional dependency is not installed; the message says which extra brings it."""

    def __init__(self, module: str, purpose: str, extra: str):
        # the suite is installed from its checkout (setup.sh), not from a package index
        super().__init__(f"{purpose} needs the Python package '{module}', which is not installed: "
                         f"pip install -e '.[{extra}]' in the suite's checkout")


def require(module: str, purpose: str, extra: str):
    """Import ``module`` or raise :class:`MissingDependencyError` naming ``extra``."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise MissingDependencyError(module, purpose, extra) from None
