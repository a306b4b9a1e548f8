"""Error types shared by every module.

`InputError` is the one error a user is meant to see: bad input (a missing workspace, a corrupt
image, an invalid config value...). The CLI prints its message as one line and exits with code 2;
everything else is a bug and keeps its traceback.
"""
from __future__ import annotations


class InputError(Exception):
    """Bad user input. The message names the file or field at fault, in one line."""

    exit_code = 2


class ConfigError(InputError):
    """An invalid config value: names `stage.field` and says what is allowed."""

    def __init__(self, field: str, message: str):
        super().__init__(f"invalid config {field}: {message}")
        self.field = field
