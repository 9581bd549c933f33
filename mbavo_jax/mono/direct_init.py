"""Initialisation of the monocular system from images alone, directly (DSO's coarse initialiser,
blur-aware): the same contract as :class:`mono.init.TwoViewTracker`.

The reference frame's points are pixels of strong gradient spread over the image
(:func:`mono.candidates.select_candidates`), every inverse depth starting at 1. Each new frame is
aligned to the reference coarse to fine (one set of points, each pyramid level seeing them at its
scale): the relative pose, affine brightness (a, b) and every point's inverse depth, by
Levenberg-Marquardt on the Huber photometric error of DSO's 8-pixel pattern with the inverse depths
eliminated by the Schur complement (the reduced system is 8x8); Jacobians by forward-mode autodiff.
DSO's priors: while the translation is small, a strong prior pulls the inverse depths to 1 and the
translation to 0; once its energy passes a cap (the translation is ``init_direct_snap`` of the
depth) the prior lets go ("snapped") and each inverse depth is pulled instead to a smoothed value,
0.2 of its own and 0.8 of the median of its neighbours' smoothed values. DSO's hand-over rule: the
system starts ``init_direct_frames`` frames after the alignment snapped.

Blur-aware: the current (blurry) frame at a point is compared with the reference image warped along
``init_direct_blur_samples`` virtual poses of the current frame's exposure path (Eq. 6,
:func:`blur.synthesize`), the path given by the constant-velocity motion from the previous frame and
the exposure fraction ``init_direct_exposure`` of the frame interval (as
``tracking.motion.exposure_from_velocity``); one sample is DSO's residual.

Failures are reasons in ``TwoView.reason``, never raised; ``restart`` asks the caller to start again
from a later frame (too little texture, or the alignment diverged).
"""

from __future__ import annotations

import dataclasses
import functools
import typing

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int
from scipy.spatial import cKDTree

from ..blur import virtual_pq
from ..config import MonoConfig
from ..geometry import ExposureTrajectory, PinholeCamera, Pose
from ..geometry.transfer import plane_transfer
from ..image import bilinear_with_gradient, linearize, pyramid
from ..tracking.motion import exposure_from_velocity
from ..tracking.points import PATTERN
from .candidates import select_candidates
from .init import TwoView, _failed

__all__ = ["DirectInitializer", "Reference", "Alignment", "align_level", "pyramid_levels"]

# LM iterations per level, finest first (DSO's); more levels take the last count.
LEVEL_ITERATIONS = (5, 5, 10, 30, 50)
MAX_LEVELS = 5
MIN_ROWS = 30  # the coarsest level keeps at least this many rows
PRIOR_WEIGHT = (150.0 / 255.0) ** 2  # DSO's alphaW on [0, 1] intensities: (d - 1)² and |t|² per point
COUPLING = (1.0 / 255.0) ** 2  # DSO's couplingWeight: (d - smoothed d)² per point, once snapped
SMOOTHING = 0.8  # DSO's regWeight: the smoothed inverse depth's share of the neighbours' median
NEIGHBOURS = 10
OUTLIER_ENERGY = 20.0 * len(PATTERN) * (12.0 / 255.0) ** 2  # DSO's point outlier energy (20 x outlierTH)
MAX_PIXEL_STEP = 0.25  # px: an inverse-depth step moves the point at most this far (DSO's)
IDEPTH_RANGE = (1e-3, 50.0)
BORDER = 2.0  # px of the level image a pattern sample keeps from the border
DEPTH_NOISE = 9.0 / 255.0  # photometric noise that a converged point's inverse-depth uncertainty is measured with


class Settings(typing.NamedTuple):
    """The static part of one level's solve (hashable)."""

    samples: int
    exposure: float
    huber: float
    snap: float


class Reference(eqx.Module):
    """The reference frame: its linear-radiance pyramid (L, H, W), each level padded to the full
    size by repeating its border; its points (level-0 pixels (N, 2), ``valid`` (N,)) and each
    point's nearest points (N, K) (``near``: a real neighbour)."""

    images: Float[Array, "L H W"]
    sizes: Float[Array, "L 2"]
    pixels: Float[Array, "N 2"]
    valid: Bool[Array, " N"]
    neighbours: Int[Array, "N K"]
    near: Bool[Array, "N K"]


