"""The exposure trajectory of a blurry frame (supplement §4, Eqs. 42-44).

A frame's exposure path is the pair (``T_ref_start``, ``T_ref_end``): the poses of the camera at the
start and end of the exposure in the reference (keyframe) frame. Virtual pose i of n sits at
s = i / (n - 1) (s = 1/2 for n = 1, i.e. the classic blur-unaware mid-exposure pose).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from . import quaternion as quat
from .pose import Pose

__all__ = ["ExposureTrajectory", "interpolate", "virtual_times", "virtual_poses"]


class ExposureTrajectory(eqx.Module):
    """Start and end pose of one exposure, both ``T_ref_*`` (camera at that instant → reference)."""

    start: Pose
    end: Pose

    def at(self, s) -> Pose:
        return interpolate(self.start, self.end, s)

    def middle(self) -> Pose:
        return interpolate(self.start, self.end, 0.5)

    def about_middle(self) -> "ExposureTrajectory":
        """The same path relative to its own mid-exposure pose: (T_mid_start, T_mid_end)."""
        mid_inv = self.middle().inverse()
        return ExposureTrajectory(mid_inv.compose(self.start), mid_inv.compose(self.end))

    def normalized(self) -> "ExposureTrajectory":
        """Both quaternions rescaled to unit norm (updates drift by rounding; the analytic
        Jacobians of the supplement assume |q| = 1 exactly)."""
        return ExposureTrajectory(self.start.normalized(), self.end.normalized())

    def plus(self, delta: Float[Array, "12"]) -> "ExposureTrajectory":
        """Local update of both poses: ``delta = [Δr_start, Δt_start, Δr_end, Δt_end]``."""
        return ExposureTrajectory(self.start.plus(delta[:6]), self.end.plus(delta[6:12]))


def interpolate(start: Pose, end: Pose, s) -> Pose:
    """Eqs. 43-44: q_s = q_0 ⊗ exp(s · log(q_0⁻¹ ⊗ q_τ)), t_s = t_0 + s (t_τ − t_0).

    Note: this decomposition is *not* Eq. 42 (SE(3) exp/log couples translation to rotation); the
    paper adopts 43-44 "for efficiency" and so do we.
    """
    s = jnp.asarray(s, dtype=start.q.dtype)
    q_rel = quat.product(quat.inverse(start.q), end.q)  # Eq. 50
    r = s * quat.log(q_rel)  # Eq. 51
    q_s = quat.product(start.q, quat.exp(r))  # Eqs. 52-53
    t_s = (1.0 - s) * start.t + s * end.t  # Eq. 47
    return Pose(q_s, t_s)


def virtual_times(n: int, dtype=jnp.float32) -> Float[Array, "n"]:
    """s_i = i/(n-1), i = 0..n-1; a single virtual frame sits at mid-exposure."""
    if n < 1:
        raise ValueError(f"the number of virtual frames must be >= 1, got {n}")
    if n == 1:
        return jnp.full((1,), 0.5, dtype=dtype)
    return jnp.linspace(0.0, 1.0, n, dtype=dtype)


def virtual_poses(traj: ExposureTrajectory, n: int) -> Pose:
    """The n virtual poses ``T_ref_i`` along the exposure, as a batched Pose (leading axis n)."""
    s = virtual_times(n, traj.start.q.dtype)
    return jax.vmap(lambda si: interpolate(traj.start, traj.end, si))(s)
