"""Errors a user can act on. The CLI prints them as one line and exits 1."""

from __future__ import annotations

__all__ = ["MbavoError", "DataError", "ConfigError", "FrameIndexError", "ArgumentError"]


class MbavoError(Exception):
    """Base class of the errors the CLI reports as ``mbavo: error: <message>``."""


class DataError(MbavoError):
    """A missing, malformed or inconsistent input file. The message names the file (and line)."""

    def __init__(self, path, message: str, line: int | None = None):
        where = f"{path}:{line}" if line is not None else f"{path}"
        super().__init__(f"{where}: {message}")
        self.path = str(path)
        self.line = line


class ConfigError(MbavoError, ValueError):
    """An unknown or invalid configuration key or value (also a ValueError: a bad argument)."""


class FrameIndexError(MbavoError, IndexError):
    """A frame index outside a sequence (also an IndexError, as for a list)."""


class ArgumentError(MbavoError, ValueError):
    """A Python API call given something it cannot use (e.g. no image where an image is needed)."""
