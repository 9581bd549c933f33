"""The blur-aware tracker: exposure start and end poses by Levenberg-Marquardt, coarse to fine.

``track(keyframe, frame, init)`` estimates the exposure trajectory (``T_ref_start``, ``T_ref_end``) of a
blurry frame relative to a sharp keyframe with known depth. Each pyramid level is one jit-compiled
``optx.least_squares`` solve with ``optx.LevenbergMarquardt`` over y = [Δstart, Δend, a, b]
(``a, b``: affine brightness, e^a · I + b); shapes are fixed per level so a sequence compiles once
per (level, n). When the first solve is poor, DSO-style motion hypotheses (zero, half, double motion,
small rotations) are tried. The status never raises.
"""

from __future__ import annotations

import dataclasses
import enum
import time
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import optimistix as optx

from ..blur import blur_lengths
from ..geometry import quaternion as quat
from ..geometry.camera import PinholeCamera
from ..geometry.pose import Pose
from ..geometry.trajectory import ExposureTrajectory
from ..image import downsample
from .geometric import depth_residuals, select_depth_points
from .points import PATTERN, LevelPoints, downsample_depth, select_points
from .residuals import LevelProblem, make_residual_fn, residuals_and_jacobian, robust

__all__ = ["TrackerConfig", "Keyframe", "Status", "TrackResult", "track", "predicted_blur_px", "choose_n"]


class Status(enum.IntEnum):
    """Outcome of one tracking call."""

    CONVERGED = 0  # LM converged on every level and the photometric error is good
    MAX_STEPS = 1  # usable estimate, but LM hit its step budget on some level
    DIVERGED = 2  # non-finite values or an error far above the initial one
    TOO_FEW_POINTS = 3  # not enough valid residuals to constrain the 12 (+2) unknowns
    LOST = 4  # finite but the photometric error is too large: the frame does not match the keyframe

    @property
    def ok(self) -> bool:
        return self in (Status.CONVERGED, Status.MAX_STEPS)


