"""Unit quaternions `[qx, qy, qz, qw]` (Hamilton), as in the MBA-VO supplement §3.

Every function takes single elements (a quaternion is shape ``(4,)``, a tangent vector ``(3,)``);
batch with ``jax.vmap``. Taylor branches use the double-``where`` trick (the unused branch is fed a
safe input) so values *and* gradients stay finite at the singular points: θ = 0 for exp and log and
q_w = 0 for log.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = [
    "exp",
    "log",
    "product",
    "Q",
    "Q_hat",
    "inverse",
    "plus",
    "to_matrix",
    "rotate",
    "from_matrix",
    "identity",
    "small_angle_eps",
]


def small_angle_eps(dtype) -> float:
    """θ² below which the Taylor branches are used (their truncation error is O(θ⁶))."""
    return 1e-4 if jnp.dtype(dtype) == jnp.float32 else 1e-8


def _small_qw_eps(dtype) -> float:
    """|q_w| below which the log uses its q_w → 0± branch (error O(q_w³ / θ³))."""
    return 1e-4 if jnp.dtype(dtype) == jnp.float32 else 1e-7


def identity(dtype=jnp.float32) -> Float[Array, "4"]:
    return jnp.array([0.0, 0.0, 0.0, 1.0], dtype=dtype)


def exp(r: Float[Array, "3"]) -> Float[Array, "4"]:
    """Eq. 2: q = [λ r, cos θ] with θ = |r|/2, λ = sin θ / (2θ); Eqs. 12-15 when θ → 0."""
    theta_sq = 0.25 * jnp.sum(r * r)
    small = theta_sq < small_angle_eps(r.dtype)
    safe_theta_sq = jnp.where(small, jnp.ones_like(theta_sq), theta_sq)
    safe_theta = jnp.sqrt(safe_theta_sq)
    lam = jnp.where(
        small,
        0.5 - theta_sq / 12.0 + theta_sq * theta_sq / 240.0,  # Eqs. 12-14
        jnp.sin(safe_theta) / (2.0 * safe_theta),
    )
    qw = jnp.where(
        small,
        1.0 - 0.5 * theta_sq + theta_sq * theta_sq / 24.0,  # Eq. 15
        jnp.cos(safe_theta),
    )
    return jnp.concatenate([lam * r, qw[None]])


def log(q: Float[Array, "4"]) -> Float[Array, "3"]:
    """Eq. 20: r = λ [qx, qy, qz] with θ = |q_xyz|, λ = 2 arctan(θ / q_w) / θ.

    Branches (supplement §3): θ → 0 uses λ = 2/q_w − 2θ²/(3 q_w³). For q_w → 0± the paper
    prints λ = ±π/θ; we keep its first-order term, λ = ±π/θ − 2 q_w/θ², so that ∂λ/∂q_w is right
    (the paper's Eqs. 33/35 give 0; the true value is −2/θ², see ``mbavo jacobians``).
    arctan(θ/q_w) picks the rotation angle in (−π, π], i.e. q and −q have the same log.
    """
    v, qw = q[:3], q[3]
    theta_sq = jnp.sum(v * v)
    eps = small_angle_eps(q.dtype)
    small_theta = theta_sq < eps
    small_qw = (jnp.abs(qw) < _small_qw_eps(q.dtype)) & ~small_theta
    regular = ~(small_theta | small_qw)

    safe_theta_sq = jnp.where(small_theta, jnp.ones_like(theta_sq), theta_sq)
    safe_theta = jnp.sqrt(safe_theta_sq)
    # q_w is never 0 for a unit quaternion with θ small, but guard anyway.
    safe_qw_taylor = jnp.where(small_theta, qw, jnp.ones_like(qw))
    safe_qw_taylor = jnp.where(jnp.abs(safe_qw_taylor) < eps, jnp.ones_like(qw), safe_qw_taylor)
    safe_qw_regular = jnp.where(regular, qw, jnp.ones_like(qw))

    lam_taylor = 2.0 / safe_qw_taylor - 2.0 * theta_sq / (3.0 * safe_qw_taylor**3)
    sign_qw = jnp.where(qw >= 0, 1.0, -1.0).astype(q.dtype)
    lam_half_turn = sign_qw * jnp.pi / safe_theta - 2.0 * qw / safe_theta_sq
    lam_regular = 2.0 * jnp.arctan(safe_theta / safe_qw_regular) / safe_theta
    lam = jnp.where(small_theta, lam_taylor, jnp.where(small_qw, lam_half_turn, lam_regular))
    return lam * v


def Q(q0: Float[Array, "4"]) -> Float[Array, "4 4"]:
    """Eq. 37: left-multiplication matrix, q0 ⊗ q1 = Q(q0) q1."""
    x, y, z, w = q0
    return jnp.array(
        [
            [w, -z, y, x],
            [z, w, -x, y],
            [-y, x, w, z],
            [-x, -y, -z, w],
        ]
    )


def Q_hat(q1: Float[Array, "4"]) -> Float[Array, "4 4"]:
    """Eq. 38: right-multiplication matrix, q0 ⊗ q1 = Q̂(q1) q0."""
    x, y, z, w = q1
    return jnp.array(
        [
            [w, z, -y, x],
            [-z, w, x, y],
            [y, -x, w, z],
            [-x, -y, -z, w],
        ]
    )


def product(q0: Float[Array, "4"], q1: Float[Array, "4"]) -> Float[Array, "4"]:
    """Eq. 36: Hamilton product q0 ⊗ q1 = Q(q0) q1."""
    return Q(q0) @ q1


def inverse(q: Float[Array, "4"]) -> Float[Array, "4"]:
    """Eq. 40: the conjugate (the inverse of a unit quaternion)."""
    return q * jnp.array([-1.0, -1.0, -1.0, 1.0], dtype=q.dtype)


def plus(q: Float[Array, "4"], delta_r: Float[Array, "3"]) -> Float[Array, "4"]:
    """Eq. 45: local update q' = q ⊗ exp(Δr)."""
    return product(q, exp(delta_r))


def to_matrix(q: Float[Array, "4"]) -> Float[Array, "3 3"]:
    """Rotation matrix of q, written as the homogeneous polynomial of Eqs. 64 and 75-77.

    It is exact for unit q and is differentiated in the ambient R⁴ exactly as the paper does.
    """
    x, y, z, w = q
    return jnp.array(
        [
            [w * w + x * x - y * y - z * z, 2 * (x * y - w * z), 2 * (w * y + x * z)],
            [2 * (w * z + x * y), w * w - x * x + y * y - z * z, 2 * (y * z - w * x)],
            [2 * (x * z - w * y), 2 * (w * x + y * z), w * w - x * x - y * y + z * z],
        ]
    )


def rotate(q: Float[Array, "4"], v: Float[Array, "3"]) -> Float[Array, "3"]:
    """R(q) v (Eq. 1's rotation), written as the sum of R's columns scaled by v's components so
    that XLA fuses it with its neighbours (a matvec compiles to a ``dot`` kernel of its own)."""
    R = to_matrix(q)
    return R[:, 0] * v[0] + R[:, 1] * v[1] + R[:, 2] * v[2]


def from_matrix(R: Float[Array, "3 3"]) -> Float[Array, "4"]:
    """Unit quaternion (q_w ≥ 0) of a rotation matrix (Shepperd's method, branch-free via argmax)."""
    m00, m11, m22 = R[0, 0], R[1, 1], R[2, 2]
    trace = m00 + m11 + m22
    candidates = jnp.stack(
        [
            jnp.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1], 1.0 + trace]),
            jnp.array([1.0 + m00 - m11 - m22, R[0, 1] + R[1, 0], R[0, 2] + R[2, 0], R[2, 1] - R[1, 2]]),
            jnp.array([R[0, 1] + R[1, 0], 1.0 - m00 + m11 - m22, R[1, 2] + R[2, 1], R[0, 2] - R[2, 0]]),
            jnp.array([R[0, 2] + R[2, 0], R[1, 2] + R[2, 1], 1.0 - m00 - m11 + m22, R[1, 0] - R[0, 1]]),
        ]
    )
    pick = jnp.argmax(jnp.array([trace, m00, m11, m22]))
    q = candidates[pick]
    q = q / jnp.linalg.norm(q)
    return jnp.where(q[3] < 0, -q, q)