class Alignment(eqx.Module):
    """The unknowns: the reference seen from the current frame ``T_cur_ref`` (p_cur = T.apply(p_ref)),
    affine brightness (a, b) with I_cur ≈ e^a I_ref + b, inverse depths (N,), their smoothed values
    (DSO's iR) and whether the prior has let go."""

    T_cur_ref: Pose
    affine: Float[Array, "2"]
    idepth: Float[Array, " N"]
    smooth: Float[Array, " N"]
    snapped: Bool[Array, ""]


class Fit(eqx.Module):
    """A level's last linearisation: each point's fit (``good``), whether its whole pattern is in view
    (``seen``), the photometric information of its
    inverse depth (Σ w J_d², without priors) and its pattern's RMS residual."""

    good: Bool[Array, " N"]
    seen: Bool[Array, " N"]
    information: Float[Array, " N"]
    rms: Float[Array, " N"]


def pyramid_levels(height: int) -> int:
    """Levels used: at most ``MAX_LEVELS``, the coarsest keeping ``MIN_ROWS`` rows."""
    levels = 1
    while levels < MAX_LEVELS and (height >> levels) >= MIN_ROWS:
        levels += 1
    return levels


def padded_pyramid(image: Float[np.ndarray, "H W"], levels: int) -> tuple[np.ndarray, np.ndarray]:
    """The 2x2 pyramid of ``image``, each level padded to the full size by edge repetition, and the
    levels' sizes (L, 2) as (width, height)."""
    h, w = image.shape
    out, sizes = [], []
    for level in pyramid(image, levels):
        level = np.asarray(level, np.float32)
        out.append(np.pad(level, ((0, h - level.shape[0]), (0, w - level.shape[1])), mode="edge"))
        sizes.append((level.shape[1], level.shape[0]))
    return np.stack(out), np.asarray(sizes, np.float32)


def nearest_points(pixels: Float[np.ndarray, "N 2"], valid: Bool[np.ndarray, " N"]) -> tuple[np.ndarray, np.ndarray]:
    """The ``NEIGHBOURS`` nearest valid points of each point (indices (N, K), and whether each is real)."""
    n = len(pixels)
    idx = np.zeros((n, NEIGHBOURS), np.int32)
    near = np.zeros((n, NEIGHBOURS), bool)
    live = np.flatnonzero(valid)
    k = min(NEIGHBOURS, len(live) - 1)
    if k < 1:
        return idx, near
    _, found = cKDTree(pixels[live]).query(pixels[live], k=k + 1)
    idx[live, :k] = live[found[:, 1:]]
    near[live, :k] = True
    return idx, near


def level_camera(camera: PinholeCamera, level) -> PinholeCamera:
    """The intrinsics of pyramid ``level`` (traced) on the full-size (padded) image."""
    f = 0.5 ** jnp.asarray(level, jnp.float32)
    return PinholeCamera(camera.fx * f, camera.fy * f, (camera.cx + 0.5) * f - 0.5, (camera.cy + 0.5) * f - 0.5,
                         camera.width, camera.height)


# ------------------------------------------------------------------------------------ residuals


class Problem(eqx.Module):
    """What one level's residuals see: both images, the level camera and size, the points' level
    pixels and the previous frame's pose (for the exposure path)."""

    ref: Float[Array, "H W"]
    cur: Float[Array, "H W"]
    camera: PinholeCamera
    size: Float[Array, "2"]
    pixels: Float[Array, "N 2"]
    T_prev_ref: Pose


def exposure_poses(problem: Problem, T_cur_ref: Pose, settings: Settings) -> Float[Array, "1 n 7"]:
    """The current frame's n virtual poses T_ref_i (rows [t, q̄]): its exposure path about the mid pose
    at the constant velocity from the previous frame, exposed ``settings.exposure`` of the interval."""
    T_ref_cur = T_cur_ref.inverse()
    about = exposure_from_velocity(problem.T_prev_ref.compose(T_ref_cur), 1.0, settings.exposure)
    return virtual_pq(ExposureTrajectory(T_ref_cur.compose(about.start), T_ref_cur.compose(about.end)), settings.samples)[None]