@dataclasses.dataclass(frozen=True)
class TrackerConfig:
    """All tracker settings in one place (defaults follow the released MBA-VO code where it is known).

    levels: pyramid levels (coarse-to-fine); points: max points per level (fine → coarse);
    n: virtual frames at full resolution (64 in the paper); n_per_level: "halve" uses
    max(n / 2^level, n_coarse_min) on coarser levels (their blur is 2^level times shorter in pixels,
    so the sampling density per blur pixel is unchanged), "same" uses n on every level;
    n_mode: "fixed" or "adaptive" (n from the predicted blur, per level, rounded up to a power of two
    within [n_min, n], ``n_per_blur_px`` frames per pixel of blur); jacobian: "analytic" (the supplement's corrected formulas) or "autodiff";
    huber: Huber threshold on intensities in [0, 1]; max_steps: LM steps per level (fine → coarse);
    outlier_sigma: patches whose cost exceeds mean + k·std are dropped (all but the coarsest level);
    affine: estimate the brightness gain and offset; blur_aware: False turns the model into classic
    direct alignment (start = end, one virtual frame); response_gamma: photometric calibration —
    images are linearised as I^γ before tracking, because blur averages *radiance* (γ = 1: images
    are used as they are; ``mbavo synth`` sequences record their γ in camera.yaml);
    blur_prior, blur_prior_min_rad, blur_prior_rel: a weak Gaussian prior keeps the exposure's
    relative motion (start⁻¹·end, rotation and translation / median depth, in radians) near the
    initial guess b₀, with σ = blur_prior_min_rad + blur_prior_rel·|b₀| and the photometric noise
    ``blur_prior`` (intensity units) as its scale: a frame expected sharp (b₀ = 0, e.g. exposure 0)
    keeps start ≈ end, a blurred one is free to move by ~20 % of its blur. Without it the start/end
    split is unobservable on sharp frames and drifts with noise. blur_prior = 0 switches it off.
    good_nrms, lost_nrms: thresholds on the residual RMS normalised by the contrast (std) of the
    observed pixels: above good_nrms the motion hypotheses are tried, above lost_nrms the frame is
    lost (≈1.4 for an unrelated image).
    depth_weight: RGB-D only — weight of the current frame's depth map (``tracking.geometric``:
    keyframe points seen from the mid-exposure pose should lie on it). The depth error, in units of
    the sensor noise σ(z) = depth_sigma[0] + depth_sigma[1]·(z − 0.4)² m, counts as
    ``depth_weight`` intensity units per σ (0.01 ≈ the photometric noise makes both terms
    maximum-likelihood under Gaussian noise; 0.03 measured better on mild blur with exact depth and
    on extreme blur with Kinect-class depth, docs/benchmarks.md); 0 = off, images only as in MBA-VO. Used when ``track``
    is given the frame's depth. depth_sigma: (a, b) of the noise model (Kinect v1: 1.2 mm,
    1.9 mm/m²; ``mbavo synth`` writes its own to camera.yaml and ``mbavo track`` reads it);
    depth_huber: Huber threshold in σ; depth_outlier: residuals beyond this many σ (a keyframe point
    hidden in the current frame, or seen past an edge) are dropped, not Huber-weighted: with exact
    depth a few dozen occluded points at hundreds of σ dominated the cost and stalled LM;
    depth_levels: the term is used on this many finest pyramid levels only; coarser levels align
    images alone (their 2x2-averaged depth makes an ill-conditioned ICP: on the mild benchmark
    sequence the depth-only optimum lay 22 mm from the truth at 160x120 and 122 mm at 80x60,
    ``scripts/depth_only_fit.py``; with depth_weight 1 on all four levels a frame landed 27 mm off,
    with 2 levels 0.03 mm, ``scripts/track_frame_pair.py``). 3 of 4 measured best at depth_weight
    0.03; stiffer weights (0.1 and 1: 5.7 and 8.5 mm off with 3 levels, 0.03 mm with 2) want 2;
    depth_stride: grid spacing of the term's keyframe points at full resolution (halved per level,
    at least 2); depth_edge: depth samples whose neighbours differ by more than this fraction are
    on a depth edge and dropped.
    """

    levels: int = 4
    points: tuple[int, ...] = (384, 256, 192, 128)
    cell: tuple[int, ...] = (30, 21, 15, 10)
    grad_threshold: float = 8.0 / 255.0
    n: int = 64
    n_per_level: str = "halve"
    n_coarse_min: int = 8
    n_mode: str = "fixed"
    n_min: int = 2
    n_per_blur_px: float = 2.0
    jacobian: str = "analytic"
    huber: float = 9.0 / 255.0
    max_steps: tuple[int, ...] = (8, 10, 12, 20)
    rtol: float = 1e-3
    atol: float = 1e-4
    outlier_sigma: float = 2.5
    affine: bool = True
    blur_aware: bool = True
    min_valid: int = 60
    good_nrms: float = 0.5
    lost_nrms: float = 1.0
    hypotheses: bool = True
    response_gamma: float = 1.0
    blur_prior: float = 0.01
    blur_prior_min_rad: float = 5e-4
    blur_prior_rel: float = 0.2
    depth_weight: float = 0.0
    depth_sigma: tuple[float, float] = (0.0012, 0.0019)
    depth_huber: float = 3.0
    depth_outlier: float = 20.0
    depth_levels: int = 3
    depth_stride: int = 8
    depth_edge: float = 0.02

    def __post_init__(self):
        if self.n_mode not in ("fixed", "adaptive"):
            raise ValueError(f"n_mode must be 'fixed' or 'adaptive', got {self.n_mode!r}")
        if self.n_per_level not in ("halve", "same"):
            raise ValueError(f"n_per_level must be 'halve' or 'same', got {self.n_per_level!r}")
        if self.jacobian not in ("autodiff", "analytic"):
            raise ValueError(f"jacobian must be 'autodiff' or 'analytic', got {self.jacobian!r}")
        if not self.response_gamma > 0:
            raise ValueError(f"response_gamma must be positive, got {self.response_gamma}")
        if self.n < 1:
            raise ValueError(f"n must be >= 1, got {self.n}")
        if not (self.depth_weight >= 0 and self.depth_huber > 0 and self.depth_stride >= 1 and self.depth_edge > 0):
            raise ValueError("depth_weight must be >= 0, depth_huber and depth_edge > 0, depth_stride >= 1")
        if not (self.depth_outlier > self.depth_huber and self.depth_levels >= 1):
            raise ValueError(f"depth_outlier ({self.depth_outlier}) must exceed depth_huber ({self.depth_huber}) and depth_levels must be >= 1, got {self.depth_levels}")
        if len(self.depth_sigma) != 2 or not (self.depth_sigma[0] > 0 and self.depth_sigma[1] >= 0):
            raise ValueError(f"depth_sigma must be (a > 0, b >= 0), got {self.depth_sigma}")
        for name in ("points", "cell", "max_steps"):
            if len(getattr(self, name)) < self.levels:
                raise ValueError(f"{name} needs one entry per level ({self.levels}), got {getattr(self, name)}")


