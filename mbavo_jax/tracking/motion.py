"""Motion models for initialisation: the constant-velocity exposure path and DSO-style hypotheses."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..geometry import quaternion as quat
from ..geometry.pose import Pose, compiled_on_host
from ..geometry.spline import SplineTrajectory
from ..geometry.trajectory import ExposureTrajectory

Path = ExposureTrajectory | SplineTrajectory

__all__ = ["pose_power", "exposure_from_velocity", "constant_velocity_guess", "motion_hypotheses"]


@compiled_on_host
def pose_power(T: Pose, alpha: float | Float[Array, ""]) -> Pose:
    """T^α with the same decomposition as Eqs. 43-44: rotation exp(α log q), translation α t."""
    alpha = jnp.asarray(alpha, T.q.dtype)
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


def motion_hypotheses(init: Path, rotation_deg: float = 2.0) -> list[tuple[str, Path]]:
    """DSO-style alternatives to the guess ``init``, named. Each moves its mid-exposure pose M — to
    the identity (zero motion), M^½ (half), M² (double) and M turned by ±``rotation_deg`` about each
    axis — and keeps the guess's blur (the path about M as in ``init``; straight or cubic)."""
    mid = init.middle()
    about_mid = init.about_middle()

    def around(m: Pose):
        return about_mid.seen_from(m)

    out = [("zero motion", around(Pose.identity())), ("half motion", around(pose_power(mid, 0.5))),
           ("double motion", around(pose_power(mid, 2.0)))]
    for axis in range(3):
        for sign in (1.0, -1.0):
            r = np.zeros(3, np.float32)
            r[axis] = sign * np.deg2rad(rotation_deg)
            turn = Pose(quat.exp(jnp.asarray(r)), jnp.zeros(3))
            out.append((f"rotation {'xyz'[axis]}{'+' if sign > 0 else '-'}", around(mid.compose(turn))))
    return out