def warp(problem: Problem, T_cur_ref: Pose, idepth: Float[Array, " N"]):
    """The pattern pixels of each point in the reference (N, P, 2) and where they land in the current
    frame (N, P, 2), with validity (in front, inside the level image with ``BORDER``)."""
    cam = problem.camera
    x_ref = problem.pixels[:, None, :] + jnp.asarray(PATTERN)[None]
    X = jax.vmap(jax.vmap(cam.backproject, (0, None)))(x_ref, 1.0 / idepth)
    Xc = jax.vmap(jax.vmap(T_cur_ref.apply))(X)
    front = Xc[..., 2] > 1e-6
    x_cur = jax.vmap(jax.vmap(cam.project))(jnp.where(front[..., None], Xc, jnp.array([0.0, 0.0, 1.0])))
    ok = front & inside(x_cur, problem.size, BORDER)
    return x_ref, jnp.where(ok[..., None], x_cur, BORDER), ok


def inside(x: Float[Array, "... 2"], size: Float[Array, "2"], border: float) -> Bool[Array, "..."]:
    """Whether pixels x lie at least ``border`` inside a level image of ``size`` (width, height)."""
    return (x[..., 0] >= border) & (x[..., 1] >= border) & (x[..., 0] <= size[0] - 1 - border) & (x[..., 1] <= size[1] - 1 - border)


def geometry(problem: Problem, T_cur_ref: Pose, idepth: Float[Array, " N"], settings: Settings):
    """Where each pattern pixel is sampled: in the current frame (N, P, 2), and in the reference for
    each virtual pose (N, P, n, 2): the pattern pixel itself for one sample, else the current pixel
    transferred through the frontal-parallel plane at the point's depth by each virtual pose
    (Eqs. 61-68, as :func:`blur.synthesize` does); and validity (N, P)."""
    x_ref, x_cur, ok = warp(problem, T_cur_ref, idepth)
    if settings.samples == 1:
        return x_cur, x_ref[:, :, None, :], ok
    pqs = exposure_poses(problem, T_cur_ref, settings)[0]

    def transfer(x, d):
        return jax.vmap(lambda pq: plane_transfer(Pose(pq[3:], pq[:3]), problem.camera, x, d))(pqs)

    ys, ok_y = jax.vmap(jax.vmap(transfer, (0, None)))(x_cur, 1.0 / idepth)
    ok = ok & jnp.all(ok_y & inside(ys, problem.size, 0.0), axis=-1)
    return x_cur, jnp.where(ok[..., None, None], ys, 0.0), ok


def samples(image: Float[Array, "H W"], x: Float[Array, "... 2"]):
    """Bilinear samples of ``image`` at pixels x with their gradients and validity."""
    flat = x.reshape(-1, 2)
    value, grad, ok = jax.vmap(lambda p: bilinear_with_gradient(image, p))(flat)
    return value.reshape(x.shape[:-1]), grad.reshape(x.shape), ok.reshape(x.shape[:-1])


def residuals(problem: Problem, T_cur_ref: Pose, affine: Float[Array, "2"], idepth: Float[Array, " N"],
              settings: Settings) -> tuple[Float[Array, "N P"], Bool[Array, "N P"]]:
    """r = I_cur(x_cur) − (e^a B + b) for each pattern pixel (DSO's residual; B by Eq. 6): B is the
    mean of the reference sampled at the virtual poses' pixels of :func:`geometry`."""
    r, ok, _, _ = _residuals(problem, T_cur_ref, affine, idepth, settings)
    return r, ok


def _residuals(problem: Problem, T_cur_ref: Pose, affine, idepth, settings: Settings):
    """:func:`residuals` with the image gradients: (r, ok, (∇I_cur (N, P, 2), ∇I_ref (N, P, n, 2)), B (N, P))."""
    x_cur, ys, ok = geometry(problem, T_cur_ref, idepth, settings)
    cur, g_cur, ok_c = samples(problem.cur, x_cur)
    ref, g_ref, ok_r = samples(problem.ref, ys)
    blurred = jnp.mean(ref, axis=-1)
    ok = ok & ok_c & jnp.all(ok_r, axis=-1)
    r = cur - (jnp.exp(affine[0]) * blurred + affine[1])
    return jnp.where(ok, r, 0.0), ok, (g_cur, g_ref), blurred


