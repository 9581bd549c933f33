"""The blur-aware tracker: exposure start and end poses by Levenberg-Marquardt, coarse to fine.

``track(keyframe, frame, init)`` estimates the exposure trajectory (``T_ref_start``, ``T_ref_end``) of a
blurry frame relative to a sharp keyframe with known depth. Each pyramid level is one jit-compiled
``optx.least_squares`` solve with ``optx.LevenbergMarquardt`` over y = [Δstart, Δend, a, b]
(``a, b``: affine brightness, e^a · I + b; with ``trajectory: cubic`` the path is a cumulative
cubic B-spline, ``geometry.spline``, and Δstart, Δend become its four control poses' updates);
shapes are fixed per level so a sequence compiles once per (level, n). When the first solve is poor, DSO-style motion hypotheses (zero, half, double motion,
small rotations) are tried. The status never raises.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import time

import jax
import jax.numpy as jnp
import numpy as np

from ..blur import blur_lengths, round_up_frames
from ..config import TrackerConfig
from ..errors import ArgumentError
from ..geometry.camera import PinholeCamera
from ..geometry.pose import Pose
from ..geometry.spline import ExposurePath, as_trajectory
from ..geometry.trajectory import ExposureTrajectory, RowClock
from ..image import linearize, pyramid
from ..masked import masked_mean
from .geometric import select_depth_points
from .level import DepthTerm, LevelInputs, LevelSettings, exposure_motion, solve_level
from .motion import motion_hypotheses
from .points import LevelPoints, downsample_depth, given_points, select_points

__all__ = ["TrackerConfig", "Keyframe", "Status", "TrackResult", "track", "predicted_blur_px", "choose_n"]


class Status(enum.IntEnum):
    """Outcome of one tracking call."""

    CONVERGED = 0  # LM converged on every level and the photometric error is good
    MAX_STEPS = 1  # usable estimate, but LM hit its step budget on some level
    DIVERGED = 2  # non-finite values or an error far above the initial one
    TOO_FEW_POINTS = 3  # not enough valid residuals to constrain the 12 (+2) unknowns
    LOST = 4  # finite but the photometric error is too large: the frame does not match the keyframe
    IMPLAUSIBLE = 5  # a usable fit that disagrees with the frames before it (set by the odometry loop, not by track)

    @property
    def ok(self) -> bool:
        return self in (Status.CONVERGED, Status.MAX_STEPS)


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
        config = config.for_image(*img.shape)
        images = pyramid(linearize(img, config.response_gamma), config.levels)
        depths = _depth_levels(dep, config.levels)
        pts = [select_points(np.asarray(images[l]), depths[l], config.points[l], config.cell[l], config.grad_threshold)
               for l in range(config.levels)]
        dpts = [select_depth_points(depths[l], _depth_stride(config, l), config.depth_edge) for l in range(config.levels)]
        cams = [camera.scaled(l) for l in range(config.levels)]
        return Keyframe(tuple(images), tuple(cams), tuple(pts), dep, tuple(dpts))

    @staticmethod
    def from_points(image, pixels, depths, camera: PinholeCamera, config: TrackerConfig = TrackerConfig()) -> "Keyframe":
        """A keyframe whose points are given (level-0 pixels (N, 2), z-depths (N,): a monocular
        window's points seen from it) instead of selected on a depth map: on each level, one point
        per level pixel, the strongest gradients first, up to the level's ``points``. No depth term."""
        img = np.asarray(image, np.float32)
        if img.shape != (camera.height, camera.width):
            raise ValueError(f"keyframe image is {img.shape[1]}x{img.shape[0]}, camera is {camera.width}x{camera.height}")
        config = config.for_image(*img.shape)
        images = pyramid(linearize(img, config.response_gamma), config.levels)
        pixels, depths = np.asarray(pixels, np.float32).reshape(-1, 2), np.asarray(depths, np.float32).reshape(-1)
        pts = [given_points(np.asarray(images[l]), (pixels + 0.5) / 2**l - 0.5, depths, config.points[l]) for l in range(config.levels)]
        none = LevelPoints(np.zeros((1, 2), np.float32), np.ones(1, np.float32), np.zeros(1, bool))
        depth = np.full(img.shape, np.nan, np.float32)
        return Keyframe(tuple(images), tuple(camera.scaled(l) for l in range(config.levels)), tuple(pts), depth, (none,) * config.levels)

    def n_points(self, level: int = 0) -> int:
        return self.points[level].count


@dataclasses.dataclass(frozen=True)
class TrackResult:
    """``trajectory`` (T_ref_start, T_ref_end), ``status`` and ``diagnostics`` (per-level n, LM steps,
    RMS photometric error, valid residuals; the hypothesis used; affine (a, b); predicted blur; time).
    Unpacks as a tuple: ``traj, status, diag = track(...)``."""

    trajectory: ExposurePath
    status: Status
    diagnostics: dict

    def __iter__(self):
        return iter((self.trajectory, self.status, self.diagnostics))


def _depth_stride(config: TrackerConfig, level: int) -> int:
    return max(2, config.depth_stride >> level)


def _depth_levels(depth: np.ndarray, levels: int) -> list[np.ndarray]:
    """A depth map per pyramid level (``points.downsample_depth``: mean of the valid depths)."""
    out = [np.asarray(depth, np.float32)]
    for _ in range(levels - 1):
        out.append(downsample_depth(out[-1]))
    return out


def _depth_pyramid(depth, levels):
    """The current frame's depth per level, 0 where missing (what ``geometric.sample_depth`` expects)."""
    d = np.asarray(depth, np.float32)
    d = np.where(np.isfinite(d) & (d > 0), d, np.nan).astype(np.float32)
    return [jnp.asarray(np.nan_to_num(x, nan=0.0)) for x in _depth_levels(d, levels)]


@jax.jit
def _mean_endpoint_distance(cam, pixels, depths, valid, traj: ExposureTrajectory):
    d, ok = blur_lengths(cam, pixels, depths, traj)
    ok = ok & valid
    return masked_mean(d, ok)


def predicted_blur_px(keyframe: Keyframe, traj: ExposureTrajectory, level: int = 0) -> float:
    """Mean image distance (level pixels) between the keyframe points seen at the start and end poses
    (fixed shapes: compiled once per sequence)."""
    pts = keyframe.points[level]
    d = _mean_endpoint_distance(keyframe.cameras[level], *pts.on_device, traj)
    return float(d)


def choose_n(blur_px: float, config: TrackerConfig) -> int:
    """Adaptive n (supplement §6: n should exceed the blur kernel size): ``n_per_blur_px`` virtual
    frames per pixel of predicted blur, rounded up to a power of two in [n_min, n]."""
    return round_up_frames(blur_px * config.n_per_blur_px, config.n_min, config.n)


def _n_for_level(config: TrackerConfig, blur0: float, level: int) -> int:
    if not config.blur_aware:
        return 1
    if config.n_mode == "adaptive":
        return choose_n(blur0 / 2**level, config)
    if config.n_per_level == "same":
        return config.n
    return max(config.n >> level, min(config.n_coarse_min, config.n))


@functools.lru_cache(maxsize=256)
def _level_settings(config: TrackerConfig, level: int, n: int, rolling: bool = False) -> LevelSettings:
    """A level's solver settings, built (and copied to the device) once per config, level, n and
    shutter model (``rolling``: per-row virtual poses)."""
    f = lambda v: jnp.float32(v)
    return LevelSettings(f(config.huber), f(config.outlier_sigma), f(config.rtol), f(config.atol),
                         f(max(config.curvature_prior_rad, 1e-12)), n=n, jacobian=config.jacobian,
                         max_steps=config.max_steps[level], rigid=not config.blur_aware, affine=config.affine,
                         use_outliers=level < config.levels - 1 and config.outlier_sigma > 0, rolling=rolling,
                         curved=config.trajectory == "cubic" and config.curvature_prior_rad > 0, frozen=n > 1 and level < config.levels - config.fresh_jacobian_levels)


@functools.lru_cache(maxsize=256)
def _row_clock(readout: float, height: int, level: int) -> RowClock:
    """A level's row clock (readout fraction ρ, full-resolution height), on the device once."""
    return RowClock.create(readout, height, level)


def _depth_term(keyframe: Keyframe, depth_pyr, level: int, config: TrackerConfig) -> DepthTerm | None:
    """The level's depth term, when the frame's depth is given and the level is fine enough."""
    if depth_pyr is None or level >= config.depth_levels:
        return None
    return DepthTerm(depth_pyr[level], *keyframe.depth_points[level].on_device, *_depth_weights(config))


@functools.lru_cache(maxsize=16)
def _depth_weights(config: TrackerConfig) -> tuple:
    """The depth term's weight, Huber threshold, outlier cut, edge fraction and σ model, on the device once."""
    f = lambda v: jnp.float32(v)
    return (f(config.depth_weight), f(config.depth_huber), f(config.depth_outlier), f(config.depth_edge),
            jnp.asarray(config.depth_sigma, jnp.float32))


@functools.lru_cache(maxsize=16)
def _prior_scales(config: TrackerConfig) -> tuple:
    """σ_I, min_rad and rel of the exposure-motion prior, on the device once."""
    return jnp.float32(config.blur_prior), jnp.float32(config.blur_prior_min_rad), jnp.float32(config.blur_prior_rel)


def _level_report(level: int, n: int, res, depth_term: bool) -> dict:
    res = jax.device_get(res)  # one device-to-host copy per level
    return dict(level=level, n=n, rms=float(res.rms), rms_init=float(res.rms_init), nrms=float(res.nrms), valid=int(res.valid),
                converged=bool(res.converged), steps=int(res.steps), depth_term=depth_term)


def _coarse_to_fine(keyframe: Keyframe, pyr, init: ExposurePath, config: TrackerConfig, blur0: float, depth_pyr=None,
                    readout: float = 0.0):
    """Solve every level, coarse to fine, each from the previous level's result: (path, affine,
    per-level reports). ``readout``: the frame's readout fraction ρ (0: global shutter). Stops
    early at a non-finite level."""
    traj, ab, per_level = init, jnp.zeros(2, jnp.float32), []
    rolling = config.blur_aware and readout > 0
    prior = None
    if config.blur_aware:  # the prior pulls the exposure motion towards the initial guess's
        prior = (exposure_motion(init), *_prior_scales(config))
    else:  # classic direct alignment: one pose, start = end = the initial mid-exposure pose
        traj = ExposureTrajectory(init.middle(), init.middle())
    for level in reversed(range(config.levels)):
        n = _n_for_level(config, blur0, level)
        depth = _depth_term(keyframe, depth_pyr, level, config)
        inputs = LevelInputs(keyframe.images[level], keyframe.cameras[level], pyr[level], *keyframe.points[level].on_device, traj, ab,
                             _row_clock(float(readout), keyframe.cameras[0].height, level))
        res = solve_level(inputs, _level_settings(config, level, n, rolling), prior, depth)
        per_level.append(_level_report(level, n, res, depth is not None))
        if not np.isfinite(per_level[-1]["rms"]):
            return res.trajectory, res.affine_ab, per_level
        traj, ab = res.trajectory, res.affine_ab
    return traj, ab, per_level


def _status(per_level, config: TrackerConfig) -> Status:
    fine = per_level[-1]
    if not all(np.isfinite(p["rms"]) for p in per_level):
        return Status.DIVERGED
    if min(p["valid"] for p in per_level) < config.min_valid:
        return Status.TOO_FEW_POINTS
    if not fine["nrms"] <= config.lost_nrms:
        return Status.LOST
    if fine["rms"] > config.diverged_factor * max(fine["rms_init"], 1e-6) + config.diverged_margin:
        return Status.DIVERGED
    return Status.CONVERGED if all(p["converged"] for p in per_level) else Status.MAX_STEPS


@dataclasses.dataclass
class _Attempt:
    """One coarse-to-fine solve from one initial guess."""

    name: str
    trajectory: ExposurePath
    affine_ab: jax.Array
    per_level: list
    status: Status

    @property
    def score(self) -> float:
        """The fine level's normalised RMS if usable, else infinity (lower is better)."""
        return self.per_level[-1]["nrms"] if self.status.ok else float("inf")


def _attempt(name, keyframe, pyr, init, config, depth_pyr, blur0=None, readout: float = 0.0) -> _Attempt:
    blur0 = predicted_blur_px(keyframe, init.middle_row_path(readout)) if blur0 is None else blur0
    traj, ab, per_level = _coarse_to_fine(keyframe, pyr, init, config, blur0, depth_pyr, readout)
    return _Attempt(name, traj, ab, per_level, _status(per_level, config))


@functools.lru_cache(maxsize=16)
def _per_step(config: TrackerConfig) -> TrackerConfig:
    """``config`` with the photometric Jacobian recomputed at every LM step on every level (one object per config)."""
    return dataclasses.replace(config, fresh_jacobian_levels=config.levels)


def _search(first: _Attempt, keyframe, pyr, init, config: TrackerConfig, depth_pyr, readout: float = 0.0) -> tuple[_Attempt, int]:
    """DSO-style: when the first solve is poor, try the motion hypotheses until one is good; the
    best usable attempt wins. Returns it and the number of attempts. The search recomputes the
    Jacobian at every step (far starts are where a frozen one is least exact) and, when the first
    solve froze it on some levels, first solves the initial guess again that way."""
    if not config.hypotheses or (first.status.ok and first.per_level[-1]["nrms"] <= config.good_nrms):
        return first, 1
    best, tried, fresh = first, 1, _per_step(config)
    again = [("initial guess, per-step Jacobian", init)] if config.fresh_jacobian_levels < config.levels else []
    for name, hyp in [*again, *motion_hypotheses(init, config.hypothesis_rotation_deg)]:
        tried += 1
        a = _attempt(name, keyframe, pyr, hyp, fresh, depth_pyr, readout=readout)
        if a.score < best.score:
            best = a
        if a.status.ok and a.score <= config.good_nrms:
            break
    return (best if np.isfinite(best.score) else first), tried


def _refuse(keyframe: Keyframe, init, t0: float) -> TrackResult:
    """A frame or keyframe that cannot constrain anything (constant image, too few points)."""
    diagnostics = {"points": keyframe.n_points(0), "hypothesis": "none", "levels": [], "blur_px": 0.0,
                   "seconds": time.perf_counter() - t0}
    return TrackResult(init, Status.TOO_FEW_POINTS, diagnostics)


def _frame_image(frame, camera: PinholeCamera) -> np.ndarray:
    """The frame as a float32 (H, W) image of the keyframe's size; non-finite pixels read as 0."""
    if frame is None or np.ndim(frame) != 2:
        raise ArgumentError(f"frame must be a grey image, a 2-D array of {camera.height}x{camera.width}, got "
                            f"{'None' if frame is None else f'shape {np.shape(frame)}'}")
    image = np.asarray(frame, np.float32)
    if image.shape != (camera.height, camera.width):
        raise ArgumentError(f"frame is {image.shape[1]}x{image.shape[0]}, keyframe is {camera.width}x{camera.height}")
    return image if np.all(np.isfinite(image)) else np.nan_to_num(image, nan=0.0, posinf=1.0, neginf=0.0)


def track(keyframe: Keyframe, frame, init: ExposurePath | None = None, config: TrackerConfig = TrackerConfig(), depth=None,
          readout: float = 0.0, blur_px: float | None = None):
    """Estimate the exposure trajectory of ``frame`` (a blurry image, float [0, 1], the keyframe's
    size) relative to ``keyframe``, from ``init`` (e.g. constant velocity; identity when None).
    ``readout``: the frame's readout fraction ρ = R/(R+τ) (``geometry.readout_fraction``; 0 = global
    shutter); with ρ > 0 the path spans the whole frame time, first row's start to last row's end.
    With ``config.trajectory`` cubic a straight ``init`` becomes a spline on the same path
    (``geometry.spline``) and the result is a :class:`~mbavo_jax.geometry.SplineTrajectory`.

    ``depth``: the frame's own depth map (metres; NaN or 0 = missing), used only when
    ``config.depth_weight > 0`` (``tracking.geometric``). ``blur_px``: :func:`predicted_blur_px` of
    ``init``'s middle-row path, when the caller has it already. Returns :class:`TrackResult`
    ``(trajectory, status, diagnostics)``; it never raises on bad image data.
    """
    t0 = time.perf_counter()
    image = _frame_image(frame, keyframe.cameras[0])
    config = config.for_image(*image.shape)
    init = ExposureTrajectory(Pose.identity(), Pose.identity()) if init is None else init
    init = as_trajectory(init, config.trajectory) if config.blur_aware else init
    if float(np.std(image)) < config.min_image_std or keyframe.n_points(0) < config.min_keyframe_points:
        return _refuse(keyframe, init, t0)
    pyr = pyramid(linearize(image, config.response_gamma), config.levels)
    depth_pyr = None
    if config.depth_weight > 0 and depth is not None:
        if np.shape(depth) != image.shape:
            raise ValueError(f"frame depth shape {np.shape(depth)} differs from image shape {image.shape}")
        depth_pyr = _depth_pyramid(depth, config.levels)
    blur0 = predicted_blur_px(keyframe, init.middle_row_path(readout)) if blur_px is None else blur_px
    first = _attempt("initial guess", keyframe, pyr, init, config, depth_pyr, blur0, readout)
    best, tried = _search(first, keyframe, pyr, init, config, depth_pyr, readout)
    fine = best.per_level[-1]
    diagnostics = dict(points=keyframe.n_points(0), hypothesis=best.name, levels=best.per_level, rms=fine["rms"], nrms=fine["nrms"],
                       affine=[float(best.affine_ab[0]), float(best.affine_ab[1])], depth_term=depth_pyr is not None, blur_px=blur0,
                       hypotheses_tried=tried, readout=float(readout), seconds=time.perf_counter() - t0)
    return TrackResult(best.trajectory, best.status, diagnostics)
