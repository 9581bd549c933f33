"""The supplement's hand-derived Jacobians (as printed, and corrected) and their cross-validation."""

from . import jacobians
from .crossval import GroupResult, cross_validate, format_table

__all__ = ["jacobians", "cross_validate", "format_table", "GroupResult"]
