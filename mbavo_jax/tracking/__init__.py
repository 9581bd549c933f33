"""The blur-aware tracker (points, residuals with two Jacobian paths, coarse-to-fine LM)."""

from .level import compiled_programs
from .motion import constant_velocity_guess, exposure_from_velocity, motion_hypotheses, pose_power
from .points import PATTERN, LevelPoints, select_points
from .tracker import Keyframe, Status, TrackerConfig, TrackResult, choose_n, predicted_blur_px, track

__all__ = [
    "PATTERN",
    "LevelPoints",
    "select_points",
    "Keyframe",
    "Status",
    "TrackerConfig",
    "TrackResult",
    "track",
    "choose_n",
    "predicted_blur_px",
    "motion_hypotheses",
    "constant_velocity_guess",
    "exposure_from_velocity",
    "pose_power",
    "compiled_programs",
]
