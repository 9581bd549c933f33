"""Photometric residuals of the blur model and their Jacobian, structured as in the paper.

For residual pixel x (integer, in the blurry current frame) with plane depth d and virtual pose i:

    v_i(x) = I_ref(π(T_ref_i · plane(x, d)))                  (Eqs. 61-68)
    r(x)   = e^a · (1/n) Σ_i v_i(x) + b − B(x)                  (blur model, main paper Eq. 6)

The 12 trajectory unknowns enter only through the n virtual poses, so the Jacobian is

    ∂r/∂y = e^a / n · Σ_i  g_i(x) · M_i,   g_i = ∂v_i/∂(p_i, q̄_i)  (1 x 7),   M_i = ∂(p_i, q̄_i)/∂y  (7 x 12)

where M_i is shared by all pixels under a global shutter. With a rolling shutter the virtual poses
are a table over row buckets b (one per image row) and M becomes M_{b,i} = ∂(p, q̄)_{b,i}/∂y, with
∂r/∂y = e^a / n · Σ_i g_i(x) · M_{b(x),i}. Three paths compute g_i and M_i: ``autodiff`` (``jax.jacfwd`` of the
per-sample function and of the trajectory), ``analytic`` (the supplement's corrected formulas:
Eqs. 85, 78-84, 56-58, 48-49, 3-11) and ``tangent`` (the default): g_i by a local perturbation
(t, ω) of each virtual camera, 6 numbers per sample from the plane point alone
(:func:`_sample_tangent`), and M_i the analytic one mapped to (t, ω) once per virtual pose
(:func:`tangent_rows`). The residual function carries a ``custom_jvp`` that returns J @ ẏ, so
``jax.linearize`` inside optimistix computes J once per step. The finer blur-aware levels compute J once,
at their start, and their steps reuse it (:func:`make_frozen_residual_fn`, the chord method;
``tracker.fresh_jacobian_levels``).

A cubic exposure path (``geometry.spline.SplineTrajectory``) has k = 24 unknowns instead of 12
(y = [Δ (k), a, b]); its M has no closed form here and is always ``jax.jacfwd`` of the pose table,
with g_i still from the chosen path.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..blur import blend, per_pixel_poses, synthesize, virtual_pq, virtual_pq_table, virtual_sample
from ..geometry import quaternion as quat
from ..geometry.camera import PinholeCamera
from ..geometry.spline import SplineTrajectory
from ..geometry.trajectory import ExposureTrajectory, virtual_times
from ..paper import jacobians as pj

__all__ = ["LevelProblem", "FrozenJacobian", "residuals_and_jacobian", "make_residual_fn", "make_frozen_residual_fn", "robust"]


class LevelProblem(eqx.Module):
    """Everything one pyramid level's solve needs (fixed shapes; R = points x 8)."""

    ref_image: Float[Array, "H W"]
    camera: PinholeCamera
    anchor: ExposureTrajectory | SplineTrajectory  # y = 0 corresponds to this trajectory
    rays: Float[Array, "R 3"]  # unit rays π⁻¹(x) of the residual pixels (Eq. 62)
    depths: Float[Array, "R"]  # plane depth d of each residual pixel
    observed: Float[Array, "R"]  # B(x), the blurry frame at the residual pixels
    mask: Bool[Array, "R"]
    n: int = eqx.field(static=True)
    jacobian: str = eqx.field(static=True)  # "tangent" | "analytic" | "autodiff"
    times: Float[Array, "B n"] | None = None  # rolling shutter: s(v, i) per row bucket (None: global shutter)
    rows: Int[Array, "R"] | None = None  # the row bucket of each residual pixel (with ``times``)


def _sample(problem: LevelProblem, pq, ray, d):
    """v_i for one residual pixel at virtual pose pq = [p (3), q̄ (4)]: the blur model's sample."""
    return virtual_sample(problem.ref_image, problem.camera, pq, ray, d)


