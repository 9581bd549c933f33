"""The methods of ``mbavo bench odometry`` (JAX-free, so the command line can list and check them)."""

from __future__ import annotations

from .errors import MbavoError

__all__ = ["ODOMETRY_METHODS", "check_methods", "parse_methods"]

ODOMETRY_METHODS = ("ours_n64", "ours_n1", "ours_adaptive", "ours_n64_depth", "ours_n1_depth", "open3d", "open3d_color", "opencv")


def check_methods(methods) -> None:
    """Raise MbavoError naming the unknown methods (or an empty selection)."""
    unknown = sorted(set(methods) - set(ODOMETRY_METHODS))
    if unknown or not methods:
        raise MbavoError(f"unknown benchmark method(s) {', '.join(unknown) or '(none left)'}; choose from {', '.join(ODOMETRY_METHODS)}")


def parse_methods(text: str, no_peers: bool = False) -> list[str]:
    """The methods of a comma-separated list ('' = all), peers dropped with ``no_peers``; checked."""
    methods = [m.strip() for m in text.split(",") if m.strip()] if text else list(ODOMETRY_METHODS)
    if no_peers:
        methods = [m for m in methods if m.startswith("ours_")]
    check_methods(methods)
    return methods