def jacobians(problem: Problem, x: Alignment, settings: Settings):
    """Residuals (N, P), validity, their Jacobian (N, P, 8) by (Δr, Δt, a, b) (the pose update of
    ``Pose.plus``), by each point's own inverse depth (N, P), and |∂x_cur/∂d| per point (N,) (the
    largest over its pattern). The sample positions of :func:`geometry` are differentiated in forward
    mode (6 pose directions and one for all inverse depths at once: each point's positions depend on
    its own inverse depth only) and chained with the image gradients. The blurred reference depends
    on the pose through the exposure path too (its velocity is the motion from the previous frame)."""
    r, ok, (g_cur, g_ref), blurred = _residuals(problem, x.T_cur_ref, x.affine, x.idepth, settings)

    def positions(delta, idepth):
        x_cur, ys, _ = geometry(problem, x.T_cur_ref.plus(delta), idepth, settings)
        return x_cur, ys

    # one forward-mode Jacobian by 7 directions: the pose update and one shift s of every inverse depth (d_i + s).
    # (A separate jvp for the depths in the same program made XLA return the translation columns wrong.)
    dx, dys = jax.jacfwd(lambda v: positions(v[:6], x.idepth + v[6]))(jnp.zeros(7, jnp.float32))  # (N, P, 2, 7), (N, P, n, 2, 7)
    gain = jnp.exp(x.affine[0])
    J = jnp.sum(g_cur[..., None] * dx, -2) - gain * jnp.mean(jnp.sum(g_ref[..., None] * dys, -2), -2)  # (N, P, 7)
    Jc = jnp.concatenate([J[..., :6], -gain * blurred[..., None], -jnp.ones_like(blurred)[..., None]], -1)
    shift = jnp.max(jnp.linalg.norm(dx[..., 6], axis=-1), axis=1)
    return r, ok, jnp.where(ok[..., None], Jc, 0.0), jnp.where(ok, J[..., 6], 0.0), shift


# ------------------------------------------------------------------------------- normal equations


class System(eqx.Module):
    """The photometric normal equations at one estimate (DSO's calcResAndGS): the 8x8 block of
    (pose (Δr, Δt), a, b) summed over good points, each point's coupling (N, 8) and inverse-depth
    terms (N,), the per-point energies (N,) and fit."""

    H: Float[Array, "8 8"]
    b: Float[Array, "8"]
    hcd: Float[Array, "N 8"]
    hdd: Float[Array, " N"]
    bd: Float[Array, " N"]
    energy: Float[Array, " N"]
    shift: Float[Array, " N"]
    fit: Fit


def huber(r, threshold: float):
    """(weight, energy) of Huber residuals: w = min(1, k/|r|), E = w r² (2 − w) (DSO's)."""
    a = jnp.abs(r)
    w = jnp.where(a < threshold, 1.0, threshold / jnp.maximum(a, threshold))
    return w, w * r * r * (2.0 - w)


def linearise(problem: Problem, x: Alignment, valid: Bool[Array, " N"], settings: Settings) -> System:
    """The Huber-weighted normal equations of the residuals at ``x`` (:func:`jacobians`)."""
    r, ok, Jc, Jd, shift = jacobians(problem, x, settings)
    w, e = huber(r, settings.huber)
    energy = jnp.sum(jnp.where(ok, e, 0.0), axis=1)
    good = valid & jnp.all(ok, axis=1) & (energy < OUTLIER_ENERGY)
    w = jnp.where(good[:, None] & ok, w, 0.0)
    hdd = jnp.sum(w * Jd * Jd, axis=1)
    rms = jnp.sqrt(jnp.mean(r * r, axis=1))
    return System(jnp.einsum("np,npi,npj->ij", w, Jc, Jc), jnp.einsum("np,npi,np->i", w, Jc, r),
                  jnp.einsum("np,npi,np->ni", w, Jc, Jd), hdd, jnp.sum(w * Jd * r, axis=1),
                  jnp.where(good, energy, OUTLIER_ENERGY), shift, Fit(good, valid & jnp.all(ok, axis=1), hdd, rms))


class Priors(eqx.Module):
    """DSO's priors at one estimate: their energy, the terms they add to the point blocks and to the
    translation, and whether the depth-1 prior is capped (let go)."""

    energy: Float[Array, ""]
    hdd: Float[Array, " N"]
    bd: Float[Array, " N"]
    weight_t: Float[Array, ""]
    capped: Bool[Array, ""]


