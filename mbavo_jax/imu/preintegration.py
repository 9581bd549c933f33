"""IMU preintegration on the manifold (Forster, Carlone, Dellaert, Scaramuzza, "On-Manifold
Preintegration for Real-Time Visual-Inertial Odometry", TRO 2017; equation numbers are the paper's).

Between two times t0 < t1 the gyroscope and accelerometer samples are integrated into the relative
motion increments (Eqs. 33-35, in the IMU frame at t0; biases held at their linearisation point)

    ΔR ← ΔR Exp(ω δ),   Δv ← Δv + R_m a δ,   Δp ← Δp + Δv δ + ½ R_m a δ²,   R_m = ΔR Exp(ω δ/2)

over the intervals δ_k between consecutive knots (t0, the samples inside (t0, t1), t1), with
ω = ω̄_k − b_g and a = ā_k − b_a. ω̄_k and ā_k are the means of the measurements at an interval's two
ends, the measurements linearly interpolated between samples (so at t0 and t1 they are
interpolated), and the specific force is rotated by the rotation at the interval's middle R_m: a
midpoint rule, whose error is O(δ²). The paper holds the first sample and ΔR over an interval, an
O(δ) error: ½ ω × a δ in Δv per second, 0.02 m/s² at 200 Hz turning at 1 rad/s against gravity (a
bias larger than the ADIS16448's noise on a 33 ms increment). The bias Jacobians follow the
recursions of Appendix B through R_m (the exact derivatives of these sums); the covariance of
[δφ, δv, δp] the propagation of Eqs. 62-63 (A and B with R_m), the white noise of an interval of
variance σ_c²/δ_k (the continuous-time density over the interval; the bias random walks are not
part of it).

Fixed shapes: the K samples are padded and masked (``valid``), and intervals touching a padded
sample or lying outside [t0, t1] have length 0, so one compiled program serves every window of K
samples; ``jax.lax.scan`` runs over the K − 1 intervals.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ..geometry import quaternion as quat
from .data import ImuNoise

__all__ = ["Preintegrated", "NavState", "ResidualJacobians", "preintegrate", "correct", "residual", "residual_jacobians",
           "skew", "so3_exp", "so3_log", "right_jacobian", "right_jacobian_inverse"]


def skew(w: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """[w]×: skew(w) @ x = w × x."""
    z = jnp.zeros_like(w[0])
    return jnp.stack([jnp.stack([z, -w[2], w[1]]), jnp.stack([w[2], z, -w[0]]), jnp.stack([-w[1], w[0], z])])


def so3_exp(phi: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Exp: rotation vector → rotation matrix (Eq. 3), through the project's quaternion exp."""
    return quat.to_matrix(quat.exp(phi))


def so3_log(R: Float[Array, "3 3"]) -> Float[Array, "3"]:
    """Log: rotation matrix → rotation vector (Eq. 5), through the project's quaternion log."""
    return quat.log(quat.from_matrix(R))


def _safe_angle(phi: Float[Array, "3"]) -> tuple[Array, Array, Array]:
    """(θ², whether θ is small, θ with a safe value of 1 where small): the double-where guard."""
    theta_sq = jnp.sum(phi * phi)
    small = theta_sq < quat.small_angle_eps(phi.dtype)
    theta = jnp.sqrt(jnp.where(small, jnp.ones_like(theta_sq), theta_sq))
    return theta_sq, small, theta


