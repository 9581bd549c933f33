"""Rigid poses as a (quaternion, translation) pytree.

``T_a_b`` maps points of frame b into frame a: ``p_a = T_a_b.apply(p_b)`` (the paper's T_b^a, Eq. 1).
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from . import quaternion as quat

__all__ = ["Pose", "compiled_on_host"]


class Pose(eqx.Module):
    """A rigid transform: ``q`` [qx, qy, qz, qw] (unit, Hamilton) and ``t`` [tx, ty, tz].

    Methods act on single poses; batch with ``jax.vmap`` (a batched Pose has leading axes on both
    fields).
    """

    q: Float[Array, "... 4"]
    t: Float[Array, "... 3"]

    @staticmethod
    def identity(dtype=jnp.float32) -> "Pose":
        return Pose(quat.identity(dtype), jnp.zeros(3, dtype))

    @staticmethod
    def from_matrix(T: Float[Array, "4 4"]) -> "Pose":
        T = jnp.asarray(T)
        return Pose(quat.from_matrix(T[:3, :3]), T[:3, 3])

    @staticmethod
    def from_vector(v: Float[Array, "7"]) -> "Pose":
        """From ``[tx, ty, tz, qx, qy, qz, qw]`` (the TUM order)."""
        v = jnp.asarray(v)
        return Pose(v[..., 3:7], v[..., 0:3])

    def to_vector(self) -> Float[Array, "... 7"]:
        """``[tx, ty, tz, qx, qy, qz, qw]`` (the TUM order)."""
        return jnp.concatenate([self.t, self.q], axis=-1)

    def rotation(self) -> Float[Array, "3 3"]:
        return quat.to_matrix(self.q)

    def as_matrix(self) -> Float[Array, "4 4"]:
        top = jnp.concatenate([self.rotation(), self.t[:, None]], axis=1)
        bottom = jnp.array([[0.0, 0.0, 0.0, 1.0]], dtype=top.dtype)
        return jnp.concatenate([top, bottom], axis=0)

    def apply(self, p: Float[Array, "3"]) -> Float[Array, "3"]:
        """Eq. 1: p_a = R p_b + t."""
        return quat.rotate(self.q, p) + self.t

    def compose(self, other: "Pose") -> "Pose":
        """``T_a_b.compose(T_b_c) = T_a_c``."""
        return _compose(self, other)

    def inverse(self) -> "Pose":
        return _inverse(self)

    def plus(self, delta: Float[Array, "6"]) -> "Pose":
        """Local update used by the solver: q' = q ⊗ exp(Δr) (Eq. 45), t' = t + Δt.

        ``delta = [Δr (3), Δt (3)]``.
        """
        return Pose(quat.plus(self.q, delta[:3]), self.t + delta[3:])

    def normalized(self) -> "Pose":
        return Pose(self.q / jnp.linalg.norm(self.q, axis=-1, keepdims=True), self.t)




def compiled_on_host(fn):
    """``fn`` as one compiled call when called on concrete arrays (poses handled outside a solver: a
    dozen small ops otherwise), and as itself inside a trace, so traced programs stay as they are."""
    compiled = jax.jit(fn)

    @functools.wraps(fn)
    def call(*args):
        traced = any(isinstance(x, jax.core.Tracer) for x in jax.tree_util.tree_leaves(args))
        return fn(*args) if traced else compiled(*args)

    return call


@compiled_on_host
def _compose(a: Pose, b: Pose) -> Pose:
    return Pose(quat.product(a.q, b.q), quat.rotate(a.q, b.t) + a.t)


@compiled_on_host
def _inverse(a: Pose) -> Pose:
    q_inv = quat.inverse(a.q)
    return Pose(q_inv, -quat.rotate(q_inv, a.t))
