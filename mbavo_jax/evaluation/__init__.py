"""Trajectory evaluation: association, Umeyama alignment, APE/RPE, frame drops, exposure-path error."""

from .align import umeyama
from .associate import associate, interpolate_poses
from .metrics import ape, exposure_path_error, frame_drop_rate, rpe, statistics

__all__ = [
    "associate",
    "interpolate_poses",
    "umeyama",
    "ape",
    "rpe",
    "statistics",
    "frame_drop_rate",
    "exposure_path_error",
]