def _trajectory(problem: LevelProblem, y12):
    return problem.anchor.plus(y12)


def _times(problem: LevelProblem, dtype) -> Float[Array, "B n"]:
    """The virtual frames' normalised times per row bucket (one bucket: the global shutter)."""
    return virtual_times(problem.n, dtype)[None] if problem.times is None else problem.times


def _rows(problem: LevelProblem) -> Int[Array, " R"]:
    return jnp.zeros(problem.depths.shape[0], jnp.int32) if problem.rows is None else problem.rows


def _pose_table(problem: LevelProblem, y12) -> Float[Array, "B n 7"]:
    """The virtual poses [p, q̄] per row bucket and virtual frame at y."""
    traj = _trajectory(problem, y12)
    return virtual_pq(traj, problem.n)[None] if problem.times is None else virtual_pq_table(traj, problem.times)


def _M_autodiff(problem: LevelProblem, y12):
    """M_{b,i} = ∂(p, q̄)_{b,i}/∂y by forward-mode autodiff of the pose table (B x n x 7 x 12)."""
    return jax.jacfwd(lambda yy: _pose_table(problem, yy))(y12)


def _M_analytic(problem: LevelProblem, y12):
    """M_{b,i} from the supplement (``paper.jacobians.virtual_pose_jacobian``: Eqs. 48-49, 56-58
    corrected) at each bucket's times, with the derivative of the update q' = q̄_anchor ⊗ exp(Δr)
    at the current Δr (Eqs. 36-37 and 3-11 corrected)."""
    a = problem.anchor
    traj = _trajectory(problem, y12)
    dq_start = quat.Q(a.start.q) @ pj.exp_jacobian(y12[0:3])  # 4 x 3
    dq_end = quat.Q(a.end.q) @ pj.exp_jacobian(y12[6:9])
    one = lambda si: pj.virtual_pose_jacobian(traj.start.q, traj.end.q, si, dq_start, dq_end)
    return jax.vmap(jax.vmap(one))(_times(problem, y12.dtype))


def chain_rows(G: Float[Array, "n R j"], M: Float[Array, "B n j k"], rows: Int[Array, " R"]) -> Float[Array, "R k"]:
    """Σ_i g_i(x) · M_{b(x),i} for every residual x (one bucket: a single contraction)."""
    if M.shape[0] == 1:
        return jnp.einsum("nrj,njk->rk", G, M[0])
    return jax.vmap(lambda g, b: jnp.einsum("nj,njk->k", g, M[b]), in_axes=(1, 0))(G, rows)


def _sample_autodiff(problem: LevelProblem, pq, ray, d):
    """(v_i, g_i = ∂v_i/∂(p, q̄) by ``jax.jacfwd`` of the per-sample function (7,), valid)."""
    def f(x):
        value, _, _, ok = _sample(problem, x, ray, d)
        return value, (value, ok)

    g, (value, ok) = jax.jacfwd(f, has_aux=True)(pq)
    return value, g, ok


def _sample_with_point_gradient(problem: LevelProblem, pq, ray, d):
    """(v_i, w = ∂v_i/∂p'_3d = ∇I · Eq. 85 (3,), p'_3d, valid) from one bilinear sample (w written
    elementwise, which fuses under vmap)."""
    value, grad, p_ref, ok = _sample(problem, pq, ray, d)
    dproj = pj.projection_jacobian(problem.camera.fx, problem.camera.fy, p_ref)  # 2 x 3
    return value, grad[0] * dproj[0] + grad[1] * dproj[1], p_ref, ok


def _sample_analytic(problem: LevelProblem, pq, ray, d):
    """(v_i, g_i = ∇I · Eq. 85 · Eqs. 78-84 (corrected) (7,), valid) from one bilinear sample."""
    value, w, _, ok = _sample_with_point_gradient(problem, pq, ray, d)
    dp = pj.transfer_jacobian_corrected(pq[3:], pq[:3], ray, d)  # 3 x 7
    return value, jnp.where(ok, w @ dp, 0.0), ok