@dataclasses.dataclass(frozen=True)
class Keyframe:
    """A sharp reference image with its pyramid, camera per level and selected points per level
    (photometric points on strong gradients; depth points on a grid, for the optional depth term)."""

    images: tuple  # per level, jnp (H_l, W_l)
    cameras: tuple  # per level, PinholeCamera
    points: tuple  # per level, LevelPoints (fixed size)
    depth: np.ndarray  # level-0 depth (metres, NaN = none)
    depth_points: tuple  # per level, LevelPoints on a grid (fixed size), for ``depth_weight``

    @staticmethod
    def create(image, depth, camera: PinholeCamera, config: TrackerConfig = TrackerConfig()) -> "Keyframe":
        img = np.asarray(image, np.float32)
        dep = np.asarray(depth, np.float32)
        if img.shape != (camera.height, camera.width):
            raise ValueError(f"keyframe image is {img.shape[1]}x{img.shape[0]}, camera is {camera.width}x{camera.height}")
        if dep.shape != img.shape:
            raise ValueError(f"keyframe depth shape {dep.shape} differs from image shape {img.shape}")
        images, cams, pts, dpts = [], [], [], []
        im, dp = linearize(img, config.response_gamma), dep
        for level in range(config.levels):
            if level:
                im = np.asarray(downsample(jnp.asarray(im)))
                dp = downsample_depth(dp)
            images.append(jnp.asarray(im))
            cams.append(camera.scaled(level))
            pts.append(select_points(im, dp, config.points[level], config.cell[level], config.grad_threshold))
            dpts.append(select_depth_points(dp, _depth_stride(config, level), config.depth_edge))
        return Keyframe(tuple(images), tuple(cams), tuple(pts), dep, tuple(dpts))

    def n_points(self, level: int = 0) -> int:
        return self.points[level].count


@dataclasses.dataclass(frozen=True)
class TrackResult:
    """``trajectory`` (T_ref_start, T_ref_end), ``status`` and ``diagnostics`` (per-level n, LM steps,
    RMS photometric error, valid residuals; the hypothesis used; affine (a, b); predicted blur; time).
    Unpacks as a tuple: ``traj, status, diag = track(...)``."""

    trajectory: ExposureTrajectory
    status: Status
    diagnostics: dict

    def __iter__(self):
        return iter((self.trajectory, self.status, self.diagnostics))


def linearize(image, gamma: float):
    """Photometric calibration by an inverse gamma response: I → clip(I, 0, 1)^γ."""
    image = np.clip(np.asarray(image, np.float32), 0.0, 1.0)
    return image if gamma == 1.0 else image ** np.float32(gamma)


def _depth_stride(config: TrackerConfig, level: int) -> int:
    return max(2, config.depth_stride >> level)


def _depth_pyramid(depth, levels):
    """The current frame's depth per level, 0 where missing (what ``geometric.sample_depth`` expects)."""
    d = np.asarray(depth, np.float32)
    d = np.where(np.isfinite(d) & (d > 0), d, np.nan).astype(np.float32)
    out = [d]
    for _ in range(levels - 1):
        out.append(downsample_depth(out[-1]))
    return [jnp.asarray(np.nan_to_num(x, nan=0.0)) for x in out]


