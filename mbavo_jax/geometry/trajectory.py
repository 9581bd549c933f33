"""The exposure trajectory of a blurry frame (supplement §4, Eqs. 42-44).

A frame's exposure path is the pair (``T_ref_start``, ``T_ref_end``): the poses of the camera at the
start and end of the exposure in the reference (keyframe) frame. Virtual pose i of n sits at
s = i / (n - 1) (s = 1/2 for n = 1, i.e. the classic blur-unaware mid-exposure pose).

Rolling shutter: with exposure τ and readout R (first row's start to last row's start), row v of an
H-row frame is exposed over [t0 + v/(H-1)·R, t0 + v/(H-1)·R + τ]; the path spans the whole frame
time [t0, t0 + R + τ], and virtual frame i of row v sits at s(v, i) = ρ·v/(H-1) + (1-ρ)·s_i with the
readout fraction ρ = R/(R+τ) (:func:`row_times`). ρ = 0 is the global shutter.
"""

from __future__ import annotations

import typing

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from . import quaternion as quat
from .pose import Pose, compiled_on_host

__all__ = ["ExposureTrajectory", "interpolate", "virtual_times", "virtual_poses", "row_times", "readout_fraction", "RowClock"]


class ExposureTrajectory(eqx.Module):
    """Start and end pose of one exposure, both ``T_ref_*`` (camera at that instant → reference)."""

    start: Pose
    end: Pose
    dof: typing.ClassVar[int] = 12  # the tracker's unknowns: a local update of each pose

    def at(self, s) -> Pose:
        return interpolate(self.start, self.end, s)

    def middle(self) -> Pose:
        return interpolate(self.start, self.end, 0.5)

    def about_middle(self) -> "ExposureTrajectory":
        """The same path relative to its own mid-exposure pose: (T_mid_start, T_mid_end)."""
        mid_inv = self.middle().inverse()
        return ExposureTrajectory(mid_inv.compose(self.start), mid_inv.compose(self.end))

    def seen_from(self, T: Pose) -> "ExposureTrajectory":
        """T ∘ path: both poses composed on the left."""
        return ExposureTrajectory(T.compose(self.start), T.compose(self.end))

    def normalized(self) -> "ExposureTrajectory":
        """Both quaternions rescaled to unit norm (updates drift by rounding; the analytic
        Jacobians of the supplement assume |q| = 1 exactly)."""
        return ExposureTrajectory(self.start.normalized(), self.end.normalized())

    def plus(self, delta: Float[Array, "12"]) -> "ExposureTrajectory":
        """Local update of both poses: ``delta = [Δr_start, Δt_start, Δr_end, Δt_end]``."""
        return ExposureTrajectory(self.start.plus(delta[:6]), self.end.plus(delta[6:12]))

    def row_path(self, v, height, readout) -> "ExposureTrajectory":
        """Row v's own exposure (of an ``height``-row frame, readout fraction ρ = ``readout``): the
        poses at s = ρ·v/(H-1) (its start) and s + 1 - ρ (its end). Along Eqs. 43-44 the sub-path
        interpolates exactly as the whole path does between those times."""
        s0 = readout * jnp.asarray(v, self.start.q.dtype) / (jnp.asarray(height, self.start.q.dtype) - 1.0)
        return ExposureTrajectory(self.at(s0), self.at(s0 + 1.0 - readout))

    def middle_row_path(self, readout) -> "ExposureTrajectory":
        """The middle row's own exposure (:meth:`row_path` at v/(H-1) = ½): the blur a frame shows
        (the path itself for a concrete ρ = 0)."""
        if not isinstance(readout, jax.core.Tracer) and float(readout) == 0.0:
            return self
        return self.row_path(0.5, 2.0, readout)


@compiled_on_host
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


def row_times(n: int, rows: Float[Array, " R"], height, readout) -> Float[Array, "R n"]:
    """s(v, i) = ρ·v/(H-1) + (1-ρ)·s_i: the normalised times of the n virtual frames of each row v
    (continuous rows allowed) of an ``height``-row frame; ρ = ``readout`` (0: every row at s_i)."""
    s = virtual_times(n, rows.dtype)
    u = rows / (jnp.asarray(height, rows.dtype) - 1.0)
    return readout * u[:, None] + (1.0 - readout) * s[None, :]


def readout_fraction(readout_s: float, exposure_s: float) -> float:
    """ρ = R/(R+τ) for readout R and exposure τ (seconds): 0 without readout, 1 when τ = 0 < R."""
    readout_s, exposure_s = max(float(readout_s), 0.0), max(float(exposure_s), 0.0)
    return 0.0 if readout_s == 0.0 else readout_s / (readout_s + exposure_s)


class RowClock(eqx.Module):
    """When the rows of one pyramid level of a frame are exposed: ρ, the full-resolution height and
    the level's scale 2^l. Level row v covers full-resolution rows whose centre is v·2^l + (2^l-1)/2
    (2x2 box pyramid, pixel centres kept), so ρ means the same on every level."""

    readout: Float[Array, ""]
    height: Float[Array, ""]
    scale: Float[Array, ""]

    @staticmethod
    def create(readout: float, height: int, level: int = 0, dtype=jnp.float32) -> "RowClock":
        return RowClock(jnp.asarray(readout, dtype), jnp.asarray(height, dtype), jnp.asarray(2.0**level, dtype))

    def times(self, rows: Float[Array, " R"], n: int) -> Float[Array, "R n"]:
        """:func:`row_times` of level rows ``rows``."""
        full = rows * self.scale + 0.5 * (self.scale - 1.0)
        return row_times(n, full, self.height, self.readout)
