"""One pyramid level of the tracker: its residuals and its Levenberg-Marquardt solve.

The cost of a level is the sum of three named residual blocks over the solver's unknowns z:

* :func:`photometric_residuals`: the blur model against the blurry frame (square-rooted Huber);
* :func:`depth_residuals_block`: the optional RGB-D term (``tracking.geometric``);
* :func:`exposure_prior_residuals`: a weak prior on the exposure motion start⁻¹·end.

:func:`solve_level` is one jit-compiled program per (level shapes, n, static settings): a sequence
compiles once per level.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import optimistix as optx
from jaxtyping import Array, Bool, Float

from ..geometry import quaternion as quat
from ..geometry.camera import PinholeCamera
from ..geometry.spline import ExposurePath, SplineTrajectory
from ..geometry.trajectory import ExposureTrajectory, RowClock
from ..masked import count, masked_mean
from .geometric import depth_residuals
from .points import PATTERN
from .residuals import FrozenJacobian, LevelProblem, make_frozen_residual_fn, make_residual_fn, residuals_and_jacobian, robust

__all__ = ["LevelInputs", "LevelSettings", "Parametrization", "ExposurePrior", "DepthTerm", "LevelObjective", "LevelResult",
           "CurvaturePrior", "control_steps", "curvature_residuals", "residual_pixels", "photometric_residuals", "depth_residuals_block", "exposure_prior_residuals", "solve_level",
           "compiled_programs"]

_TRACES = {"solve_level": 0}

# The damped Gauss-Newton step [J; √λ I] δ = [r; 0] by its normal equations (JᵀJ + λI) δ = Jᵀr and
# Cholesky: a k x k system (k ≤ 26 unknowns) instead of LAPACK's QR of the R x k matrix, whose
# threaded CPU kernel costs far more than the whole residual evaluation. A stiff curvature prior
# (rows ~1e5 x the photometric ones) makes JᵀJ singular in float32: that solve keeps QR.
LINEAR_SOLVER = lx.Normal(lx.Cholesky())


def compiled_programs() -> int:
    """How many level programs the tracker has compiled in this process (one per new signature)."""
    return _TRACES["solve_level"]


class LevelInputs(eqx.Module):
    """What one level's solve reads: the keyframe level, its points, the current frame, the anchor
    (y = 0 is this exposure path), the affine brightness carried over from the coarser level and
    the frame's row clock (rolling shutter; used when the settings say ``rolling``)."""

    ref_image: Float[Array, "H W"]
    camera: PinholeCamera
    cur_image: Float[Array, "H W"]
    pixels: Float[Array, "N 2"]
    depths: Float[Array, " N"]
    valid: Bool[Array, " N"]
    anchor: ExposurePath
    affine_ab: Float[Array, "2"]
    clock: RowClock


class LevelSettings(eqx.Module):
    """Per-level solver settings; the static ones select the compiled program."""

    huber: Float[Array, ""]
    outlier_sigma: Float[Array, ""]
    rtol: Float[Array, ""]
    atol: Float[Array, ""]
    curvature_sigma: Float[Array, ""]  # a cubic path's curvature prior (radians; 0 = off)
    n: int = eqx.field(static=True)
    jacobian: str = eqx.field(static=True)
    max_steps: int = eqx.field(static=True)
    rigid: bool = eqx.field(static=True)
    affine: bool = eqx.field(static=True)
    use_outliers: bool = eqx.field(static=True)
    rolling: bool = eqx.field(static=True, default=False)  # per-row virtual poses (readout fraction > 0)
    curved: bool = eqx.field(static=True, default=False)  # a cubic path's curvature prior is on
    frozen: bool = eqx.field(static=True, default=False)  # the photometric Jacobian computed once, at the level's start


class Parametrization(eqx.Module):
    """The solver's unknowns z → y = [Δstart (6), Δend (6), a, b]: 12 blur-aware unknowns or 6 rigid
    ones (start = end), plus 2 affine ones when estimated (added to the coarser level's a, b). A
    cubic path (``dof`` 24) has a local update of each of its four control poses instead."""

    affine_ab: Float[Array, "2"]
    rigid: bool = eqx.field(static=True)
    affine: bool = eqx.field(static=True)
    dof: int = eqx.field(static=True, default=12)  # the path's unknowns (the anchor's ``dof``)

    @property
    def motion_size(self) -> int:
        return 6 if self.rigid else self.dof

    def size(self) -> int:
        return self.motion_size + (2 if self.affine else 0)

    def expand(self, z: Float[Array, " m"]) -> Float[Array, " Y"]:
        m = self.motion_size
        y12 = jnp.concatenate([z[:6], z[:6]]) if self.rigid else z[:m]
        ab = z[m : m + 2] if self.affine else jnp.zeros(2, z.dtype)
        return jnp.concatenate([y12, self.affine_ab + ab])