def _frame_pyramid(image, levels):
    out = [jnp.asarray(image, jnp.float32)]
    for _ in range(levels - 1):
        out.append(downsample(out[-1]))
    return out


@jax.jit
def _mean_endpoint_distance(cam, pixels, depths, valid, traj: ExposureTrajectory):
    d, ok = blur_lengths(cam, pixels, depths, traj)
    ok = ok & valid
    return jnp.sum(jnp.where(ok, d, 0.0)) / jnp.maximum(ok.sum(), 1)


def predicted_blur_px(keyframe: Keyframe, traj: ExposureTrajectory, level: int = 0) -> float:
    """Mean image distance (level pixels) between the keyframe points seen at the start and end poses
    (fixed shapes: compiled once per sequence)."""
    pts = keyframe.points[level]
    d = _mean_endpoint_distance(keyframe.cameras[level], *pts.on_device, traj)
    return float(d)


def choose_n(blur_px: float, config: TrackerConfig) -> int:
    """Adaptive n (supplement §6: n should exceed the blur kernel size): ``n_per_blur_px`` virtual
    frames per pixel of predicted blur, rounded up to a power of two in [n_min, n]."""
    need = max(config.n_min, int(np.ceil(max(blur_px, 0.0) * config.n_per_blur_px)))
    return int(min(config.n, 2 ** int(np.ceil(np.log2(need)))))


# ----------------------------------------------------------------------------------- one level


def _level_setup(cam, cur_image, pixels, depths, pvalid, anchor: ExposureTrajectory):
    """Residual pixels of the current frame for this level's solve (fixed during the solve): each
    keyframe point projected with the middle pose, rounded, plus the 8-pixel pattern."""
    mid = anchor.middle().inverse()  # T_cur_ref at mid-exposure
    P = jax.vmap(cam.backproject)(pixels, depths)
    x_cur = jax.vmap(lambda p: cam.project(mid.apply(p)))(P)
    ok_pt = pvalid & jnp.all(jnp.isfinite(x_cur), axis=1) & (jax.vmap(mid.apply)(P)[:, 2] > 1e-3)
    base = jnp.round(jnp.where(ok_pt[:, None], x_cur, 0.0))
    res = (base[:, None, :] + jnp.asarray(PATTERN)[None]).reshape(-1, 2)
    h, w = cur_image.shape
    inside = (res[:, 0] >= 1) & (res[:, 1] >= 1) & (res[:, 0] <= w - 2) & (res[:, 1] <= h - 2)
    mask = jnp.repeat(ok_pt, PATTERN.shape[0]) & inside
    col = jnp.clip(res[:, 0], 0, w - 1).astype(jnp.int32)
    row = jnp.clip(res[:, 1], 0, h - 1).astype(jnp.int32)
    observed = cur_image[row, col]
    rays = jax.vmap(cam.unit_ray)(res)
    d = jnp.repeat(depths, PATTERN.shape[0])
    return rays, d, observed, mask