def right_jacobian(phi: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Eq. 8: J_r(φ) = I − (1 − cos θ)/θ² [φ]× + (θ − sin θ)/θ³ [φ]×² (Taylor terms for θ → 0)."""
    theta_sq, small, theta = _safe_angle(phi)
    a = jnp.where(small, 0.5 - theta_sq / 24.0, (1.0 - jnp.cos(theta)) / (theta * theta))
    b = jnp.where(small, 1.0 / 6.0 - theta_sq / 120.0, (theta - jnp.sin(theta)) / (theta * theta * theta))
    W = skew(phi)
    return jnp.eye(3, dtype=phi.dtype) - a * W + b * (W @ W)


def right_jacobian_inverse(phi: Float[Array, "3"]) -> Float[Array, "3 3"]:
    """Eq. 9: J_r⁻¹(φ) = I + ½[φ]× + (1/θ² − (1 + cos θ)/(2θ sin θ)) [φ]×² (Taylor 1/12 for θ → 0)."""
    theta_sq, small, theta = _safe_angle(phi)
    c = jnp.where(small, 1.0 / 12.0 + theta_sq / 720.0,
                  1.0 / (theta * theta) - (1.0 + jnp.cos(theta)) / (2.0 * theta * jnp.sin(theta)))
    W = skew(phi)
    return jnp.eye(3, dtype=phi.dtype) + 0.5 * W + c * (W @ W)


class Preintegrated(eqx.Module):
    """The preintegrated measurement between two times: ``dt`` (s), ``delta_R`` (3, 3), ``delta_v``,
    ``delta_p`` (Eqs. 33-35), ``covariance`` (9, 9) of [δφ, δv, δp] (Eq. 63), the bias Jacobians
    (Appendix B) and the biases ``bias_g``, ``bias_a`` they were integrated (linearised) at."""

    dt: Float[Array, ""]
    delta_R: Float[Array, "3 3"]
    delta_v: Float[Array, "3"]
    delta_p: Float[Array, "3"]
    covariance: Float[Array, "9 9"]
    dR_dbg: Float[Array, "3 3"]
    dv_dbg: Float[Array, "3 3"]
    dv_dba: Float[Array, "3 3"]
    dp_dbg: Float[Array, "3 3"]
    dp_dba: Float[Array, "3 3"]
    bias_g: Float[Array, "3"]
    bias_a: Float[Array, "3"]


class NavState(eqx.Module):
    """A navigation state: ``R`` (3, 3), ``v``, ``p`` of the IMU in the world (world-from-IMU), and
    its gyroscope and accelerometer biases. Local moves (:func:`residual_jacobians`): R ← R Exp(δφ),
    v ← v + δv, p ← p + R δp, b ← b + δb (Forster §VI)."""

    R: Float[Array, "3 3"]
    v: Float[Array, "3"]
    p: Float[Array, "3"]
    bias_g: Float[Array, "3"]
    bias_a: Float[Array, "3"]


class _Interval(eqx.Module):
    """One integration interval: its length and the bias-corrected mean measurements over it."""

    dt: Float[Array, "K"]
    omega: Float[Array, "K 3"]
    acc: Float[Array, "K 3"]


def _intervals(t, gyro, accel, valid, t0, t1, bias_g, bias_a) -> _Interval:
    """The K − 1 intervals between consecutive samples clipped to [t0, t1] (length 0 outside it and
    where a sample is padding), with the means of the interpolated measurements at their ends."""
    lo, hi = jnp.clip(t[:-1], t0, t1), jnp.clip(t[1:], t0, t1)
    span = t[1:] - t[:-1]
    safe = jnp.where(span > 0, span, jnp.ones_like(span))
    wa, wb = (lo - t[:-1]) / safe, (hi - t[:-1]) / safe  # interpolation weights of the interval's ends

    def mean(m):
        d = m[1:] - m[:-1]
        return m[:-1] + 0.5 * (wa + wb)[:, None] * d

    dt = jnp.where(valid[:-1] & valid[1:] & (span > 0), hi - lo, jnp.zeros_like(lo))
    return _Interval(dt, mean(gyro) - bias_g, mean(accel) - bias_a)


def _empty(dtype, bias_g, bias_a) -> Preintegrated:
    z3, eye = jnp.zeros((3, 3), dtype), jnp.eye(3, dtype=dtype)
    return Preintegrated(jnp.zeros((), dtype), eye, jnp.zeros(3, dtype), jnp.zeros(3, dtype), jnp.zeros((9, 9), dtype),
                         z3, z3, z3, z3, z3, bias_g, bias_a)


def _step(pre: Preintegrated, k, densities: Float[Array, "2"]) -> Preintegrated:
    """One interval of Eqs. 33-35 with the velocity and position driven by the rotation at the
    interval's middle, R_m = ΔR Exp(ω δ/2); the bias Jacobians' recursions (Appendix B, through R_m)
    and the covariance propagation (Eqs. 62-63; each interval's noise density² · δ)."""
    dt, w, a = k
    eye, z3 = jnp.eye(3, dtype=dt.dtype), jnp.zeros((3, 3), dt.dtype)
    dR_k, Jr = so3_exp(w * dt), right_jacobian(w * dt)
    half, Jh = so3_exp(0.5 * w * dt), right_jacobian(0.5 * w * dt)
    Rm = pre.delta_R @ half
    Rma = Rm @ skew(a)
    dRm_dbg = half.T @ pre.dR_dbg - 0.5 * Jh * dt  # right-perturbation Jacobian of R_m
    A = jnp.block([[dR_k.T, z3, z3], [-Rma @ half.T * dt, eye, z3], [-0.5 * Rma @ half.T * dt * dt, eye * dt, eye]])
    Bg = jnp.concatenate([Jr, -0.5 * Rma @ Jh * dt, -0.25 * Rma @ Jh * dt * dt])
    Ba = jnp.concatenate([z3, Rm, 0.5 * Rm * dt])
    cov = A @ pre.covariance @ A.T + dt * (densities[0] ** 2 * Bg @ Bg.T + densities[1] ** 2 * Ba @ Ba.T)
    return Preintegrated(
        dt=pre.dt + dt,
        delta_R=pre.delta_R @ dR_k,
        delta_v=pre.delta_v + Rm @ a * dt,
        delta_p=pre.delta_p + pre.delta_v * dt + 0.5 * (Rm @ a) * dt * dt,
        covariance=cov,
        dR_dbg=dR_k.T @ pre.dR_dbg - Jr * dt,
        dv_dbg=pre.dv_dbg - Rma @ dRm_dbg * dt,
        dv_dba=pre.dv_dba - Rm * dt,
        dp_dbg=pre.dp_dbg + pre.dv_dbg * dt - 0.5 * Rma @ dRm_dbg * dt * dt,
        dp_dba=pre.dp_dba + pre.dv_dba * dt - 0.5 * Rm * dt * dt,
        bias_g=pre.bias_g,
        bias_a=pre.bias_a,
    )


def preintegrate(t: Float[Array, "K"], gyro: Float[Array, "K 3"], accel: Float[Array, "K 3"], t0: Float[Array, ""] | float,
                 t1: Float[Array, ""] | float, bias_g: Float[Array, "3"], bias_a: Float[Array, "3"], noise: ImuNoise,
                 valid: Bool[Array, "K"] | None = None) -> Preintegrated:
    """The preintegrated measurement of the samples (``t`` increasing, on the clock of t0 and t1)
    from ``t0`` to ``t1`` at the biases ``bias_g``, ``bias_a`` (module docstring). The samples must
    span [t0, t1] (:func:`~mbavo_jax.imu.data.window` picks them); ``valid`` masks padding."""
    valid = jnp.ones(t.shape, bool) if valid is None else valid
    densities = jnp.asarray([noise.gyro_noise, noise.accel_noise], gyro.dtype)
    return _preintegrate(t, gyro, accel, jnp.asarray(t0, t.dtype), jnp.asarray(t1, t.dtype), bias_g, bias_a, densities, valid)


@jax.jit
def _preintegrate(t: Float[Array, "K"], gyro: Float[Array, "K 3"], accel: Float[Array, "K 3"], t0: Float[Array, ""],
                  t1: Float[Array, ""], bias_g: Float[Array, "3"], bias_a: Float[Array, "3"], densities: Float[Array, "2"],
                  valid: Bool[Array, "K"]) -> Preintegrated:
    """:func:`preintegrate` compiled: the intervals, then one scan over them."""
    iv = _intervals(t, gyro, accel, valid, t0, t1, bias_g, bias_a)
    step = lambda pre, k: (_step(pre, k, densities), None)
    pre, _ = jax.lax.scan(step, _empty(gyro.dtype, bias_g, bias_a), (iv.dt.astype(gyro.dtype), iv.omega, iv.acc))
    return pre


def correct(pre: Preintegrated, bias_g: Float[Array, "3"], bias_a: Float[Array, "3"]) -> Preintegrated:
    """Eq. 44: the increments at other biases to first order, ΔR Exp(∂ΔR/∂b_g δb_g),
    Δv + ∂Δv/∂b_g δb_g + ∂Δv/∂b_a δb_a, Δp likewise, δb = b − b̄ (b̄ the biases ``pre`` holds). The
    result holds the new biases; its Jacobians and covariance are ``pre``'s."""
    dbg, dba = bias_g - pre.bias_g, bias_a - pre.bias_a
    return eqx.tree_at(lambda p: (p.delta_R, p.delta_v, p.delta_p, p.bias_g, p.bias_a), pre,
                       (pre.delta_R @ so3_exp(pre.dR_dbg @ dbg), pre.delta_v + pre.dv_dbg @ dbg + pre.dv_dba @ dba,
                        pre.delta_p + pre.dp_dbg @ dbg + pre.dp_dba @ dba, bias_g, bias_a))


def _predicted(pre: Preintegrated, si: NavState, sj: NavState, gravity: Float[Array, "3"]):
    """R_iᵀ R_j, R_iᵀ (v_j − v_i − g Δt) and R_iᵀ (p_j − p_i − v_i Δt − ½ g Δt²): the state's side of Eq. 45."""
    dt = pre.dt
    return (si.R.T @ sj.R, si.R.T @ (sj.v - si.v - gravity * dt),
            si.R.T @ (sj.p - si.p - si.v * dt - 0.5 * gravity * dt * dt))


def residual(pre: Preintegrated, state_i: NavState, state_j: NavState, gravity: Float[Array, "3"]) -> Float[Array, "9"]:
    """Eq. 45: [r_ΔR, r_Δv, r_Δp] between ``state_i`` at t0 and ``state_j`` at t1, the increments
    corrected to state_i's biases (Eq. 44); ``gravity`` in the world frame (e.g. [0, 0, −9.81])."""
    c = correct(pre, state_i.bias_g, state_i.bias_a)
    dR, dv, dp = _predicted(pre, state_i, state_j, gravity)
    return jnp.concatenate([so3_log(c.delta_R.T @ dR), dv - c.delta_v, dp - c.delta_p])


class ResidualJacobians(eqx.Module):
    """∂r/∂(state_i) and ∂r/∂(state_j), each (9, 15) over the local moves [δφ, δv, δp, δb_g, δb_a]."""

    i: Float[Array, "9 15"]
    j: Float[Array, "9 15"]


def residual_jacobians(pre: Preintegrated, state_i: NavState, state_j: NavState, gravity: Float[Array, "3"]) -> ResidualJacobians:
    """The analytic Jacobians of :func:`residual` (Forster Appendix C; p ← p + R δp)."""
    si, sj, dt = state_i, state_j, pre.dt
    eye, z3 = jnp.eye(3, dtype=dt.dtype), jnp.zeros((3, 3), dt.dtype)
    c = correct(pre, si.bias_g, si.bias_a)
    dR, dv, dp = _predicted(pre, si, sj, gravity)
    r_R = so3_log(c.delta_R.T @ dR)
    Jinv = right_jacobian_inverse(r_R)
    dRb = -Jinv @ so3_exp(r_R).T @ right_jacobian(pre.dR_dbg @ (si.bias_g - pre.bias_g)) @ pre.dR_dbg
    Ji = jnp.block([
        [-Jinv @ sj.R.T @ si.R, z3, z3, dRb, z3],
        [skew(dv), -si.R.T, z3, -pre.dv_dbg, -pre.dv_dba],
        [skew(dp), -si.R.T * dt, -eye, -pre.dp_dbg, -pre.dp_dba],
    ])
    Jj = jnp.block([
        [Jinv, z3, z3, z3, z3],
        [z3, si.R.T, z3, z3, z3],
        [z3, z3, si.R.T @ sj.R, z3, z3],
    ])
    return ResidualJacobians(Ji, Jj)