class ExposurePrior(eqx.Module):
    """Gaussian prior on the exposure motion b = [log(start⁻¹·end rotation), its translation] around
    the initial guess b₀: residual weight · scale · (b − b₀), with translation scaled by 1/median depth."""

    blur0: Float[Array, "6"]
    scale: Float[Array, "6"]
    weight: Float[Array, ""]


class CurvaturePrior(eqx.Module):
    """Gaussian prior on a cubic path's bend: residual weight · scale · (v_{j+1} − v_j), v_j = [log of
    control j⁻¹·j+1 rotation, translation step] (zero on a constant-velocity path), translation
    scaled by 1/median depth as in :class:`ExposurePrior`."""

    scale: Float[Array, "6"]
    weight: Float[Array, ""]


class DepthTerm(eqx.Module):
    """The optional RGB-D residuals of one level (``tracking.geometric``) and their weights."""

    cur_depth: Float[Array, "H W"]
    pixels: Float[Array, "M 2"]
    depths: Float[Array, " M"]
    valid: Bool[Array, " M"]
    weight: Float[Array, ""]
    huber: Float[Array, ""]
    outlier: Float[Array, ""]
    edge: Float[Array, ""]
    sigma: Float[Array, "2"]


class LevelObjective(eqx.Module):
    """Everything the level's least-squares function reads (passed to optimistix as ``args``)."""

    problem: LevelProblem
    param: Parametrization
    huber: Float[Array, ""]
    prior: ExposurePrior | None
    depth: DepthTerm | None
    curvature: CurvaturePrior | None = None
    frozen: FrozenJacobian | None = None  # the photometric Jacobian at the level's start (None: recomputed at every step)


class LevelResult(eqx.Module):
    """A level's outcome: the exposure path and affine (a, b) it found, the RMS photometric error
    after and before, its contrast-normalised RMS, the valid residuals, convergence and LM steps."""

    trajectory: ExposurePath
    affine_ab: Float[Array, "2"]
    rms: Float[Array, ""]
    rms_init: Float[Array, ""]
    nrms: Float[Array, ""]
    valid: Array
    converged: Array
    steps: Array


def exposure_motion(traj: ExposurePath) -> Float[Array, "6"]:
    """b = [log(q) (3), t (3)] of start⁻¹·end: the camera's motion during the exposure."""
    rel = traj.start.inverse().compose(traj.end)
    return jnp.concatenate([quat.log(rel.q), rel.t])


def residual_pixels(camera: PinholeCamera, cur_image, pixels, depths, valid, anchor: ExposurePath):
    """(rays, plane depths, observed intensities, mask, rows) of the residual pixels: each keyframe
    point projected into the current frame with the anchor's middle pose, rounded, plus the 8-pixel
    pattern; ``rows`` is each pixel's image row (its rolling-shutter bucket)."""
    mid = anchor.middle().inverse()  # T_cur_ref at mid-exposure
    P = jax.vmap(camera.backproject)(pixels, depths)
    x_cur = jax.vmap(lambda p: camera.project(mid.apply(p)))(P)
    ok_pt = valid & jnp.all(jnp.isfinite(x_cur), axis=1) & (jax.vmap(mid.apply)(P)[:, 2] > 1e-3)
    base = jnp.round(jnp.where(ok_pt[:, None], x_cur, 0.0))
    res = (base[:, None, :] + jnp.asarray(PATTERN)[None]).reshape(-1, 2)
    h, w = cur_image.shape
    inside = (res[:, 0] >= 1) & (res[:, 1] >= 1) & (res[:, 0] <= w - 2) & (res[:, 1] <= h - 2)
    mask = jnp.repeat(ok_pt, PATTERN.shape[0]) & inside
    col = jnp.clip(res[:, 0], 0, w - 1).astype(jnp.int32)
    row = jnp.clip(res[:, 1], 0, h - 1).astype(jnp.int32)
    rays = jax.vmap(camera.unit_ray)(res)
    return rays, jnp.repeat(depths, PATTERN.shape[0]), cur_image[row, col], mask, row