@partial(jax.jit, static_argnames=("n", "jacobian", "max_steps", "rigid", "affine", "use_outliers"))
def _solve_level(
    ref_image, cam, cur_image, pixels, depths, pvalid, anchor, affine_ab, huber, outlier_sigma, rtol, atol,
    prior_blur, prior_sigma_intensity, prior_min_rad, prior_rel, depth_term,
    *, n, jacobian, max_steps, rigid, affine, use_outliers,
):
    """One level's LM solve. ``depth_term``: None, or (current depth, depth-point pixels, depths,
    validity, weight, huber, outlier, edge, sigma) for the optional geometric residuals."""
    rays, d, observed, mask = _level_setup(cam, cur_image, pixels, depths, pvalid, anchor)
    problem = LevelProblem(ref_image, cam, anchor, rays, d, observed, mask, n, jacobian)
    residual = make_residual_fn()
    m = 6 if rigid else 12
    dtype = ref_image.dtype

    def expand(z):
        y12 = jnp.concatenate([z[:6], z[:6]]) if rigid else z[:12]
        ab = z[m : m + 2] if affine else jnp.zeros(2, dtype)
        return jnp.concatenate([y12, affine_ab + ab])

    npat = PATTERN.shape[0]
    if use_outliers:  # drop patches whose cost at the level's start is far above the rest
        r0, _, v0 = residuals_and_jacobian(expand(jnp.zeros(m + 2, dtype)), problem, with_jacobian=False)
        vp = v0.reshape(-1, npat)
        cost = jnp.sum(jnp.where(vp, r0.reshape(-1, npat) ** 2, 0.0), 1) / jnp.maximum(vp.sum(1), 1)
        good = vp.sum(1) > npat // 2
        cnt = jnp.maximum(good.sum(), 1)
        mean = jnp.sum(jnp.where(good, cost, 0.0)) / cnt
        std = jnp.sqrt(jnp.sum(jnp.where(good, (cost - mean) ** 2, 0.0)) / cnt)
        keep = cost <= mean + outlier_sigma * std
        problem = eqx.tree_at(lambda p: p.mask, problem, problem.mask & jnp.repeat(keep, npat))

    # weak prior on the exposure's relative motion start⁻¹·end (6-vector [ω, t/z̄]), in radians
    zmed = jnp.nanmedian(jnp.where(pvalid, depths, jnp.nan))
    scale = jnp.concatenate([jnp.ones(3, dtype), jnp.full(3, 1.0 / jnp.where(jnp.isfinite(zmed), zmed, 1.0))])
    sqrt_valid = jnp.sqrt(jnp.maximum(problem.mask.sum(), 1).astype(dtype))
    prior_weight = prior_sigma_intensity / (prior_min_rad + prior_rel * jnp.linalg.norm(scale * prior_blur))

    def blur_vector(traj):
        rel = traj.start.inverse().compose(traj.end)
        return jnp.concatenate([quat.log(rel.q), rel.t])

    def geometric(z, prob):
        cur_depth, dpix, ddep, dval, weight, dhuber, outlier, edge, sigma = depth_term
        mid = prob.anchor.plus(expand(z)[:12]).middle()
        r, _ = depth_residuals(mid, cam, cur_depth, dpix, ddep, dval, edge, sigma, outlier)
        return weight * robust(r, dhuber)

    def fn(z, prob):
        parts = [robust(residual(expand(z), prob), huber)]
        if depth_term is not None:
            parts.append(geometric(z, prob))
        if not rigid:
            parts.append(prior_weight * sqrt_valid * scale * (blur_vector(prob.anchor.plus(expand(z)[:12])) - prior_blur))
        return jnp.concatenate(parts) if len(parts) > 1 else parts[0]

    # RMS norm: the max-norm default asks every one of thousands of residuals to settle below atol
    solver = optx.LevenbergMarquardt(rtol=rtol, atol=atol, norm=optx.rms_norm, linear_solver=lx.QR())
    z0 = jnp.zeros(m + (2 if affine else 0), dtype)
    sol = optx.least_squares(fn, solver, z0, args=problem, max_steps=max_steps, throw=False)
    y = expand(sol.value)
    r, _, valid = residuals_and_jacobian(y, problem, with_jacobian=False)
    nvalid = valid.sum()
    rms = jnp.sqrt(jnp.sum(r * r) / jnp.maximum(nvalid, 1))
    obs_mean = jnp.sum(jnp.where(valid, problem.observed, 0.0)) / jnp.maximum(nvalid, 1)
    obs_std = jnp.sqrt(jnp.sum(jnp.where(valid, (problem.observed - obs_mean) ** 2, 0.0)) / jnp.maximum(nvalid, 1))
    r_init, _, valid0 = residuals_and_jacobian(expand(z0), problem, with_jacobian=False)
    rms0 = jnp.sqrt(jnp.sum(r_init**2) / jnp.maximum(valid0.sum(), 1))
    traj = anchor.plus(y[:12]).normalized()
    converged = sol.result == optx.RESULTS.successful
    return traj, y[12:14], rms, rms0, nvalid, converged, sol.stats["num_steps"], rms / jnp.maximum(obs_std, 1e-6)