def priors(x: Alignment, good: Bool[Array, " N"], valid: Bool[Array, " N"], snap: float) -> Priors:
    """The depth-1 and zero-translation prior α (|t|² N + Σ (d − 1)²), capped at α snap² N; once
    capped, the coupling of each inverse depth to its smoothed value instead (DSO's calcResAndGS and calcEC)."""
    count = jnp.sum(valid).astype(jnp.float32)
    alpha = PRIOR_WEIGHT * (jnp.sum(jnp.where(good, (x.idepth - 1.0) ** 2, 0.0)) + jnp.sum(x.T_cur_ref.t**2) * count)
    cap = PRIOR_WEIGHT * snap**2 * count
    capped = alpha > cap
    weight = jnp.where(capped, 0.0, PRIOR_WEIGHT)
    coupling = jnp.where(capped, COUPLING, 0.0)
    hdd = jnp.where(good, weight + coupling, 0.0)
    bd = jnp.where(good, weight * (x.idepth - 1.0) + coupling * (x.idepth - x.smooth), 0.0)
    couple_energy = coupling * jnp.sum(jnp.where(good, (x.idepth - x.smooth) ** 2, 0.0))
    return Priors(jnp.minimum(alpha, cap) + couple_energy, hdd, bd, weight * count, capped)


def lm_step(system: System, prior: Priors, x: Alignment, good: Bool[Array, " N"], lam) -> tuple[Float[Array, "8"], Float[Array, " N"]]:
    """One damped Gauss-Newton step (DSO's): the 8x8 system with the inverse depths eliminated
    (Schur complement), solved with Jacobi scaling; each inverse depth back-substituted and limited to
    ``MAX_PIXEL_STEP`` of image motion. Points that do not fit do not move."""
    H = system.H + jnp.diag(jnp.concatenate([jnp.zeros(3), jnp.full(3, prior.weight_t), jnp.zeros(2)]))
    b = system.b + jnp.concatenate([jnp.zeros(3), prior.weight_t * x.T_cur_ref.t, jnp.zeros(2)])
    hdd = (system.hdd + prior.hdd) * (1.0 + lam)
    inv = jnp.where(good & (hdd > 0), 1.0 / jnp.where(hdd > 0, hdd, 1.0), 0.0)
    bd = system.bd + prior.bd
    S = H + jnp.diag(jnp.diag(H)) * lam - jnp.einsum("n,ni,nj->ij", inv, system.hcd, system.hcd)
    g = b - jnp.einsum("n,ni,n->i", inv, system.hcd, bd)
    scale = 1.0 / jnp.sqrt(jnp.maximum(jnp.diag(S), 1e-12))
    step = -scale * jnp.linalg.solve(S * scale[:, None] * scale[None, :] + 1e-9 * jnp.eye(8), g * scale)
    dd = -(bd + system.hcd @ step) * inv
    limit = MAX_PIXEL_STEP / jnp.maximum(system.shift, 1e-10)
    return step, jnp.clip(dd, -limit, limit)


def smoothed(x: Alignment, good: Bool[Array, " N"], neighbours: Int[Array, "N K"], near: Bool[Array, "N K"]) -> Float[Array, " N"]:
    """DSO's optReg: each good point's smoothed inverse depth becomes 0.2 of its own and 0.8 of the
    median of its good neighbours' smoothed values (when it has at least 3); all 1 before snapping."""
    use = near & good[neighbours]
    values = jnp.where(use, x.smooth[neighbours], jnp.nan)
    median = jnp.nanmedian(values, axis=1)
    ok = good & (jnp.sum(use, axis=1) > 2)
    out = jnp.where(ok, (1.0 - SMOOTHING) * x.idepth + SMOOTHING * jnp.where(ok, median, 0.0), x.smooth)
    return jnp.where(x.snapped, out, jnp.ones_like(out))


# ------------------------------------------------------------------------------------ one level


class _Loop(eqx.Module):
    x: Alignment
    system: System
    lam: Float[Array, ""]
    it: Int[Array, ""]
    fails: Int[Array, ""]
    done: Bool[Array, ""]


