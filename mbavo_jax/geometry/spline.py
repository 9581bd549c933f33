"""A cubic exposure path: the cumulative cubic B-spline on the project's pose parameterisation.

Four control poses T_0..T_3 (``T_ref_j``, uniform knots) define one spline segment, the one between
T_1 and T_2, and the frame time s ∈ [0, 1] (first row's start to last row's end, as for
:class:`~mbavo_jax.geometry.trajectory.ExposureTrajectory`) is its parameter u = s. As Eqs. 43-44 do
for the straight path, rotation and translation are splined apart:

    q(u) = q_0 ⊗ Π_{j=1..3} exp(B̃_j(u) · log(q_{j-1}⁻¹ ⊗ q_j)),   t(u) = t_0 + Σ_j B̃_j(u) (t_j − t_{j-1})

with the cumulative basis B̃_1 = (5 + 3u − 3u² + u³)/6, B̃_2 = (1 + 3u + 3u² − 2u³)/6, B̃_3 = u³/6.
Control poses evenly spaced along a constant-velocity path (T_j = T_1 · V^(j−1)) give
B̃_1 + B̃_2 + B̃_3 = 1 + u, i.e. exactly the straight path T_1 → T_2 (:meth:`SplineTrajectory.from_linear`).
"""

from __future__ import annotations

import typing

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from . import quaternion as quat
from .pose import Pose
from .trajectory import ExposureTrajectory

__all__ = ["SplineTrajectory", "ExposurePath", "cumulative_basis", "spline_pose", "as_trajectory"]


def cumulative_basis(u) -> Float[Array, "3"]:
    """[B̃_1, B̃_2, B̃_3](u) of the uniform cubic B-spline (B̃_0 = 1)."""
    u2 = u * u
    u3 = u2 * u
    return jnp.stack([(5.0 + 3.0 * u - 3.0 * u2 + u3) / 6.0, (1.0 + 3.0 * u + 3.0 * u2 - 2.0 * u3) / 6.0, u3 / 6.0])


def spline_pose(controls: Pose, u) -> Pose:
    """The pose at segment parameter ``u`` of the spline with control poses ``controls`` (leading axis 4)."""
    q, t = controls.q, controls.t
    u = jnp.asarray(u, q.dtype)
    b = cumulative_basis(u)
    rel = jax.vmap(lambda a, c: quat.log(quat.product(quat.inverse(a), c)))(q[:3], q[1:])  # (3, 3)
    q_u = q[0]
    for j in range(3):
        q_u = quat.product(q_u, quat.exp(b[j] * rel[j]))
    return Pose(q_u, t[0] + b @ (t[1:] - t[:3]))


class SplineTrajectory(eqx.Module):
    """A frame's exposure path as a cumulative cubic B-spline: ``controls`` holds the four control
    poses ``T_ref_j`` (a batched Pose, leading axis 4); s ∈ [0, 1] is the segment between controls
    1 and 2. Offers the methods of ExposureTrajectory that the blur model, the tracker and the loops
    call; ``start``/``end`` are the poses at s = 0 and 1."""

    controls: Pose
    dof: typing.ClassVar[int] = 24  # the tracker's unknowns: a local update of each control pose

    @staticmethod
    def from_linear(path: ExposureTrajectory) -> "SplineTrajectory":
        """The straight path start → end as a spline: control poses evenly spaced on it (the ends
        extended by one step each way), which gives the same poses for every s."""
        w = quat.log(quat.product(quat.inverse(path.start.q), path.end.q))
        dt = path.end.t - path.start.t
        before = Pose(quat.product(path.start.q, quat.exp(-w)), path.start.t - dt)
        after = Pose(quat.product(path.end.q, quat.exp(w)), path.end.t + dt)
        stack = lambda *xs: jnp.stack(xs)
        return SplineTrajectory(jax.tree_util.tree_map(stack, before, path.start, path.end, after))

    def control(self, j: int) -> Pose:
        return jax.tree_util.tree_map(lambda x: x[j], self.controls)

    def at(self, s) -> Pose:
        return spline_pose(self.controls, s)

    @property
    def start(self) -> Pose:
        return self.at(0.0)

    @property
    def end(self) -> Pose:
        return self.at(1.0)

    def middle(self) -> Pose:
        return self.at(0.5)

    def chord(self) -> ExposureTrajectory:
        """The straight path between the spline's start and end (blur-length estimates)."""
        return ExposureTrajectory(self.start, self.end)

    def seen_from(self, T: Pose) -> "SplineTrajectory":
        """T ∘ path: every control pose composed on the left (the spline moves with them)."""
        return SplineTrajectory(jax.vmap(T.compose)(self.controls))

    def about_middle(self) -> "SplineTrajectory":
        """The same path relative to its own mid-exposure pose."""
        return self.seen_from(self.middle().inverse())

    def normalized(self) -> "SplineTrajectory":
        return SplineTrajectory(self.controls.normalized())

    def plus(self, delta: Float[Array, "24"]) -> "SplineTrajectory":
        """Local update of each control pose: ``delta = [Δr_0, Δt_0, ..., Δr_3, Δt_3]``."""
        return SplineTrajectory(jax.vmap(Pose.plus)(self.controls, delta.reshape(4, 6)))

    def row_path(self, v, height, readout) -> ExposureTrajectory:
        """Row v's own exposure (ExposureTrajectory.row_path's times) as the straight path between
        its start and end poses on the spline."""
        s0 = readout * jnp.asarray(v, self.controls.q.dtype) / (jnp.asarray(height, self.controls.q.dtype) - 1.0)
        return ExposureTrajectory(self.at(s0), self.at(s0 + 1.0 - readout))

    def middle_row_path(self, readout) -> ExposureTrajectory:
        """The middle row's own exposure as a straight path (the chord for a concrete ρ = 0)."""
        if not isinstance(readout, jax.core.Tracer) and float(readout) == 0.0:
            return self.chord()
        return self.row_path(0.5, 2.0, readout)


ExposurePath = ExposureTrajectory | SplineTrajectory  # either exposure path (``tracker.trajectory``)


def as_trajectory(path: ExposurePath, kind: str) -> ExposurePath:
    """``path`` as the exposure path of ``kind`` (``tracker.trajectory``): a straight path becomes
    a spline for ``cubic``; anything else is returned as it is."""
    if kind == "cubic" and isinstance(path, ExposureTrajectory):
        return SplineTrajectory.from_linear(path)
    return path