# ----------------------------------------------------------------------------------- public API


def _n_for_level(config: TrackerConfig, blur0: float, level: int) -> int:
    if not config.blur_aware:
        return 1
    if config.n_mode == "adaptive":
        return choose_n(blur0 / 2**level, config)
    if config.n_per_level == "same":
        return config.n
    return max(config.n >> level, min(config.n_coarse_min, config.n))


def _coarse_to_fine(keyframe: Keyframe, pyr, init: ExposureTrajectory, config: TrackerConfig, blur0: float, depth_pyr=None):
    traj = init
    ab = jnp.zeros(2, jnp.float32)
    per_level = []
    rigid = not config.blur_aware
    if rigid:  # classic direct alignment: one pose, start = end = the initial mid-exposure pose
        mid = init.middle()
        traj = ExposureTrajectory(mid, mid)
    rel0 = init.start.inverse().compose(init.end)
    prior_blur = jnp.concatenate([quat.log(rel0.q), rel0.t])
    for level in reversed(range(config.levels)):
        pts = keyframe.points[level]
        n = _n_for_level(config, blur0, level)
        depth_term = None
        if depth_pyr is not None and level < config.depth_levels:
            dp = keyframe.depth_points[level]
            depth_term = (
                depth_pyr[level], *dp.on_device, config.depth_weight, config.depth_huber, config.depth_outlier,
                config.depth_edge, tuple(config.depth_sigma),
            )
        out = _solve_level(
            keyframe.images[level], keyframe.cameras[level], pyr[level],
            *pts.on_device,
            traj, ab, config.huber, config.outlier_sigma, config.rtol, config.atol, prior_blur, config.blur_prior,
            config.blur_prior_min_rad, config.blur_prior_rel, depth_term,
            n=n, jacobian=config.jacobian, max_steps=config.max_steps[level], rigid=rigid,
            affine=config.affine, use_outliers=level < config.levels - 1 and config.outlier_sigma > 0,
        )
        new_traj, ab, rms, rms0, nvalid, converged, steps, nrms = out
        per_level.append(
            dict(
                level=level, n=n, rms=float(rms), rms_init=float(rms0), nrms=float(nrms), valid=int(nvalid),
                converged=bool(converged), steps=int(steps), depth_term=depth_term is not None,
            )
        )
        if not np.isfinite(float(rms)):
            return new_traj, ab, per_level
        traj = new_traj
    return traj, ab, per_level


def _status(per_level, config: TrackerConfig) -> Status:
    fine = per_level[-1]
    if not all(np.isfinite(p["rms"]) for p in per_level):
        return Status.DIVERGED
    if min(p["valid"] for p in per_level) < config.min_valid:
        return Status.TOO_FEW_POINTS
    if not fine["nrms"] <= config.lost_nrms:
        return Status.LOST
    if fine["rms"] > 2.0 * max(fine["rms_init"], 1e-6) + 0.02:
        return Status.DIVERGED
    return Status.CONVERGED if all(p["converged"] for p in per_level) else Status.MAX_STEPS


def motion_hypotheses(init: ExposureTrajectory) -> list:
    """DSO-style alternatives to the constant-velocity guess. Each moves the mid-exposure pose M of
    ``init`` — to the identity (zero motion), M^½ (half), M² (double) and M with ±2° about each axis —
    and keeps the guess's blur (start and end about M as in ``init``)."""
    from .motion import pose_power

    mid = init.middle()
    to_start = mid.inverse().compose(init.start)
    to_end = mid.inverse().compose(init.end)

    def around(m: Pose):
        return ExposureTrajectory(m.compose(to_start), m.compose(to_end))

    out = [("zero motion", around(Pose.identity())), ("half motion", around(pose_power(mid, 0.5))), ("double motion", around(pose_power(mid, 2.0)))]
    for axis in range(3):
        for sign in (1.0, -1.0):
            r = np.zeros(3, np.float32)
            r[axis] = sign * np.deg2rad(2.0)
            out.append((f"rotation {'xyz'[axis]}{'+' if sign > 0 else '-'}", around(mid.compose(Pose(quat.exp(jnp.asarray(r)), jnp.zeros(3))))))
    return out