def _problem(reference: Reference, cur: Float[Array, "L H W"], camera: PinholeCamera, level, T_prev_ref: Pose) -> Problem:
    """Level ``level``'s :class:`Problem` (the points at that level's pixel coordinates)."""
    f = 0.5 ** jnp.asarray(level, jnp.float32)
    return Problem(reference.images[level], cur[level], level_camera(camera, level), reference.sizes[level],
                   (reference.pixels + 0.5) * f - 0.5, T_prev_ref)


def _iterate(problem: Problem, reference: Reference, settings: Settings, state: _Loop, iterations) -> _Loop:
    """One LM iteration (DSO's trackFrame loop): step, re-linearise, accept if the energy (photometric
    with outliers capped, plus the priors) drops; on acceptance the smoothed depths follow."""
    x, sys, valid, first = state.x, state.system, reference.valid, state.it < 0
    prior = priors(x, sys.fit.good, valid, settings.snap)
    step, dd = lm_step(sys, prior, x, sys.fit.good, state.lam)
    step, dd = jnp.where(first, 0.0, step), jnp.where(first, 0.0, dd)  # the first pass only linearises at x
    idepth = jnp.clip(x.idepth + dd, *IDEPTH_RANGE)
    new = Alignment(x.T_cur_ref.plus(step[:6]), x.affine + step[6:], idepth, x.smooth, x.snapped)
    new_sys = linearise(problem, new, valid, settings)
    new_prior = priors(new, new_sys.fit.good, valid, settings.snap)
    accept = first | (jnp.sum(new_sys.energy) + new_prior.energy < jnp.sum(sys.energy) + prior.energy)
    new = Alignment(new.T_cur_ref, new.affine, new.idepth, new.smooth, new.snapped | new_prior.capped)
    new = Alignment(new.T_cur_ref, new.affine, new.idepth, smoothed(new, new_sys.fit.good, reference.neighbours, reference.near),
                    new.snapped)
    x = jax.tree_util.tree_map(lambda a, b: jnp.where(accept, a, b), new, x)
    sys = jax.tree_util.tree_map(lambda a, b: jnp.where(accept, a, b), new_sys, sys)
    lam = jnp.where(first, state.lam, jnp.where(accept, jnp.maximum(state.lam * 0.5, 1e-4), jnp.minimum(state.lam * 4.0, 1e4)))
    fails = jnp.where(accept, 0, state.fails + 1)
    done = ~first & ((state.it + 1 >= iterations) | (fails >= 2) | ~(jnp.linalg.norm(step) > 1e-6))
    return _Loop(x, sys, lam, state.it + 1, fails, done)


@functools.partial(jax.jit, static_argnames=("settings",))
def align_level(reference: Reference, cur: Float[Array, "L H W"], camera: PinholeCamera, level: Int[Array, ""],
                x: Alignment, T_prev_ref: Pose, iterations: Int[Array, ""], settings: Settings) -> tuple[Alignment, Fit]:
    """Levenberg-Marquardt on pyramid ``level`` (at most ``iterations`` steps, two rejections in a
    row end it, DSO's trackFrame on one level); points that end without a fit take their smoothed
    inverse depth (DSO's applyStep). Returns the estimate and its last linearisation's :class:`Fit`."""
    problem = _problem(reference, cur, camera, level, T_prev_ref)
    blank = jax.eval_shape(lambda: linearise(problem, x, reference.valid, settings))
    blank = jax.tree_util.tree_map(lambda a: jnp.zeros(a.shape, a.dtype), blank)  # linearised by the first pass (it = -1)
    start = _Loop(x, blank, jnp.asarray(0.1, jnp.float32), jnp.asarray(-1, jnp.int32), jnp.asarray(0, jnp.int32), jnp.asarray(False))
    end = jax.lax.while_loop(lambda s: ~s.done, lambda s: _iterate(problem, reference, settings, s, iterations), start)
    x, fit = end.x, end.system.fit
    idepth = jnp.where(fit.good, x.idepth, x.smooth)
    return Alignment(x.T_cur_ref, x.affine, idepth, x.smooth, x.snapped), fit


# ------------------------------------------------------------------------------------ the frames


