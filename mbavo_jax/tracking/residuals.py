"""Photometric residuals of the blur model and their Jacobian, structured as in the paper.

For residual pixel x (integer, in the blurry current frame) with plane depth d and virtual pose i:

    v_i(x) = I_ref(π(T_ref_i · plane(x, d)))                  (Eqs. 61-68)
    r(x)   = e^a · (1/n) Σ_i v_i(x) + b − B(x)                  (blur model, main paper Eq. 6)

The 12 trajectory unknowns enter only through the n virtual poses, so the Jacobian is

    ∂r/∂y = e^a / n · Σ_i  g_i(x) · M_i,   g_i = ∂v_i/∂(p_i, q̄_i)  (1 x 7),   M_i = ∂(p_i, q̄_i)/∂y  (7 x 12)

where M_i is shared by all pixels. Two paths compute g_i and M_i: ``autodiff`` (``jax.jacfwd`` of the
per-sample function and of the trajectory) and ``analytic`` (the supplement's corrected formulas:
Eqs. 85, 78-84, 56-58, 48-49, 3-11). The residual function carries a ``custom_jvp`` that returns
J @ ẏ, so ``jax.linearize`` inside optimistix computes J once per step.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ..geometry import quaternion as quat
from ..image import bilinear_cell
from ..geometry.camera import PinholeCamera
from ..geometry.pose import Pose
from ..geometry.trajectory import ExposureTrajectory, interpolate, virtual_times
from ..geometry.transfer import plane_point
from ..paper import jacobians as pj

__all__ = ["LevelProblem", "residuals_and_jacobian", "make_residual_fn", "robust", "bilinear_with_gradient"]


class LevelProblem(eqx.Module):
    """Everything one pyramid level's solve needs (fixed shapes; R = points x 8)."""

    ref_image: Float[Array, "H W"]
    camera: PinholeCamera
    anchor: ExposureTrajectory  # y = 0 corresponds to this trajectory
    rays: Float[Array, "R 3"]  # unit rays π⁻¹(x) of the residual pixels (Eq. 62)
    depths: Float[Array, "R"]  # plane depth d of each residual pixel
    observed: Float[Array, "R"]  # B(x), the blurry frame at the residual pixels
    mask: Bool[Array, "R"]
    n: int = eqx.field(static=True)
    jacobian: str = eqx.field(static=True)  # "autodiff" | "analytic"


def bilinear_with_gradient(image, x):
    """Bilinear sample, its exact spatial derivative (the derivative of the interpolant), validity."""
    valid, fu, fv, (i00, i01, i10, i11) = bilinear_cell(image, x)
    top = i00 + fu * (i01 - i00)
    bottom = i10 + fu * (i11 - i10)
    value = top + fv * (bottom - top)
    du = (1 - fv) * (i01 - i00) + fv * (i11 - i10)
    dv = bottom - top
    zero = jnp.zeros_like(value)
    return jnp.where(valid, value, zero), jnp.where(valid, jnp.stack([du, dv]), jnp.zeros(2, value.dtype)), valid


def _sample(problem: LevelProblem, pq, ray, d):
    """v_i for one residual pixel at virtual pose pq = [p (3), q̄ (4)]: value and validity."""
    p_ref, _, ok = plane_point(pq[3:], pq[:3], ray, d)
    ok = ok & (p_ref[2] > 1e-6)
    safe = jnp.where(ok, p_ref, jnp.array([0.0, 0.0, 1.0], p_ref.dtype))
    value, grad, inside = bilinear_with_gradient(problem.ref_image, problem.camera.project(safe))
    valid = ok & inside
    return value, grad, safe, valid


def _trajectory(problem: LevelProblem, y12) -> ExposureTrajectory:
    return problem.anchor.plus(y12)


def _virtual_pq(traj: ExposureTrajectory, s):
    p = interpolate(traj.start, traj.end, s)
    return jnp.concatenate([p.t, p.q])


def _M_autodiff(problem: LevelProblem, y12, s):
    """M_i = ∂(p_i, q̄_i)/∂y by forward-mode autodiff of the exposure trajectory (n x 7 x 12)."""
    return jax.vmap(lambda si: jax.jacfwd(lambda yy: _virtual_pq(_trajectory(problem, yy), si))(y12))(s)