def track(keyframe: Keyframe, frame, init: ExposureTrajectory | None = None, config: TrackerConfig = TrackerConfig(), depth=None):
    """Estimate the exposure trajectory of ``frame`` (a blurry image, float [0, 1], the keyframe's
    size) relative to ``keyframe``.

    ``depth``: the frame's own depth map (metres; NaN or 0 = missing), used only when
    ``config.depth_weight > 0`` (the geometric term of ``tracking.geometric``).

    ``init``: the initial guess (e.g. constant velocity); the identity when None. Returns
    :class:`TrackResult` ``(trajectory, status, diagnostics)``; it never raises on bad data — a
    black, textureless or unrelated frame gives a non-ok status.
    """
    t0 = time.perf_counter()
    image = np.asarray(frame, np.float32)
    cam0 = keyframe.cameras[0]
    if image.shape != (cam0.height, cam0.width):
        raise ValueError(f"frame is {image.shape[1]}x{image.shape[0]}, keyframe is {cam0.width}x{cam0.height}")
    if init is None:
        init = ExposureTrajectory(Pose.identity(), Pose.identity())
    if not np.all(np.isfinite(image)):
        image = np.nan_to_num(image, nan=0.0, posinf=1.0, neginf=0.0)
    # a constant image (black, saturated, textureless) cannot constrain anything
    if float(np.std(image)) < 1e-4:
        diagnostics = {"points": keyframe.n_points(0), "hypothesis": "none", "levels": [], "blur_px": 0.0, "seconds": time.perf_counter() - t0}
        return TrackResult(init, Status.TOO_FEW_POINTS, diagnostics)
    diagnostics = {"points": keyframe.n_points(0), "hypothesis": "initial guess"}
    if keyframe.n_points(0) < max(8, config.min_valid // 8):
        diagnostics.update(levels=[], seconds=time.perf_counter() - t0, blur_px=0.0)
        return TrackResult(init, Status.TOO_FEW_POINTS, diagnostics)
    pyr = _frame_pyramid(linearize(image, config.response_gamma), config.levels)
    depth_pyr = None
    if config.depth_weight > 0 and depth is not None:
        if np.shape(depth) != image.shape:
            raise ValueError(f"frame depth shape {np.shape(depth)} differs from image shape {image.shape}")
        depth_pyr = _depth_pyramid(depth, config.levels)
    blur0 = predicted_blur_px(keyframe, init)
    traj, ab, per_level = _coarse_to_fine(keyframe, pyr, init, config, blur0, depth_pyr)
    status = _status(per_level, config)
    tried = 1
    if config.hypotheses and (not status.ok or per_level[-1]["nrms"] > config.good_nrms):
        best = (per_level[-1]["nrms"] if status.ok else np.inf, traj, ab, per_level, status, "initial guess")
        for name, hyp in motion_hypotheses(init):
            tried += 1
            t2, ab2, pl2 = _coarse_to_fine(keyframe, pyr, hyp, config, predicted_blur_px(keyframe, hyp), depth_pyr)
            st2 = _status(pl2, config)
            score = pl2[-1]["nrms"] if st2.ok else np.inf
            if score < best[0]:
                best = (score, t2, ab2, pl2, st2, name)
            if st2.ok and score <= config.good_nrms:
                break
        if np.isfinite(best[0]):
            _, traj, ab, per_level, status, diagnostics["hypothesis"] = best
    diagnostics.update(
        levels=per_level,
        rms=per_level[-1]["rms"],
        nrms=per_level[-1]["nrms"],
        affine=[float(ab[0]), float(ab[1])],
        depth_term=depth_pyr is not None,
        blur_px=blur0,
        hypotheses_tried=tried,
        seconds=time.perf_counter() - t0,
    )
    return TrackResult(traj, status, diagnostics)
