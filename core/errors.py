"""Exception types whose messages are shown to the user as one line (no traceback) by the CLI."""

from __future__ import annotations

__all__ = ["InputError", "DatasetError"]


class InputError(ValueError):
    """Bad user input (file, folder, config, intrinsics ...). The message names the culprit and the problem."""


class DatasetError(InputError):
    """A sequence that cannot be read: missing folder or file, corrupt image, unknown layout, ..."""

