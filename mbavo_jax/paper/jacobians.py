"""The supplement's hand-derived Jacobians, written as printed, and corrected where they are wrong.

Functions named ``*_printed`` transcribe the supplement literally (equation numbers in each
docstring). Functions named ``*_corrected`` hold our derivation where the printed form fails the
cross-validation (``mbavo jacobians``, ``tests/test_paper_jacobians.py``); where the printed form
holds there is a single function. The library's analytic Jacobian path uses only the correct forms.

All functions take single elements (batch with ``jax.vmap``); quaternions are ``[qx, qy, qz, qw]``
and every quaternion Jacobian is taken in the ambient R⁴ at a unit quaternion, as in the paper.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Float

from ..geometry import quaternion as quat
from ..geometry.quaternion import Q, Q_hat

_HALF_I = jnp.array([[0.5, 0.0, 0.0], [0.0, 0.5, 0.0], [0.0, 0.0, 0.5], [0.0, 0.0, 0.0]])

# --------------------------------------------------------------------------------------------
# Exponential map, Eqs. 3-11 and 16-19
# --------------------------------------------------------------------------------------------


def _exp_jacobian_from(r, dtheta_dr):
    """Eqs. 3, 6-11 assembled for a given ∂θ/∂r (Eqs. 4-5 supply it)."""
    theta = 0.5 * jnp.linalg.norm(r)
    lam = jnp.sin(theta) / (2 * theta)
    dlam_dtheta = (jnp.cos(theta) - 2 * lam) / (2 * theta)  # Eq. 5 (holds)
    dqv = dlam_dtheta * jnp.outer(r, dtheta_dr) + lam * jnp.eye(3, dtype=r.dtype)  # Eqs. 6-10
    dqw = -jnp.sin(theta) * dtheta_dr  # Eqs. 10-11
    return jnp.concatenate([dqv, dqw[None, :]], axis=0)


def exp_jacobian_printed(r: Float[Array, "3"]) -> Float[Array, "4 3"]:
    """Eqs. 3-11 as printed: ∂θ/∂r = r / (2θ) (Eq. 4-5). Regular θ only."""
    theta = 0.5 * jnp.linalg.norm(r)
    return _exp_jacobian_from(r, r / (2 * theta))


def exp_jacobian_corrected(r: Float[Array, "3"]) -> Float[Array, "4 3"]:
    """Eqs. 3-11 with ∂θ/∂r = r / (4θ): θ = |r|/2 gives ∂θ/∂r = r / (2|r|) = r / (4θ)."""
    theta = 0.5 * jnp.linalg.norm(r)
    return _exp_jacobian_from(r, r / (4 * theta))


def exp_jacobian_small_printed(r: Float[Array, "3"]) -> Float[Array, "4 3"]:
    """Eqs. 16-19: the θ → 0 limit, ∂q_xyz/∂r = ½ I and ∂q_w/∂r = 0 (independent of r)."""
    return _HALF_I.astype(r.dtype)


def exp_jacobian(r: Float[Array, "3"]) -> Float[Array, "4 3"]:
    """The exp Jacobian the library uses: Eqs. 3-11 (corrected), and near θ = 0 the exact
    derivative of the Taylor forms 12-15 (which tends to Eqs. 16-19)."""
    theta_sq = 0.25 * jnp.sum(r * r)
    small = theta_sq < quat.small_angle_eps(r.dtype)
    safe_r = jnp.where(small, jnp.array([1.0, 0.0, 0.0], r.dtype), r)
    regular = exp_jacobian_corrected(safe_r)
    lam = 0.5 - theta_sq / 12 + theta_sq**2 / 240
    dlam_dthsq = -1.0 / 12 + theta_sq / 120
    dqv = lam * jnp.eye(3, dtype=r.dtype) + dlam_dthsq * jnp.outer(r, 0.5 * r)
    dqw = (-0.5 + theta_sq / 12) * 0.5 * r
    taylor = jnp.concatenate([dqv, dqw[None, :]], axis=0)
    return jnp.where(small, taylor, regular)


# --------------------------------------------------------------------------------------------
# Logarithm map, Eqs. 21-29, 30-31, 32-35
# --------------------------------------------------------------------------------------------


def _log_jacobian_from(q, lam, dlam_dq):
    """Eqs. 21-27: ∂r_i/∂q_j = ∂λ/∂q_j q_i + λ δ_ij (j < 3)."""
    lam_block = jnp.concatenate([lam * jnp.eye(3, dtype=q.dtype), jnp.zeros((3, 1), q.dtype)], axis=1)
    return jnp.outer(q[:3], dlam_dq) + lam_block


def _log_lambda(q):
    theta = jnp.linalg.norm(q[:3])
    return theta, 2 * jnp.arctan(theta / q[3]) / theta


def log_jacobian_regular(q: Float[Array, "4"]) -> Float[Array, "3 4"]:
    """Eqs. 21-29 (hold at unit q): ∂λ/∂q_xyz = (2 q_w − λ) q_xyz / θ², ∂λ/∂q_w = −2."""
    theta, lam = _log_lambda(q)
    dlam = jnp.concatenate([(2 * q[3] - lam) * q[:3] / theta**2, jnp.array([-2.0], q.dtype)])
    return _log_jacobian_from(q, lam, dlam)


def _small_theta_lambda(q):
    theta_sq = jnp.sum(q[:3] ** 2)
    return theta_sq, 2 / q[3] - 2 * theta_sq / (3 * q[3] ** 3)


def log_jacobian_small_printed(q: Float[Array, "4"]) -> Float[Array, "3 4"]:
    """Eqs. 30-31 as printed: ∂λ/∂q_x = 2/q_w − 4 q_x / (3 q_w³), ∂λ/∂q_w = −2/q_w² + 2θ²/q_w⁴."""
    theta_sq, lam = _small_theta_lambda(q)
    qw = q[3]
    dlam = jnp.concatenate([2 / qw - 4 * q[:3] / (3 * qw**3), jnp.array([-2 / qw**2 + 2 * theta_sq / qw**4])])
    return _log_jacobian_from(q, lam, dlam)


def log_jacobian_small_corrected(q: Float[Array, "4"]) -> Float[Array, "3 4"]:
    """Eqs. 30-31 corrected: λ = 2/q_w − 2θ²/(3 q_w³) gives ∂λ/∂q_x = −4 q_x / (3 q_w³)
    (no 2/q_w term); Eq. 31 holds."""
    theta_sq, lam = _small_theta_lambda(q)
    qw = q[3]
    dlam = jnp.concatenate([-4 * q[:3] / (3 * qw**3), jnp.array([-2 / qw**2 + 2 * theta_sq / qw**4])])
    return _log_jacobian_from(q, lam, dlam)


def log_jacobian_half_turn_printed(q: Float[Array, "4"]) -> Float[Array, "3 4"]:
    """Eqs. 32-35 as printed: λ = ±π/θ for q_w → 0±; ∂λ/∂q_xyz = −λ q_xyz/θ² for q_w > 0
    (Eq. 32) and +λ q_xyz/θ² for q_w < 0 (Eq. 34); ∂λ/∂q_w = 0 (Eqs. 33, 35)."""
    theta = jnp.linalg.norm(q[:3])
    positive = q[3] >= 0
    lam = jnp.where(positive, jnp.pi / theta, -jnp.pi / theta)
    dlam_v = jnp.where(positive, -lam * q[:3] / theta**2, lam * q[:3] / theta**2)
    dlam = jnp.concatenate([dlam_v, jnp.zeros((1,), q.dtype)])
    return _log_jacobian_from(q, lam, dlam)


def log_jacobian_half_turn_corrected(q: Float[Array, "4"]) -> Float[Array, "3 4"]:
    """Eqs. 32-35 corrected: with λ = ±π/θ, ∂λ/∂q_xyz = −λ q_xyz/θ² on *both* sides (Eq. 34 has
    the wrong sign) and ∂λ/∂q_w = −2/θ² (not 0: arctan(θ/q_w) = ±π/2 − q_w/θ + O(q_w³)), which is
    −2 on a unit quaternion, continuous with Eq. 29."""
    theta = jnp.linalg.norm(q[:3])
    lam = jnp.where(q[3] >= 0, jnp.pi / theta, -jnp.pi / theta)
    dlam = jnp.concatenate([-lam * q[:3] / theta**2, jnp.array([-2.0 / theta**2], q.dtype)])
    return _log_jacobian_from(q, lam, dlam)


def log_jacobian(q: Float[Array, "4"]) -> Float[Array, "3 4"]:
    """The log Jacobian the library uses: Eqs. 21-29 with the corrected branches."""
    theta_sq = jnp.sum(q[:3] ** 2)
    small = theta_sq < quat.small_angle_eps(q.dtype)
    half = (jnp.abs(q[3]) < (1e-4 if q.dtype == jnp.float32 else 1e-7)) & ~small
    safe_reg = jnp.where(small | half, jnp.array([0.6, 0.0, 0.0, 0.8], q.dtype), q)
    safe_small = jnp.where(small, q, jnp.array([0.0, 0.0, 0.0, 1.0], q.dtype))
    safe_half = jnp.where(half, q, jnp.array([1.0, 0.0, 0.0, 0.0], q.dtype))
    return jnp.where(
        small,
        log_jacobian_small_corrected(safe_small),
        jnp.where(half, log_jacobian_half_turn_corrected(safe_half), log_jacobian_regular(safe_reg)),
    )


# --------------------------------------------------------------------------------------------
# Product, inverse, plus: Eqs. 39, 41, 46
# --------------------------------------------------------------------------------------------


def product_jacobians_printed(q0, q1):
    """Eq. 39 as printed: ∂q/∂q0 = Q̄(q1), ∂q/∂q1 = Q(q0). No Q̄ is defined in the supplement;
    read literally as the un-hatted Q of Eq. 37."""
    return Q(q1), Q(q0)


def product_jacobians_corrected(q0, q1):
    """Eq. 39 corrected: ∂q/∂q0 = Q̂(q1) (Eq. 38; Eq. 36 says q = Q̂(q1) q0), ∂q/∂q1 = Q(q0)."""
    return Q_hat(q1), Q(q0)


def inverse_jacobian(q):
    """Eq. 41: diag(−1, −1, −1, 1)."""
    return jnp.diag(jnp.array([-1.0, -1.0, -1.0, 1.0], q.dtype))


def plus_jacobian(q):
    """Eq. 46: ∂(q ⊗ exp(Δr))/∂Δr at Δr = 0 is Q(q) · [½ I; 0]."""
    return Q(q) @ _HALF_I.astype(q.dtype)


# --------------------------------------------------------------------------------------------
# Trajectory: Eqs. 48-49, 56-58, 59-60
# --------------------------------------------------------------------------------------------


def translation_jacobians(s, dtype=jnp.float64):
    """Eqs. 48-49: ∂t_t/∂t_0 = (1 − t/τ) I, ∂t_t/∂t_τ = (t/τ) I, with s = t/τ."""
    eye = jnp.eye(3, dtype=dtype)
    return (1 - s) * eye, s * eye


def _trajectory_parts(q0, qtau, s):
    q0_inv = quat.inverse(q0)
    q_rel = quat.product(q0_inv, qtau)  # Eq. 50 / 54
    r = s * quat.log(q_rel)  # Eq. 51
    q_t0 = quat.exp(r)  # Eq. 52
    return q0_inv, q_rel, r, q_t0


def rotation_jacobians_printed(q0, qtau, s):
    """Eqs. 56-58 as printed. The factor "∂r/∂q̄" is, as the text after Eq. 58 says, the log-map
    Jacobian (Eqs. 21-35) — evaluated at q̄_τ^0, without the factor t/τ of Eq. 51."""
    q0_inv, q_rel, r, q_t0 = _trajectory_parts(q0, qtau, s)
    dexp = exp_jacobian(r)
    dlog = log_jacobian(q_rel)
    dqt0_dq0 = dexp @ dlog @ Q_hat(qtau) @ inverse_jacobian(q0)  # Eq. 57
    dqt_dq0 = Q_hat(q_t0) + Q(q0) @ dqt0_dq0  # Eq. 56
    dqt_dqtau = Q(q0) @ dexp @ dlog @ Q(q0_inv)  # Eq. 58
    return dqt_dq0, dqt_dqtau


def rotation_jacobians_corrected(q0, qtau, s):
    """Eqs. 56-58 corrected: ∂r/∂q̄_τ^0 = (t/τ) ∂log(q̄_τ^0)/∂q̄_τ^0 (Eq. 51 scales the log by t/τ;
    "∂r/∂q̄_0^w" in Eq. 57 and "∂r/∂q̄_τ^w" in Eq. 58 denote this same factor)."""
    q0_inv, q_rel, r, q_t0 = _trajectory_parts(q0, qtau, s)
    dexp = exp_jacobian(r)
    dr = s * log_jacobian(q_rel)
    dqt0_dq0 = dexp @ dr @ Q_hat(qtau) @ inverse_jacobian(q0)
    dqt_dq0 = Q_hat(q_t0) + Q(q0) @ dqt0_dq0
    dqt_dqtau = Q(q0) @ dexp @ dr @ Q(q0_inv)
    return dqt_dq0, dqt_dqtau


def local_rotation_jacobians(q0, qtau, s):
    """Eqs. 59-60: ∂q̄_t/∂Δr_0 = ∂q̄_t/∂q̄_0 · Q(q̄_0) · [½ I; 0], same for Δr_τ (with the corrected
    Eqs. 56-58 inside)."""
    dq0, dqtau = rotation_jacobians_corrected(q0, qtau, s)
    return dq0 @ plus_jacobian(q0), dqtau @ plus_jacobian(qtau)


def virtual_pose_jacobian(q0, qtau, s, dq0_dr=None, dqtau_dr=None):
    """∂(p_i, q̄_i)/∂(Δr_0, Δt_0, Δr_τ, Δt_τ), a 7 × 12 matrix (rows: p then q̄), from Eqs. 48-49
    and 56-58 (corrected): the per-virtual-pose trajectory Jacobian the tracker chains through.
    ``dq0_dr``, ``dqtau_dr`` (4 × 3): derivatives of the start and end quaternions by their local
    updates; by default Q(q̄)·[½I; 0], the update at Δr = 0 (then this is Eqs. 59-60)."""
    dtype = q0.dtype
    dq0_dr = plus_jacobian(q0) if dq0_dr is None else dq0_dr
    dqtau_dr = plus_jacobian(qtau) if dqtau_dr is None else dqtau_dr
    dqi_dq0, dqi_dqtau = rotation_jacobians_corrected(q0, qtau, s)
    dt0, dtt = translation_jacobians(s, dtype)
    z33 = jnp.zeros((3, 3), dtype)
    z43 = jnp.zeros((4, 3), dtype)
    top = jnp.concatenate([z33, dt0, z33, dtt], axis=1)
    bottom = jnp.concatenate([dqi_dq0 @ dq0_dr, z43, dqi_dqtau @ dqtau_dr, z43], axis=1)
    return jnp.concatenate([top, bottom], axis=0)


# --------------------------------------------------------------------------------------------
# Plane transfer: Eqs. 69-84; projection: Eq. 85
# --------------------------------------------------------------------------------------------


def _alphas_betas_gammas(q, ray):
    x, y, z = ray
    qx, qy, qz, qw = q
    a0 = qx * x + qy * y + qz * z  # Eq. 69
    a1 = qy * x - qw * z - qx * y
    a2 = qw * y - qx * z + qz * x  # Eq. 70
    a3 = qw * x + qy * z - qz * y
    a4 = qw * z + qx * y - qy * x  # Eq. 71
    b0 = -2 * (qw * qz - qx * qy)
    b1 = 2 * (qw * qy + qx * qz)  # Eq. 72
    b2 = 2 * (qw * qz + qx * qy)
    b3 = -2 * (qw * qx - qy * qz)  # Eq. 73
    b4 = -2 * (qw * qy - qx * qz)
    b5 = 2 * (qw * qx + qy * qz)  # Eq. 74
    g0 = x * (qw**2 + qx**2 - qy**2 - qz**2) + y * b0 + z * b1  # Eq. 75
    g1 = x * b2 + y * (qw**2 - qx**2 + qy**2 - qz**2) + z * b3  # Eq. 76
    g2 = x * b4 + y * b5 + z * (qw**2 - qx**2 - qy**2 + qz**2)  # Eq. 77
    return (a0, a1, a2, a3, a4), (g0, g1, g2)


def _transfer_jacobian(q, p, ray, d, sign_83):
    (a0, a1, a2, a3, a4), (g0, g1, g2) = _alphas_betas_gammas(q, ray)
    lam = g2  # Eq. 64 equals Eq. 77
    one = jnp.ones_like(lam)
    zero = jnp.zeros_like(lam)
    dp = jnp.array([[one, zero, -g0 / lam], [zero, one, -g1 / lam], [zero, zero, one - g2 / lam]])  # Eqs. 78-80
    c = 2 * (d - p[2]) / lam
    dqx = c * jnp.array([a0 - a2 * g0 / lam, a1 - a2 * g1 / lam, a2 - a2 * g2 / lam])  # Eq. 81
    dqy = c * jnp.array([a4 + a3 * g0 / lam, a0 + a3 * g1 / lam, -a3 + a3 * g2 / lam])  # Eq. 82
    dqz = c * jnp.array([-a2 + sign_83 * a0 * g0 / lam, a3 - a0 * g1 / lam, a0 - a0 * g2 / lam])  # Eq. 83
    dqw = c * jnp.array([a3 - a4 * g0 / lam, a2 - a4 * g1 / lam, a4 - a4 * g2 / lam])  # Eq. 84
    return jnp.concatenate([dp, jnp.stack([dqx, dqy, dqz, dqw], axis=1)], axis=1)


def transfer_jacobian_printed(q, p, ray, d) -> Float[Array, "3 7"]:
    """Eqs. 78-84 as printed: ∂p'_3d/∂(p_x, p_y, p_z, q_x, q_y, q_z, q_w)."""
    return _transfer_jacobian(q, p, ray, d, sign_83=1.0)


def transfer_jacobian_corrected(q, p, ray, d) -> Float[Array, "3 7"]:
    """Eqs. 78-84 corrected: the first entry of Eq. 83 is −α₂ − α₀γ₀/λ (printed: + α₀γ₀/λ);
    ∂γ₀/∂q_z = −2α₂ and ∂λ/∂q_z = 2α₀ give (2(d−p_z)/λ)(−α₂ − α₀γ₀/λ)."""
    return _transfer_jacobian(q, p, ray, d, sign_83=-1.0)


def projection_jacobian(fx, fy, p) -> Float[Array, "2 3"]:
    """Eq. 85: ∂π/∂p'_3d for a pinhole camera."""
    X, Y, Z = p
    zero = jnp.zeros_like(Z)
    return jnp.array([[fx / Z, zero, -fx * X / Z**2], [zero, fy / Z, -fy * Y / Z**2]])