def reject_outlier_patches(problem: LevelProblem, r0: Float[Array, " R"], v0: Bool[Array, " R"], k) -> LevelProblem:
    """Drop the patches whose mean squared residual r0 (at the level's start, valid where v0) exceeds
    mean + k·std over the patches."""
    npat = PATTERN.shape[0]
    vp = v0.reshape(-1, npat)
    cost = masked_mean(r0.reshape(-1, npat) ** 2, vp, axis=1)
    good = vp.sum(1) > npat // 2
    mean = masked_mean(cost, good)
    std = jnp.sqrt(masked_mean((cost - mean) ** 2, good))
    keep = cost <= mean + k * std
    return eqx.tree_at(lambda p: p.mask, problem, problem.mask & jnp.repeat(keep, npat))


_RESIDUAL = make_residual_fn(with_valid=True)
_FROZEN_RESIDUAL = make_frozen_residual_fn()


def photometric_residuals(y, problem: LevelProblem, huber, frozen: FrozenJacobian | None = None) -> tuple[Float[Array, " R"], tuple]:
    """The blur model's photometric residuals at y, square-rooted Huber (custom JVP: J @ ẏ, with J
    ``frozen`` at the level's start when given), and the plain residuals with their validity."""
    r, valid = _RESIDUAL(y, problem) if frozen is None else _FROZEN_RESIDUAL(y, problem, frozen)
    return robust(r, huber), (r, valid)


def depth_residuals_block(traj: ExposurePath, camera: PinholeCamera, term: DepthTerm) -> Float[Array, " M"]:
    """The depth term at the path's middle pose (:func:`depth_residuals`, truncated at ``outlier`` σ;
    a point without a valid depth sample costs nothing), weighted and square-rooted Huber."""
    r, _ = depth_residuals(traj.middle(), camera, term.cur_depth, term.pixels, term.depths, term.valid, term.edge,
                           (term.sigma[0], term.sigma[1]), term.outlier)
    return term.weight * robust(r, term.huber)


def exposure_prior_residuals(traj: ExposurePath, prior: ExposurePrior) -> Float[Array, "6"]:
    """The exposure-motion prior's six residuals."""
    return prior.weight * prior.scale * (exposure_motion(traj) - prior.blur0)


def control_steps(path: SplineTrajectory) -> Float[Array, "3 6"]:
    """v_j = [log(q_j⁻¹ q_{j+1}), t_{j+1} − t_j] between a cubic path's consecutive control poses."""
    q, t = path.controls.q, path.controls.t
    rot = jax.vmap(lambda a, b: quat.log(quat.product(quat.inverse(a), b)))(q[:3], q[1:])
    return jnp.concatenate([rot, t[1:] - t[:3]], axis=1)


def curvature_residuals(path: SplineTrajectory, prior: CurvaturePrior) -> Float[Array, "12"]:
    """The curvature prior's residuals: the two second differences of the control steps, weighted."""
    v = control_steps(path)
    return (prior.weight * prior.scale * (v[1:] - v[:2])).reshape(-1)


def objective(z, obj: LevelObjective):
    """The level's least-squares function: the residual blocks stacked, and (aux) the plain
    photometric residuals with their validity."""
    y = obj.param.expand(z)
    traj = obj.problem.anchor.plus(y[: obj.param.dof])
    photometric, aux = photometric_residuals(y, obj.problem, obj.huber, obj.frozen)
    parts = [photometric]
    if obj.depth is not None:
        parts.append(depth_residuals_block(traj, obj.problem.camera, obj.depth))
    if obj.prior is not None:
        parts.append(exposure_prior_residuals(traj, obj.prior))
    if obj.curvature is not None:
        parts.append(curvature_residuals(traj, obj.curvature))
    return (jnp.concatenate(parts) if len(parts) > 1 else parts[0]), aux