def _sample_tangent(problem: LevelProblem, pq, ray, d):
    """(v_i, g_i = ∂v_i/∂(t, ω) (6,), valid): the sample's derivative by a translation t and a left
    rotation exp(ω) R_i of the virtual camera. With w = ∇I · Eq. 85 and e = p'_3d − t_i (the ray to
    the plane, e_z = d − t_z), ∂p'/∂t = P = I − e e_zᵀ / e_z and ∂p'/∂ω = −P [e]×, so
    g_i = [a, e × a] with a = Pᵀ w (the 3 x 7 matrix of Eqs. 78-84 is never formed)."""
    value, w, p_ref, ok = _sample_with_point_gradient(problem, pq, ray, d)
    e = p_ref - pq[:3]
    s = (e[0] * w[0] + e[1] * w[1] + e[2] * w[2]) / jnp.where(ok, e[2], 1.0)  # e·w / e_z as a sum: it fuses, a dot does not
    a = w - s * jnp.array([0.0, 0.0, 1.0], w.dtype)
    return value, jnp.where(ok, jnp.concatenate([a, jnp.cross(e, a)]), 0.0), ok


def tangent_rows(M: Float[Array, "B n 7 k"], pqs: Float[Array, "B n 7"]) -> Float[Array, "B n 6 k"]:
    """∂(t, ω)_{b,i}/∂y from ∂(p, q̄)_{b,i}/∂y: ω = 2 vec(δq̄ ⊗ q̄⁻¹) (Eqs. 38, 40) for the unit q̄_i."""
    def one(m, pq):
        dw = 2 * quat.Q_hat(quat.inverse(pq[3:]))[:3]  # 3 x 4
        return jnp.concatenate([m[:3], dw @ m[3:]], axis=0)

    return jax.vmap(jax.vmap(one))(M, pqs)


SAMPLERS = {"tangent": _sample_tangent, "analytic": _sample_analytic, "autodiff": _sample_autodiff}


def _jacobian(problem: LevelProblem, yk, pqs: Float[Array, "B n 7"], G: Float[Array, "n R j"], rows, gain) -> Float[Array, "R k"]:
    """∂r/∂y_k = e^a / n · Σ_i g_i · M_{b,i} (M analytic for a straight path unless the path is
    ``autodiff``; in (t, ω) for ``tangent``)."""
    analytic = problem.jacobian != "autodiff" and isinstance(problem.anchor, ExposureTrajectory)
    M = _M_analytic(problem, yk) if analytic else _M_autodiff(problem, yk)
    if problem.jacobian == "tangent":
        M = tangent_rows(M, pqs)
    return (gain / problem.n) * chain_rows(G, M, rows)


def residuals_and_jacobian(y: Float[Array, " Y"], problem: LevelProblem, with_jacobian: bool = True):
    """Residuals r (R,) at y = [Δstart (6), Δend (6), a, b] (a spline: [Δcontrols (24), a, b]) and,
    optionally, J = ∂r/∂y (R, k + 2), both from one pass over the n x R virtual samples.

    Invalid residuals (a sample outside the keyframe, a ray missing the plane, masked pixels) are 0
    with zero Jacobian rows. Also returns the per-residual validity.
    """
    k = problem.anchor.dof
    yk, a, b = y[:k], y[k], y[k + 1]
    pqs, rows = _pose_table(problem, yk), _rows(problem)  # (B, n, 7), (R,)
    gain = jnp.exp(a)
    if not with_jacobian:
        synth, ok = synthesize(problem.ref_image, problem.camera, pqs, problem.rays, problem.depths, rows)
    else:
        sample = SAMPLERS[problem.jacobian]
        values, G, oks = per_pixel_poses(lambda pq, ray, d: sample(problem, pq, ray, d), pqs, rows, problem.rays, problem.depths)
        synth, ok = blend(values, oks)  # values, oks, G: (n, R, ...)
    valid = problem.mask & ok
    r = jnp.where(valid, gain * synth + b - problem.observed, 0.0)
    if not with_jacobian:
        return r, None, valid
    J = jnp.concatenate([_jacobian(problem, yk, pqs, G, rows, gain), (gain * synth)[:, None], jnp.ones_like(synth)[:, None]], axis=1)
    return r, jnp.where(valid[:, None], J, 0.0), valid