def _M_analytic(problem: LevelProblem, y12, s):
    """M_i from the supplement: Eqs. 48-49 (translation), 56-58 corrected (rotation), and the
    derivative of the update q' = q̄_anchor ⊗ exp(Δr) (Eqs. 36-37 and 3-11 corrected)."""
    a = problem.anchor
    traj = _trajectory(problem, y12)
    dq_start_dy = quat.Q(a.start.q) @ pj.exp_jacobian(y12[0:3])  # 4 x 3
    dq_end_dy = quat.Q(a.end.q) @ pj.exp_jacobian(y12[6:9])

    def one(si):
        dqi_dqs, dqi_dqe = pj.rotation_jacobians_corrected(traj.start.q, traj.end.q, si)
        dt_s, dt_e = pj.translation_jacobians(si, y12.dtype)
        z3 = jnp.zeros((3, 3), y12.dtype)
        z43 = jnp.zeros((4, 3), y12.dtype)
        top = jnp.concatenate([z3, dt_s, z3, dt_e], axis=1)
        bottom = jnp.concatenate([dqi_dqs @ dq_start_dy, z43, dqi_dqe @ dq_end_dy, z43], axis=1)
        return jnp.concatenate([top, bottom], axis=0)

    return jax.vmap(one)(s)


def _g_autodiff(problem: LevelProblem, pq, ray, d):
    """g_i = ∂v_i/∂(p, q̄) by ``jax.jacfwd`` of the per-sample function (1 x 7)."""
    f = lambda x: _sample(problem, x, ray, d)[0]
    return jax.jacfwd(f)(pq)


def _g_analytic(problem: LevelProblem, pq, ray, d):
    """g_i = ∇I · Eq. 85 · Eqs. 78-84 (corrected)."""
    _, grad, p_ref, valid = _sample(problem, pq, ray, d)
    dproj = pj.projection_jacobian(problem.camera.fx, problem.camera.fy, p_ref)  # 2 x 3
    dp = pj.transfer_jacobian_corrected(pq[3:], pq[:3], ray, d)  # 3 x 7
    return jnp.where(valid, grad @ dproj @ dp, 0.0)


def residuals_and_jacobian(y: Float[Array, "14"], problem: LevelProblem, with_jacobian: bool = True):
    """Residuals r (R,) at y = [Δstart (6), Δend (6), a, b] and, optionally, J = ∂r/∂y (R, 14).

    Invalid residuals (a sample outside the keyframe, a ray missing the plane, masked pixels) are 0
    with zero Jacobian rows. Also returns the per-residual validity.
    """
    y12, a, b = y[:12], y[12], y[13]
    traj = _trajectory(problem, y12)
    s = virtual_times(problem.n, y.dtype)
    pqs = jax.vmap(lambda si: _virtual_pq(traj, si))(s)  # (n, 7)

    def per_pose(pq):
        vals, _, _, ok = jax.vmap(lambda ray, d: _sample(problem, pq, ray, d))(problem.rays, problem.depths)
        return vals, ok

    vals, ok = jax.vmap(per_pose)(pqs)  # (n, R)
    valid = problem.mask & jnp.all(ok, axis=0)
    synth = jnp.mean(vals, axis=0)
    gain = jnp.exp(a)
    r = jnp.where(valid, gain * synth + b - problem.observed, 0.0)
    if not with_jacobian:
        return r, None, valid
    if problem.jacobian == "analytic":
        G = jax.vmap(lambda pq: jax.vmap(lambda ray, d: _g_analytic(problem, pq, ray, d))(problem.rays, problem.depths))(pqs)
        M = _M_analytic(problem, y12, s)
    else:
        G = jax.vmap(lambda pq: jax.vmap(lambda ray, d: _g_autodiff(problem, pq, ray, d))(problem.rays, problem.depths))(pqs)
        M = _M_autodiff(problem, y12, s)
    J12 = (gain / problem.n) * jnp.einsum("nrj,njk->rk", G, M)
    J = jnp.concatenate([J12, (gain * synth)[:, None], jnp.ones_like(synth)[:, None]], axis=1)
    J = jnp.where(valid[:, None], J, 0.0)
    return r, J, valid


def make_residual_fn():
    """``f(y, problem) -> r`` with a custom JVP ``J @ ẏ`` (J from the problem's Jacobian path)."""

    @jax.custom_jvp
    def f(y, problem):
        return residuals_and_jacobian(y, problem, with_jacobian=False)[0]

    @f.defjvp
    def f_jvp(primals, tangents):
        y, problem = primals
        y_dot, _ = tangents  # the problem's data is not differentiated
        r, J, _ = residuals_and_jacobian(y, problem, with_jacobian=True)
        return r, J @ y_dot

    return f


def robust(r, k):
    """Square-rooted Huber: ½ robust(r)² = Huber_k(r), so least squares minimises the Huber cost."""
    a = jnp.abs(r)
    safe = jnp.where(a > k, a, k)
    return jnp.where(a > k, jnp.sign(r) * jnp.sqrt(2 * k * safe - k * k), r)
