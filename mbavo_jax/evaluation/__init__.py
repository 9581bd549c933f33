"""Trajectory evaluation: association, Umeyama alignment, APE/RPE, frame drops, exposure-path error (per frame and per row)."""

from .align import umeyama
from .associate import associate, interpolate_poses
from .metrics import (aligned_positions, ape, exposure_path_error, exposure_path_lengths, frame_drop_rate, global_shutter_rows, row_fractions,
                      row_path_error, rpe, statistics)
from .poses import pose_matrices, slerp
from .runs import evaluate_run

__all__ = [
    "associate",
    "interpolate_poses",
    "umeyama",
    "ape",
    "rpe",
    "aligned_positions",
    "statistics",
    "frame_drop_rate",
    "exposure_path_error",
    "exposure_path_lengths",
    "row_path_error",
    "row_fractions",
    "global_shutter_rows",
    "evaluate_run",
    "pose_matrices",
    "slerp",
]