def make_residual_fn(with_valid: bool = False):
    """``f(y, problem) -> r`` with a custom JVP ``J @ ẏ`` (J from the problem's Jacobian path); with
    ``with_valid``, ``(r, valid)`` (the mask has no tangent), so a solver's last linearisation also
    gives the residuals' validity without another pass."""

    @jax.custom_jvp
    def f(y, problem):
        r, _, valid = residuals_and_jacobian(y, problem, with_jacobian=False)
        return r, valid

    @f.defjvp
    def f_jvp(primals, tangents):
        y, problem = primals
        y_dot, _ = tangents  # the problem's data is not differentiated
        r, J, valid = residuals_and_jacobian(y, problem, with_jacobian=True)
        return (r, valid), (J @ y_dot, np.zeros(valid.shape, jax.dtypes.float0))

    return f if with_valid else (lambda y, problem: f(y, problem)[0])


class FrozenJacobian(eqx.Module):
    """The photometric Jacobian's path columns ∂r/∂y_k at a level's start y₀ (affine a₀ there),
    reused at every LM step of the level (the chord method: :func:`make_frozen_residual_fn`)."""

    path: Float[Array, "R k"]
    a0: Float[Array, ""]

    def jvp(self, y: Float[Array, " Y"], r: Float[Array, " R"], valid: Bool[Array, " R"], problem: LevelProblem,
            y_dot: Float[Array, " Y"]) -> Float[Array, " R"]:
        """J @ ẏ at y (residuals r, valid where ``valid``; 0 elsewhere): the path columns from y₀
        rescaled by e^(a − a₀) (they are proportional to the gain), the affine ones exact (∂r/∂a =
        e^a·synth = r − b + B, ∂r/∂b = 1). The coefficients are masked, not only the product, so that
        the transpose the linear solver takes stays finite where B is not (NaN pixels)."""
        k = self.path.shape[1]
        a, b = y[k], y[k + 1]
        d_a = jnp.where(valid, r - b + problem.observed, 0.0)
        return jnp.where(valid, jnp.exp(a - self.a0) * (self.path @ y_dot[:k]) + d_a * y_dot[k] + y_dot[k + 1], 0.0)


def make_frozen_residual_fn():
    """``f(y, problem, frozen) -> (r, valid)`` as :func:`make_residual_fn` with ``with_valid``, but
    its JVP uses the :class:`FrozenJacobian` ``frozen``: one forward pass over the samples per LM
    step instead of the samples' derivatives."""

    @jax.custom_jvp
    def f(y, problem, frozen):
        r, _, valid = residuals_and_jacobian(y, problem, with_jacobian=False)
        return r, valid

    @f.defjvp
    def f_jvp(primals, tangents):
        y, problem, frozen = primals
        y_dot = tangents[0]  # the problem's data and the frozen Jacobian are not differentiated
        r, _, valid = residuals_and_jacobian(y, problem, with_jacobian=False)
        return (r, valid), (frozen.jvp(y, r, valid, problem, y_dot), np.zeros(valid.shape, jax.dtypes.float0))

    return f


def robust(r, k):
    """Square-rooted Huber: ½ robust(r)² = Huber_k(r), so least squares minimises the Huber cost."""
    a = jnp.abs(r)
    safe = jnp.where(a > k, a, k)
    return jnp.where(a > k, jnp.sign(r) * jnp.sqrt(2 * k * safe - k * k), r)
