"""Motion models for initialisation: the constant-velocity exposure path."""

from __future__ import annotations

import jax.numpy as jnp

from ..geometry import quaternion as quat
from ..geometry.pose import Pose
from ..geometry.trajectory import ExposureTrajectory

__all__ = ["pose_power", "exposure_from_velocity", "constant_velocity_guess"]


def pose_power(T: Pose, alpha: float) -> Pose:
    """T^α with the same decomposition as Eqs. 43-44: rotation exp(α log q), translation α t."""
    return Pose(quat.exp(alpha * quat.log(T.q)), alpha * T.t)


def exposure_from_velocity(V: Pose, frame_dt: float, exposure: float) -> ExposureTrajectory:
    """Exposure path of a frame about its own mid-exposure pose, (T_mid_start, T_mid_end), when the
    camera moves by ``V`` (body frame) every ``frame_dt`` seconds and the exposure lasts ``exposure``
    seconds: V^(-e/2dt) and V^(+e/2dt), interpolated as in Eqs. 43-44."""
    half = 0.5 * exposure / frame_dt
    return ExposureTrajectory(pose_power(V, -half), pose_power(V, half))


def constant_velocity_guess(
    T_world_ref: Pose, T_world_prev: Pose, T_world_last: Pose, frame_dt: float, exposure: float, gap: float | None = None
) -> ExposureTrajectory:
    """Exposure path of the next frame relative to the keyframe, assuming the motion from the
    previous to the last frame (mid-exposure poses ``T_world_*``, ``frame_dt`` apart) continues for
    ``gap`` seconds (default ``frame_dt``) and the exposure lasts ``exposure`` seconds."""
    gap = frame_dt if gap is None else gap
    V = T_world_prev.inverse().compose(T_world_last)  # motion over one frame interval (body frame)
    mid = T_world_last.compose(pose_power(V, gap / frame_dt))
    about_mid = exposure_from_velocity(V, frame_dt, exposure)
    start, end = mid.compose(about_mid.start), mid.compose(about_mid.end)
    ref_inv = T_world_ref.inverse()
    return ExposureTrajectory(ref_inv.compose(start), ref_inv.compose(end))
