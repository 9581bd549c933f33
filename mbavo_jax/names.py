"""Names that become folder names inside an output folder (a sweep's sequences and configurations):
one path component of a safe character set, so that no name reaches outside the folder it is
joined to (no ``/``, no ``.`` or ``..``, no hidden name). JAX-free."""

from __future__ import annotations

import re

from .errors import ConfigError

__all__ = ["NAME_RULE", "MAX_NAME", "is_safe_name", "check_name"]

SAFE = re.compile(r"[A-Za-z0-9_=+-][A-Za-z0-9._=+-]*")  # matched whole: never '.', '..', '/', a hidden name
MAX_NAME = 200  # characters: a folder name fits every filesystem's limit (255 bytes)
NAME_RULE = "letters, digits and _ . = + -, not starting with '.'"


def is_safe_name(name) -> bool:
    """Whether ``name`` can be a folder name inside an output folder (see the module docstring)."""
    return isinstance(name, str) and len(name) <= MAX_NAME and SAFE.fullmatch(name) is not None


def check_name(name, where: str, what: str) -> str:
    """``name`` when :func:`is_safe_name`, else a one-line ConfigError naming ``where`` (e.g. the
    sweep file) and the name."""
    if not is_safe_name(name):
        size = f", at most {MAX_NAME} characters" if isinstance(name, str) and len(name) > MAX_NAME else ""
        shown = repr(name) if len(repr(name)) <= 80 else repr(name)[:77] + "..."
        raise ConfigError(f"{where}: {what} name {shown} cannot be a folder name (use {NAME_RULE}{size}; give name:)")
    return name
