"""The one exception type for bad input: it always names the file and what is wrong with it."""

from __future__ import annotations

from pathlib import Path


class InputError(ValueError):
    """Malformed or inconsistent input.

    ``str(err)`` reads ``"<path>: <what is wrong>"`` so a user can go straight to the file.
    """

    def __init__(self, path, message: str):
        self.path = Path(path) if path is not None else None
        self.message = message
        super().__init__(f"{self.path}: {message}" if self.path is not None else message)
