"""Geometry of the MBA-VO supplement: quaternions, poses, exposure trajectories, camera, transfer."""

from . import quaternion
from .camera import PinholeCamera
from .pose import Pose
from .spline import ExposurePath, SplineTrajectory, as_trajectory
from .trajectory import ExposureTrajectory, RowClock, interpolate, readout_fraction, row_times, virtual_poses, virtual_times
from .transfer import plane_point, plane_transfer

__all__ = [
    "quaternion",
    "PinholeCamera",
    "Pose",
    "ExposureTrajectory",
    "SplineTrajectory",
    "ExposurePath",
    "as_trajectory",
    "interpolate",
    "virtual_poses",
    "virtual_times",
    "row_times",
    "readout_fraction",
    "RowClock",
    "plane_point",
    "plane_transfer",
]