def reference_of(image: Float[np.ndarray, "H W"], config: MonoConfig) -> Reference:
    """The reference frame (linear radiance): its padded pyramid and gradient-selected points with neighbours."""
    images, sizes = padded_pyramid(image, pyramid_levels(image.shape[0]))
    picked = select_candidates(image, config.init_direct_points, config)
    pixels, valid = np.asarray(picked.pixels, np.float32), np.asarray(picked.valid, bool)
    neighbours, near = nearest_points(pixels, valid)
    return Reference(jnp.asarray(images), jnp.asarray(sizes), jnp.asarray(pixels), jnp.asarray(valid), jnp.asarray(neighbours),
                     jnp.asarray(near))


def fresh_alignment(count: int, T_cur_ref: Pose) -> Alignment:
    """All inverse depths (and their smoothed values) 1, no brightness change, not snapped."""
    ones = jnp.ones(count, jnp.float32)
    return Alignment(T_cur_ref, jnp.zeros(2, jnp.float32), ones, ones, jnp.asarray(False))


def without_translation(T: Pose) -> Pose:
    return Pose(T.q, jnp.zeros_like(T.t))


def translation_share(x: Alignment, good: np.ndarray) -> float:
    """DSO's snap measure: sqrt(|t|² + mean (d − 1)² over the good points), relative to depth 1."""
    d = np.asarray(x.idepth)[good]
    spread = float(np.mean((d - 1.0) ** 2)) if len(d) else 0.0
    return float(np.sqrt(float(np.sum(np.asarray(x.T_cur_ref.t) ** 2)) + spread))


def parallax_deg(X: Float[np.ndarray, "n 3"], centre: Float[np.ndarray, "3"]) -> float:
    """Median angle (deg) between the rays from the reference camera and from ``centre`` to the points X."""
    a = X / np.linalg.norm(X, axis=1, keepdims=True)
    b = X - centre
    b = b / np.linalg.norm(b, axis=1, keepdims=True)
    return float(np.degrees(np.median(2.0 * np.arcsin(np.clip(0.5 * np.linalg.norm(a - b, axis=1), 0.0, 1.0)))))


def handed_over(x: Alignment, fit: Fit, reference: Reference, camera: PinholeCamera, config: MonoConfig, frames: int) -> TwoView:
    """The ok TwoView of an alignment that may hand over: its converged points (a fit, pattern RMS under
    ``ba_outlier``, inverse
    depth known within ``init_direct_max_depth_std`` of itself for ``DEPTH_NOISE`` of photometric
    noise), scaled so that their median depth is 1; not ok when fewer than ``init_min_tracks``."""
    d, info = np.asarray(x.idepth, np.float64), np.asarray(fit.information, np.float64)
    good = np.asarray(fit.good) & (np.asarray(fit.rms) < config.ba_outlier)
    sure = good & (DEPTH_NOISE < config.init_direct_max_depth_std * d * np.sqrt(np.maximum(info, 0.0)))
    kept, need = int(sure.sum()), config.init_min_tracks
    if kept < need:
        return _failed(f"too few converged points: {kept} (need {need})", frames, int(good.sum()))
    scale = float(np.median(1.0 / d[sure]))
    pixels = np.asarray(reference.pixels, np.float32)[sure]
    T_ref_cur = x.T_cur_ref.inverse()
    T_ref_cur = Pose(T_ref_cur.q, T_ref_cur.t / scale)
    X = np.asarray(jax.vmap(camera.backproject)(jnp.asarray(pixels), jnp.asarray(1.0 / (d[sure] * scale), jnp.float32)), np.float64)
    parallax = parallax_deg(X, np.asarray(T_ref_cur.t, np.float64))
    return TwoView(True, "", T_ref_cur, pixels, (d[sure] * scale).astype(np.float32), parallax, int(good.sum()), kept, frames)