def make_prior(level: LevelInputs, problem: LevelProblem, blur0, sigma_intensity, min_rad, rel) -> ExposurePrior:
    """The prior's scale (translation / median point depth) and weight (σ_I / σ_b · √valid residuals,
    σ_b = min_rad + rel·|b₀| scaled)."""
    dtype = level.ref_image.dtype
    zmed = jnp.nanmedian(jnp.where(level.valid, level.depths, jnp.nan))
    scale = jnp.concatenate([jnp.ones(3, dtype), jnp.full(3, 1.0 / jnp.where(jnp.isfinite(zmed), zmed, 1.0))])
    sqrt_valid = jnp.sqrt(count(problem.mask, dtype))
    weight = sigma_intensity / (min_rad + rel * jnp.linalg.norm(scale * blur0)) * sqrt_valid
    return ExposurePrior(blur0, scale, weight)


def _summary(problem: LevelProblem, r: Float[Array, " R"], valid: Bool[Array, " R"], r0: Float[Array, " R"],
             valid0: Bool[Array, " R"]) -> tuple:
    """(rms of the residuals r (valid where ``valid``), rms at the start (r0, valid0), nrms = rms /
    contrast of the observed pixels, valid residuals); residuals outside the problem's mask do not count."""
    nvalid = valid.sum()
    rms = jnp.sqrt(jnp.sum(r * r) / count(valid, r.dtype))
    obs_mean = masked_mean(problem.observed, valid)
    obs_std = jnp.sqrt(masked_mean((problem.observed - obs_mean) ** 2, valid))
    valid0 = valid0 & problem.mask
    rms0 = jnp.sqrt(jnp.sum(jnp.where(valid0, r0, 0.0) ** 2) / count(valid0, r0.dtype))
    return rms, rms0, rms / jnp.maximum(obs_std, 1e-6), nvalid


@jax.jit
def solve_level(level: LevelInputs, settings: LevelSettings, prior: tuple | None, depth: DepthTerm | None) -> LevelResult:
    """One level's LM solve (optimistix, RMS termination norm, :data:`LINEAR_SOLVER`). ``prior``: None (rigid) or
    (b₀, σ_I, min_rad, rel) of :func:`make_prior`."""
    _TRACES["solve_level"] += 1  # runs once per compiled signature
    rays, d, observed, mask, rows = residual_pixels(level.camera, level.cur_image, level.pixels, level.depths, level.valid, level.anchor)
    times = level.clock.times(jnp.arange(level.cur_image.shape[0], dtype=d.dtype), settings.n) if settings.rolling else None
    problem = LevelProblem(level.ref_image, level.camera, level.anchor, rays, d, observed, mask, settings.n, settings.jacobian,
                           times, rows if settings.rolling else None)
    param = Parametrization(level.affine_ab, settings.rigid, settings.affine, level.anchor.dof)
    z0 = jnp.zeros(param.size(), level.ref_image.dtype)
    y0 = param.expand(z0)
    r0, J0, valid0 = residuals_and_jacobian(y0, problem, with_jacobian=settings.frozen)
    if settings.use_outliers:
        problem = reject_outlier_patches(problem, r0, valid0, settings.outlier_sigma)
    prior_term = None if prior is None else make_prior(level, problem, *prior)
    curvature = None
    if prior is not None and isinstance(level.anchor, SplineTrajectory) and settings.curved:
        curvature = CurvaturePrior(prior_term.scale, prior[1] / settings.curvature_sigma * jnp.sqrt(count(problem.mask, d.dtype)))
    k = param.dof
    frozen = FrozenJacobian(J0[:, :k], y0[k]) if settings.frozen else None
    obj = LevelObjective(problem, param, settings.huber, prior_term, depth, curvature, frozen)
    solver = optx.LevenbergMarquardt(rtol=settings.rtol, atol=settings.atol, norm=optx.rms_norm, linear_solver=lx.QR() if curvature is not None else LINEAR_SOLVER)
    sol = optx.least_squares(objective, solver, z0, args=obj, has_aux=True, max_steps=settings.max_steps, throw=False)
    y = param.expand(sol.value)
    rms, rms0, nrms, nvalid = _summary(problem, *sol.state.aux, r0, valid0)  # the aux of the last accepted step, at sol.value
    traj = level.anchor.plus(y[:k]).normalized()
    converged = sol.result == optx.RESULTS.successful
    return LevelResult(traj, y[k : k + 2], rms, rms0, nrms, nvalid, converged, sol.stats["num_steps"])
