"""Geometry of the MBA-VO supplement: quaternions, poses, exposure trajectories, camera, transfer."""

from . import quaternion
from .camera import PinholeCamera
from .pose import Pose
from .trajectory import ExposureTrajectory, interpolate, virtual_poses, virtual_times
from .transfer import plane_point, plane_transfer

__all__ = [
    "quaternion",
    "PinholeCamera",
    "Pose",
    "ExposureTrajectory",
    "interpolate",
    "virtual_poses",
    "virtual_times",
    "plane_point",
    "plane_transfer",
]