@dataclasses.dataclass(frozen=True)
class DirectInitializer:
    """Direct initialisation state over incoming frames (the contract of
    :class:`mono.init.TwoViewTracker`): the camera, the settings, the photometric calibration
    (``gamma``: frames are display values, compared in linear radiance), the :class:`Reference`, the
    last frame's :class:`Alignment`, the last frame's pose and frame-to-frame motion (constant
    motion), frames since the reference and the frame at which the alignment snapped (0: not yet)."""

    camera: PinholeCamera
    config: MonoConfig
    gamma: float
    reference: Reference
    alignment: Alignment
    previous: Pose
    motion: Pose
    frames: int = 0
    snapped_at: int = 0

    @staticmethod
    def start(image: Float[np.ndarray, "H W"], camera: PinholeCamera, config: MonoConfig, gamma: float = 1.0) -> "DirectInitializer":
        """An initialiser whose reference is ``image`` (display values in [0, 1])."""
        reference = reference_of(linearize(image, gamma), config)
        count = reference.pixels.shape[0]
        return DirectInitializer(camera, config, gamma, reference, fresh_alignment(count, Pose.identity()), Pose.identity(),
                                 Pose.identity())

    def settings(self) -> Settings:
        cfg = self.config
        return Settings(cfg.init_direct_blur_samples, cfg.init_direct_exposure, cfg.ba_huber, cfg.init_direct_snap)

    def guess(self) -> Alignment:
        """The previous alignment moved on by the last motion; before it snapped, DSO's fresh start
        (no translation, inverse depths 1)."""
        T = self.motion.compose(self.previous)
        if bool(self.alignment.snapped):
            return Alignment(T, self.alignment.affine, self.alignment.idepth, self.alignment.smooth, self.alignment.snapped)
        fresh = fresh_alignment(self.reference.pixels.shape[0], without_translation(T))
        return Alignment(fresh.T_cur_ref, self.alignment.affine, fresh.idepth, fresh.smooth, fresh.snapped)

    def align(self, image: Float[np.ndarray, "H W"]) -> tuple[Alignment, Fit]:
        """Align ``image`` to the reference, coarsest level first."""
        cur, _ = padded_pyramid(linearize(image, self.gamma), self.reference.images.shape[0])
        cur, x, fit = jnp.asarray(cur), self.guess(), None
        for level in reversed(range(cur.shape[0])):
            iterations = LEVEL_ITERATIONS[min(level, len(LEVEL_ITERATIONS) - 1)]
            x, fit = align_level(self.reference, cur, self.camera, jnp.asarray(level, jnp.int32), x, self.previous,
                                 jnp.asarray(iterations, jnp.int32), self.settings())
        return x, fit

    def update(self, image: Float[np.ndarray, "H W"]) -> "tuple[DirectInitializer, TwoView]":
        """Align ``image`` and report: not yet (the reason), diverged (``restart``), or the start."""
        cfg, frames = self.config, self.frames + 1
        points, need = int(np.sum(np.asarray(self.reference.valid))), cfg.init_min_tracks
        if points < need:
            return dataclasses.replace(self, frames=frames), dataclasses.replace(
                _failed(f"too little texture: {points} points with gradient (need {need})", frames, points), restart=True)
        x, fit = self.align(image)
        good = np.asarray(fit.good) & (np.asarray(fit.rms) < cfg.ba_outlier)
        share = float(good.sum()) / max(1, int(np.sum(np.asarray(fit.seen))))  # of the points in view
        finite = bool(np.all(np.isfinite(np.asarray(x.T_cur_ref.to_vector()))))
        if share < cfg.init_direct_min_fit or not finite:
            reason = f"alignment diverged: {100 * share:.0f} % of the points in view fit (need {100 * cfg.init_direct_min_fit:.0f} %)"
            return dataclasses.replace(self, frames=frames), dataclasses.replace(_failed(reason, frames, int(good.sum())), restart=True)
        snapped_at = self.snapped_at or (frames if bool(x.snapped) else 0)
        state = dataclasses.replace(self, alignment=x, previous=x.T_cur_ref, motion=x.T_cur_ref.compose(self.previous.inverse()),
                                    frames=frames, snapped_at=snapped_at)
        if not snapped_at:
            moved = translation_share(x, good)
            reason = f"too little translation: {100 * moved:.1f} % of the depth (need {100 * cfg.init_direct_snap:.1f} %)"
            return state, _failed(reason, frames, int(good.sum()))
        if frames <= snapped_at + cfg.init_direct_frames:
            reason = f"translation enough since frame {snapped_at}: starting at frame {snapped_at + cfg.init_direct_frames + 1}"
            return state, _failed(reason, frames, int(good.sum()))
        return state, handed_over(x, fit, self.reference, self.camera, cfg, frames)
