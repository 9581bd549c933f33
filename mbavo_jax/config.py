"""Every setting of mbavo in one place: frozen dataclasses with one line of help and a valid range per
field. The YAML files (``configs/default.yaml``), ``--set section.key=value``, the flags of
``mbavo synth | deblur | bench`` and docs/settings.md are derived from these classes; why a default
is what it is lives in docs/settings.md.

This module imports neither JAX nor NumPy, so the command line can parse and reject arguments fast.
Loading goes through OmegaConf structured configs (typed merge of defaults, YAML and dot-list
overrides, unknown keys rejected; a ``${...}`` is refused, never resolved); ranges are checked by
the dataclasses themselves, so a config built in Python is checked the same way.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import pathlib
import typing
from typing import Any, Callable

from .errors import ConfigError

__all__ = [
    "setting", "TrackerConfig", "OdometryConfig", "DeblurConfig", "EvalConfig", "RunConfig", "SynthConfig",
    "BenchConfig", "SweepConfig", "MonoConfig", "RuntimeConfig", "PRESETS", "DEPTH_SIGMA", "load_config", "default_yaml", "settings_markdown", "add_arguments",
    "from_arguments", "as_dict", "calibration_of", "HUBER_DRAWS",
]


@dataclasses.dataclass(frozen=True)
class Check:
    """A valid range: ``ok(value)`` for each value (each element of a tuple), ``text`` for the error."""

    ok: Callable[[Any], bool]
    text: str


POSITIVE = Check(lambda v: v > 0, "> 0")
NONNEG = Check(lambda v: v >= 0, ">= 0")
AT_LEAST_1 = Check(lambda v: v >= 1, ">= 1")
FRACTION = Check(lambda v: 0 < v <= 1, "in (0, 1]")
FINITE = Check(lambda v: math.isfinite(v), "finite")


def at_least(k) -> Check:
    return Check(lambda v: v >= k, f">= {k}")


def setting(default, help: str, check: Check | None = None, choices: tuple = ()):
    """A dataclass field with its one-line help, its range and (for strings) its choices."""
    return dataclasses.field(default=default, metadata={"help": help, "check": check, "choices": choices})


class Settings:
    """Mixin: field types, ranges and choices checked on construction (``section`` names the YAML
    section in messages); ``relations`` adds checks between fields."""

    section: typing.ClassVar[str] = ""

    def __post_init__(self):
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            value = getattr(self, f.name)
            key = f"{self.section}.{f.name}" if self.section else f.name
            _check_type(key, value, hints[f.name])
            check, choices = f.metadata.get("check"), f.metadata.get("choices")
            for v in value if isinstance(value, tuple) else (value,):
                if check is not None and not check.ok(v):
                    raise ConfigError(f"{key}: must be {check.text}, got {_show(value)}")
                if choices and v not in choices:
                    raise ConfigError(f"{key}: must be one of {', '.join(map(str, choices))}, got {value!r}")
        for message in self.relations():
            raise ConfigError(f"{self.section}: {message}" if self.section else message)

    def relations(self) -> list[str]:
        return []


def _show(v) -> str:
    return str(list(v)) if isinstance(v, tuple) else repr(v)


def _check_type(key: str, value, hint) -> None:
    """bool where bool, int where int (not bool, not 2.5), numbers where float, tuples of those."""
    origin = typing.get_origin(hint)
    if origin is tuple:
        args = [a for a in typing.get_args(hint) if a is not Ellipsis]
        if not isinstance(value, tuple):
            raise ConfigError(f"{key}: expected a list, got {value!r}")
        if Ellipsis not in typing.get_args(hint) and len(value) != len(args):
            raise ConfigError(f"{key}: expected {len(args)} values, got {_show(value)}")
        for v in value:
            _check_type(key, v, args[0])
        return
    if hint is bool:
        ok = isinstance(value, bool)
    elif hint is int:
        ok = isinstance(value, int) and not isinstance(value, bool)
    elif hint is float:
        ok = isinstance(value, (int, float)) and not isinstance(value, bool)
    elif hint is str:
        ok = isinstance(value, str)
    else:
        ok = True
    if not ok:
        raise ConfigError(f"{key}: expected {getattr(hint, '__name__', hint)}, got {value!r}")


# ----------------------------------------------------------------------------------------- tracker

PATTERN_SIZE = 8  # residuals per point: DSO's 8-pixel pattern (tracking.points.PATTERN)
MIN_CELL = 8  # smallest point-selection cell (px): patches (5x5 px) of neighbouring cells stay apart


def _grid_cells(height: int, width: int, cell: int) -> int:
    """Whole ``cell`` x ``cell`` blocks of a height x width level (``tracking.points.select_points``' grid)."""
    return (height // cell) * (width // cell)


def _fitted_cell(height: int, width: int, cell: int, need: int) -> int:
    """The largest cell, at most ``cell`` and at least ``MIN_CELL`` (if ``cell`` is), whose grid holds ``need`` cells."""
    c = cell
    while c > MIN_CELL and _grid_cells(height, width, c) < need:
        c -= 1
    return c


@dataclasses.dataclass(frozen=True)
class TrackerConfig(Settings):
    """The blur-aware tracker (``tracking.track``): points, virtual frames, solver, robust costs,
    status thresholds, the exposure-motion prior and the optional RGB-D depth term."""

    section: typing.ClassVar[str] = "tracker"

    levels: int = setting(4, "pyramid levels, solved coarse to fine", AT_LEAST_1)
    points: tuple[int, ...] = setting((384, 256, 192, 128), "max points per level (fine -> coarse); fixed shapes", AT_LEAST_1)
    cell: tuple[int, ...] = setting((30, 21, 15, 10), "point-selection grid cell per level (pixels)", AT_LEAST_1)
    grad_threshold: float = setting(8.0 / 255.0, "points need an intensity gradient above this (8/255)", NONNEG)
    n: int = setting(64, "virtual frames at full resolution (the paper's 64)", AT_LEAST_1)
    n_per_level: str = setting("halve", "halve: n/2^level on coarser levels (at least n_coarse_min); same: n on every level",
                               choices=("halve", "same"))
    n_coarse_min: int = setting(8, "fewest virtual frames on a coarse level with n_per_level: halve", AT_LEAST_1)
    n_mode: str = setting("fixed", "fixed | adaptive (n from the predicted blur, per level)", choices=("fixed", "adaptive"))
    n_min: int = setting(2, "adaptive n: at least this many virtual frames", AT_LEAST_1)
    n_per_blur_px: float = setting(2.0, "adaptive n: virtual frames per pixel of predicted blur (power of two, <= n)", POSITIVE)
    jacobian: str = setting("tangent", "tangent (each sample's derivative by a local move of its virtual camera, chained through the "
                                       "supplement's trajectory Jacobian) | analytic (the supplement's corrected formulas) | autodiff",
                            choices=("tangent", "analytic", "autodiff"))
    trajectory: str = setting("linear", "exposure path: linear (start and end poses, Eqs. 43-44) | cubic (cumulative cubic B-spline, "
                              "four control poses; its pose Jacobian always by autodiff)", choices=("linear", "cubic"))
    huber: float = setting(9.0 / 255.0, "Huber threshold on [0, 1] intensities (9/255)", POSITIVE)
    max_steps: tuple[int, ...] = setting((8, 10, 12, 20), "Levenberg-Marquardt steps per level (fine -> coarse)", AT_LEAST_1)
    fresh_jacobian_levels: int = setting(1, "the coarsest this many pyramid levels recompute the photometric Jacobian at every LM "
                                         "step (they capture the motion away from the prediction); the finer ones, when blur-aware "
                                         "(n > 1), compute it once, at their start, and their steps evaluate residuals only (the chord "
                                         "method; robust weights, affine columns and the other blocks stay exact); >= levels: all recompute", NONNEG)
    rtol: float = setting(1e-3, "LM relative tolerance (optimistix, RMS norm)", POSITIVE)
    atol: float = setting(1e-4, "LM absolute tolerance (optimistix, RMS norm)", POSITIVE)
    outlier_sigma: float = setting(2.5, "drop patches whose cost exceeds mean + k std (all but the coarsest level; 0 = off)", NONNEG)
    affine: bool = setting(True, "estimate the affine brightness e^a I + b")
    blur_aware: bool = setting(True, "false: classic direct alignment (start = end, one virtual frame)")
    min_valid: int = setting(60, "fewer valid residuals on a level: too few points", AT_LEAST_1)
    min_keyframe_points: int = setting(8, "a keyframe with fewer selected points cannot be tracked against", AT_LEAST_1)
    min_image_std: float = setting(1e-4, "a frame whose intensities vary less than this (black, saturated) is not tracked", NONNEG)
    good_nrms: float = setting(0.5, "residual RMS / contrast above this: try the motion hypotheses", POSITIVE)
    lost_nrms: float = setting(1.0, "residual RMS / contrast above this: the frame is lost (~1.4 for an unrelated image)", POSITIVE)
    diverged_factor: float = setting(2.0, "final RMS above factor x initial RMS + diverged_margin: diverged", POSITIVE)
    diverged_margin: float = setting(0.02, "see diverged_factor (intensity units)", NONNEG)
    hypotheses: bool = setting(True, "try DSO-style motion hypotheses when the first solve is poor")
    hypothesis_rotation_deg: float = setting(2.0, "the rotation hypotheses turn the guess by this much about each axis", POSITIVE)
    response_gamma: float = setting(1.0, "photometric calibration: images are linearised as I^gamma (camera.yaml's wins)", POSITIVE)
    readout_s: float = setting(0.0, "rolling shutter: first row's start to last row's start, seconds (0 = global shutter; "
                                     "camera.yaml's readout_ms wins)", NONNEG)
    blur_prior: float = setting(0.01, "weak prior on the exposure motion start^-1 end: its intensity scale (0 = off)", NONNEG)
    blur_prior_min_rad: float = setting(5e-4, "prior sigma = min + rel * |initial exposure motion| (radians)", POSITIVE)
    blur_prior_rel: float = setting(0.2, "see blur_prior_min_rad", NONNEG)
    curvature_prior_rad: float = setting(0.0, "trajectory: cubic: prior sigma (radians) on the control poses' second differences "
                                               "(0 = off; small: nearly straight paths)", NONNEG)
    depth_weight: float = setting(0.0, "RGB-D: weight of the frame's depth map, intensity units per sigma (0 = images only)", NONNEG)
    depth_sigma: tuple[float, float] = setting((0.0012, 0.0019), "depth noise sigma(z) = a + b (z - 0.4)^2 m (Kinect v1; camera.yaml's wins)", NONNEG)
    depth_huber: float = setting(3.0, "Huber threshold of the depth term, in sigma", POSITIVE)
    depth_outlier: float = setting(20.0, "depth residuals beyond this many sigma (occlusions) cost as much as one at it: they stop pulling the pose", POSITIVE)
    depth_levels: int = setting(3, "the depth term is used on this many finest levels (2 for weights >= 0.1)", AT_LEAST_1)
    depth_stride: int = setting(8, "grid spacing of the depth term's keyframe points (full-resolution pixels)", AT_LEAST_1)
    depth_edge: float = setting(0.02, "depth samples whose neighbours differ by more than this fraction are edges: dropped", POSITIVE)

    @property
    def min_cells(self) -> int:
        """Point cells a pyramid level must offer: 1.5x the points whose residuals reach ``min_valid``."""
        return math.ceil(1.5 * self.min_valid / PATTERN_SIZE)

    @functools.lru_cache(maxsize=64)
    def for_image(self, height: int, width: int) -> "TrackerConfig":
        """These settings for a ``height`` x ``width`` image (the one rule for small and large images).

        A level is used when its grid can hold ``min_cells`` cells of ``MIN_CELL`` px (or of its own
        cell, if smaller); coarser levels are dropped with their entries of points, cell and max_steps.
        On each level used, the cell shrinks (not below that floor) until the level holds ``min_cells``
        cells. Returns ``self`` when nothing changes; raises ConfigError when not even the
        full-resolution level qualifies."""
        need, floors = self.min_cells, [min(MIN_CELL, c) for c in self.cell]
        levels = 0
        while levels < self.levels and _grid_cells(height >> levels, width >> levels, floors[levels]) >= need:
            levels += 1
        if levels == 0:
            have = _grid_cells(height, width, floors[0])
            fix = f"lower tracker.min_valid to {math.floor(have * PATTERN_SIZE / 1.5)} or less" if have else "use larger images"
            raise ConfigError(f"{width}x{height} images are too small to track: they hold {have} point cell(s) of {floors[0]} px, "
                              f"tracker.min_valid={self.min_valid} needs {need} ({fix})")
        cells = tuple(_fitted_cell(height >> l, width >> l, self.cell[l], need) for l in range(levels))
        if levels == self.levels and cells == self.cell[:levels]:
            return self
        return dataclasses.replace(self, levels=levels, points=self.points[:levels], cell=cells,
                                   max_steps=self.max_steps[:levels])

    def size_note(self, height: int, width: int) -> str:
        """One line saying what :meth:`for_image` changes for this image size ('' when nothing)."""
        eff = self.for_image(height, width)
        if eff == self:
            return ""
        parts = []
        if eff.levels < self.levels:
            h, w = height >> eff.levels, width >> eff.levels
            parts.append(f"using {eff.levels} pyramid levels instead of {self.levels} (a {w}x{h} px level is too small)")
        if eff.cell != self.cell[: eff.levels]:
            parts.append(f"point cells {list(eff.cell)} px instead of {list(self.cell[: eff.levels])}")
        if not parts:
            return ""
        return f"{width}x{height}: " + ", ".join(parts) + f" (each level needs {self.min_cells} point cells of at least {MIN_CELL} px)"

    def relations(self) -> list[str]:
        out = [f"{name} needs one entry per level ({self.levels}), got {list(getattr(self, name))}"
               for name in ("points", "cell", "max_steps") if len(getattr(self, name)) < self.levels]
        if self.depth_outlier <= self.depth_huber:
            out.append(f"depth_outlier ({self.depth_outlier}) must exceed depth_huber ({self.depth_huber})")
        if self.depth_sigma[0] <= 0:
            out.append(f"depth_sigma: a must be > 0, got {list(self.depth_sigma)}")
        return out


# ---------------------------------------------------------------------------------------- odometry


@dataclasses.dataclass(frozen=True)
class OdometryConfig(Settings):
    """The sequence loop (``odometry.run_odometry``): keyframe decisions, recovery, exposure times."""

    section: typing.ClassVar[str] = "odometry"

    mode: str = setting("auto", "rgbd: track with the sequence's depth; mono: images only (the depth is not read); auto: rgbd when "
                        "the sequence has depth", choices=("auto", "rgbd", "mono"))
    keyframe_flow: float = setting(0.1, "new keyframe when the mean point flow exceeds this fraction of the image width", POSITIVE)
    keyframe_max_blur_px: float = setting(float("inf"), "... unless the frame is blurred more than this (mean px): wait for a sharper one", POSITIVE)
    keyframe_flow_max: float = setting(0.15, "... but no longer than until the flow exceeds this fraction of the width", POSITIVE)
    keyframe_min_visible: float = setting(0.6, "... or fewer than this fraction of its points are in view (whatever the blur)", FRACTION)
    deblur_min_blur_px: float = setting(2.0, "deblur a new keyframe blurred more than this (full-resolution px)", NONNEG)
    deblur_first_keyframe: bool = setting(True, "deblur the first keyframe (and one made after drops) once the next frame gives the velocity")
    reset_after_drops: int = setting(3, "consecutive dropped frames before the current frame becomes a keyframe", AT_LEAST_1)
    reset_min_image_std: float = setting(1e-3, "a frame whose intensities vary less than this never becomes a reset keyframe", NONNEG)
    exposure: str = setting("auto", "exposure times: auto (the data's when it records them or exposure_s > 0, else estimated); "
                            "known (required); estimate (ignore the data's, estimate online); none (frames are sharp)",
                            choices=("auto", "known", "estimate", "none"))
    exposure_s: float = setting(0.0, "exposure time (s) to use when the sequence records none (0: not given)", NONNEG)
    exposure_guess: float = setting(0.5, "estimated exposure: fraction of the frame interval assumed until frames are tracked", FRACTION)
    exposure_window: int = setting(30, "estimated exposure: weighted median over this many recent samples", AT_LEAST_1)
    exposure_pair_ratio: float = setting(1.3, "estimated exposure: a sample pairs two raw frames whose speeds differ by this factor", at_least(1.05))
    exposure_pair_frames: int = setting(6, "estimated exposure: a frame is paired with one of this many recent frames", AT_LEAST_1)
    exposure_pair_levels: int = setting(2, "estimated exposure: a pair's frames are tracked against each other on this many finest "
                                        "pyramid levels (both are tracked already: their relative pose needs no capture range)", AT_LEAST_1)
    short_exposure: float = setting(0.25, "a frame exposed for at most this fraction of the frame interval (known or estimated), "
                                    "with a velocity to predict its blur, is tracked with adaptive n (tracker.n_mode)", FRACTION)
    sharp_blur_px: float = setting(0.5, "a frame tracked with adaptive n whose predicted blur is below this (full-resolution px) is "
                                   "tracked as sharp: one pose, start = end (global shutter, linear path; 0 = never)", NONNEG)
    adaptive_below_px: float = setting(6.0, "a frame whose predicted blur (constant-velocity guess, full-resolution px) is below this "
                                       "is tracked with adaptive n (tracker.n_mode: few virtual frames for a little blur; global "
                                       "shutter, linear path; 0 = never)", NONNEG)
    exposure_settled: float = setting(0.05, "estimated exposure: settled when it moved by at most this fraction of the frame interval "
                                      "over its last 6 samples; then only every exposure_thin-th tracked frame is paired", FRACTION)
    exposure_thin: int = setting(8, "see exposure_settled (1: every frame is paired)", AT_LEAST_1)
    exposure_probe: int = setting(60, "estimated exposure: at most this many first frames run once before the run (nothing written; "
                                  "tracked blind to blur, no keyframe deblurred), stopping once the estimate has settled (exposure_settled); "
                                  "the run starts from their exposure samples, not the guess, and does not pair them again (0 = off)", NONNEG)
    reject_rms_ratio: float = setting(2.5, "a tracked frame whose residual RMS exceeds this multiple of the largest of the recent "
                                      "frames' is dropped as implausible (0 = off)", NONNEG)
    reject_jump_ratio: float = setting(4.0, "... or whose pose lies further from the constant-velocity prediction than this multiple "
                                       "of the recent frames' median distance plus reject_jump_px, per frame interval (0 = off)", NONNEG)
    reject_jump_px: float = setting(4.0, "see reject_jump_ratio (full-resolution pixels)", NONNEG)
    reject_window: int = setting(10, "the recent tracked frames the two checks above compare with (they start after 3)", AT_LEAST_1)
    confirm_jumps: bool = setting(True, "a fit implausible only by its distance from the prediction is tracked again by local descent "
                                  "from the last tracked frame's pose, and kept when that start lies at least, and the two fits at "
                                  "most, reject_jump_px apart")
    triptychs: int = setting(3, "blurry / reblurred / deblurred images written for the first deblurred keyframes", NONNEG)


@dataclasses.dataclass(frozen=True)
class DeblurConfig(Settings):
    """Keyframe deblurring (``deblur.deblur``): min ||A x - b||^2 + lambda ||grad x||^2 by conjugate gradients."""

    section: typing.ClassVar[str] = "deblur"

    n: int = setting(0, "virtual frames of the blur operator; 0: one per pixel of blur (95th percentile), rounded up as n_step says", NONNEG)
    n_min: int = setting(8, "with n = 0: at least this many virtual frames", AT_LEAST_1)
    n_max: int = setting(64, "with n = 0: at most this many virtual frames", AT_LEAST_1)
    n_step: int = setting(16, "with n = 0: a power of two up to this many virtual frames, a multiple of it above (0: powers of "
                          "two only)", NONNEG)
    iterations: int = setting(30, "conjugate-gradient iterations, at most", AT_LEAST_1)
    tolerance: float = setting(0.01, "stop CG once the residual of the normal equations is below this fraction of the first "
                               "(0: always all iterations)", Check(lambda v: 0 <= v < 1, "in [0, 1)"))
    regularization: float = setting(2e-2, "weight lambda of the gradient penalty", NONNEG)
    coarse_to_fine: bool = setting(True, "solve at half resolution first (half the virtual frames, the same iterations and "
                                   "tolerance), then fine_iterations full-resolution steps from it upsampled")
    fine_iterations: int = setting(6, "with coarse_to_fine: conjugate-gradient iterations at full resolution", AT_LEAST_1)
    solver: str = setting("table", "table (every sample's bilinear cell found once per keyframe) | render (render_blurry at "
                          "every iteration: the reference, slower)", choices=("table", "render"))


@dataclasses.dataclass(frozen=True)
class EvalConfig(Settings):
    """How ``mbavo track`` and the benchmarks score a run against ground truth."""

    section: typing.ClassVar[str] = "evaluation"

    t_max_diff: float = setting(0.02, "largest timestamp difference (s) when matching estimated and true poses", POSITIVE)
    align: str = setting("se3", "Umeyama alignment before the ATE of RGB-D runs (monocular runs are always scored after sim3: "
                         "their scale is free)", choices=("none", "se3", "sim3"))


@dataclasses.dataclass(frozen=True)
class MonoConfig(Settings):
    """The monocular system (``mbavo track --mode mono``): initialisation from images, candidate
    points traced along epipolar lines, and the windowed photometric bundle adjustment (DSO's)."""

    section: typing.ClassVar[str] = "mono"

    # --- the window and its bundle adjustment (mono.ba)
    window: int = setting(7, "keyframes in the bundle-adjustment window (DSO's 7)", at_least(2))
    points: int = setting(2000, "active points in the window, padded to this many (DSO's 2000)", AT_LEAST_1)
    ba_iterations: int = setting(6, "Levenberg-Marquardt iterations of one bundle adjustment", AT_LEAST_1)
    ba_huber: float = setting(9.0 / 255.0, "Huber threshold of the photometric residuals on [0, 1] intensities", POSITIVE)
    ba_outlier: float = setting(12.0 / 255.0, "a point-keyframe pattern whose RMS residual exceeds this is an outlier", POSITIVE)
    ba_lambda: float = setting(1e-4, "initial Levenberg-Marquardt damping (relative to the diagonal)", POSITIVE)
    ba_blur_samples: int = setting(1, "virtual frames of the blur model in the bundle adjustment: each keyframe's recorded (blurry) image is compared with its points' hosts blurred along its exposure path; 1: the deblurred keyframes compared with each other (the paper's back-end)", AT_LEAST_1)
    deblur_regularization: float = setting(0.1, "the keyframe deblurring's gradient penalty in monocular runs (in place of deblur.regularization): its depth is the window's points filled in between them, so its blur kernels are less sure than a depth sensor's and a weak penalty rings, which makes the keyframe's new points outliers in the bundle adjustment", NONNEG)
    fresh_jacobian_levels: int = setting(4, "the tracker's levels that recompute the photometric Jacobian at every LM step in monocular runs, in place of "
                                         "tracker.fresh_jacobian_levels (>= tracker.levels: all, the per-step Jacobian; tracking is a small part of "
                                         "a monocular frame's time)", NONNEG)
    # --- candidate (immature) points (mono.candidates)
    candidates: int = setting(1500, "candidate points selected on each new keyframe (DSO's 1500)", AT_LEAST_1)
    trace_outlier: float = setting(16.0 / 255.0, "a candidate whose best match along its epipolar line has a larger RMS pattern residual is an outlier", POSITIVE)
    ready_interval: float = setting(1.0, "a candidate joins the window once its inverse-depth interval is at most this fraction of its midpoint", POSITIVE)
    # --- initialisation (mono.init)
    init_min_parallax_deg: float = setting(0.5, "initialise once the median parallax angle of the tracked points exceeds this", POSITIVE)
    init_min_tracks: int = setting(80, "fewer tracked corners (direct start: converged points) than this: too little texture to initialise", at_least(8))
    init_max_frames: int = setting(60, "start initialising again from a later frame after this many frames without success", AT_LEAST_1)
    init_corners: int = setting(1000, "at most this many corners tracked from the reference frame (spread over the image)", at_least(8))
    init_corner_contrast: float = setting(8.0 / 255.0, "a corner needs about this step contrast on [0, 1] intensities (above noise)", POSITIVE)
    init_ransac_px: float = setting(2.0, "essential-matrix RANSAC: largest distance (px) of an inlier from its epipolar line", POSITIVE)
    init_min_inlier_ratio: float = setting(0.6, "fewer essential-matrix inliers than this fraction of the tracks: geometry failed", FRACTION)
    initialiser: str = setting("corners", "how the monocular system starts: corners (KLT tracks, the essential matrix; mono.init) or direct "
                               "(DSO's coarse initialiser, blur-aware: pose, brightness and inverse depths aligned photometrically; "
                               "mono.direct_init)", choices=("corners", "direct"))
    init_direct_points: int = setting(1000, "direct start: gradient-selected points of the reference frame (fixed count, padded)", at_least(8))
    init_direct_blur_samples: int = setting(8, "direct start: virtual frames of the blur model along the current frame's exposure path "
                                            "(1: DSO's residual, blind to blur)", AT_LEAST_1)
    init_direct_exposure: float = setting(0.5, "direct start: the exposure as a fraction of the frame interval (the blur model's path is "
                                          "this much of the constant-velocity motion between frames)", FRACTION)
    init_direct_snap: float = setting(2.5 / 150.0, "direct start: the prior pulling inverse depths to 1 and the translation to 0 lets go "
                                      "once sqrt(|t|² + mean (d − 1)²) exceeds this (the translation relative to the depth; DSO's "
                                      "2.5/150)", POSITIVE)
    init_direct_frames: int = setting(5, "direct start: the system starts this many frames after the prior let go (DSO's 5)", NONNEG)
    init_direct_min_fit: float = setting(0.5, "direct start: fewer of the points in view fitting (pattern RMS under ba_outlier) than this fraction: the "
                                         "alignment diverged, start again from a later frame", FRACTION)
    init_direct_max_depth_std: float = setting(0.5, "direct start: a point joins the window only if its inverse depth is known within "
                                               "this fraction of itself (for 9/255 of photometric noise)", POSITIVE)
    # --- keyframes and restarts (odometry.mono, mono.keyframes)
    keyframe_shift: float = setting(0.5, "weight of DSO's point-shift keyframe rule (1 = DSO's weights, 0 = off): a new keyframe also when the weighted RMS point shift, relative to width + height, exceeds 1", NONNEG)
    ba_max_move: float = setting(0.02, "a bundle adjustment that moves the new keyframe's view of the window's points by more than this fraction of the image width (median) is run again without the points it dropped (undone if it moves that far again)", POSITIVE)
    exposure_probe: int = setting(60, "estimated exposure: at most this many first frames run once before the run (as odometry.exposure_probe, "
                                  "the monocular loop blind to blur, nothing deblurred or written), stopping once the estimate has settled "
                                  "(odometry.exposure_settled); the run's keyframes are then deblurred along the estimate, not the guess (0 = off)",
                                  NONNEG)
    restart_motions: int = setting(9, "frame-to-frame motions kept: after a loss the one of median speed carries the last good pose to the new start, which keeps that speed", AT_LEAST_1)


@dataclasses.dataclass(frozen=True)
class RuntimeConfig(Settings):
    """How the process runs: JAX's persistent compilation cache and the compiled programs it holds
    (``mbavo_jax.runtime``), and how often a monocular run leaves the checkpoint that --resume continues from."""

    section: typing.ClassVar[str] = "runtime"

    compilation_cache: bool = setting(True, "keep compiled programs on disk so that a second run with the same settings compiles nothing")
    cache_dir: str = setting("", "folder of the compilation cache ('' = $XDG_CACHE_HOME/mbavo_jax/jax, i.e. ~/.cache/mbavo_jax/jax); "
                                 "programs go in a subfolder per jaxlib version and processor")
    cache_max_mb: int = setting(2048, "size of the compilation cache: least recently used programs are removed past it; reads and "
                                      "writes take a file lock, so that processes sharing the cache never read a half-written program",
                                POSITIVE)
    release_programs_at: float = setting(0.5, "a run first releases the compiled programs this process holds (they come back from the "
                                         "compilation cache) when their memory maps pass this fraction of the system's limit "
                                         "(vm.max_map_count): past it XLA cannot load another program and the process dies", FRACTION)
    checkpoint_every: int = setting(1, "monocular runs: write the --resume checkpoint (checkpoint.npz) after every k-th frame; a resume "
                                    "goes on from the last one, the frames after it tracked again (0: none, no --resume)", NONNEG)
    trim_memory: bool = setting(True, "after each frame, hand the memory that was freed back to the system (glibc's malloc_trim; "
                                "nothing elsewhere), so that a long run's resident memory stays flat: else a new program's work "
                                "buffers (a keyframe deblurred with more virtual frames) stay resident for the rest of the run")


@dataclasses.dataclass(frozen=True)
class RunConfig:
    """The sections of a config file (``configs/default.yaml``): one per settings class."""

    tracker: TrackerConfig = dataclasses.field(default_factory=TrackerConfig)
    odometry: OdometryConfig = dataclasses.field(default_factory=OdometryConfig)
    deblur: DeblurConfig = dataclasses.field(default_factory=DeblurConfig)
    evaluation: EvalConfig = dataclasses.field(default_factory=EvalConfig)
    mono: MonoConfig = dataclasses.field(default_factory=MonoConfig)
    runtime: RuntimeConfig = dataclasses.field(default_factory=RuntimeConfig)

    def replace(self, **sections) -> "RunConfig":
        """A copy with fields of sections replaced: ``cfg.replace(tracker=dict(n=32))``."""
        return dataclasses.replace(self, **{k: dataclasses.replace(getattr(self, k), **v) for k, v in sections.items()})


# --------------------------------------------------------------------------------------- generator

# sigma(z) = a + b (z - 0.4)^2 metres of each generated depth model (tracking.geometric uses the same form)
DEPTH_SIGMA: dict[str, tuple[float, float]] = {
    "exact": (0.0005, 0.0),  # 16-bit quantisation (0.2 mm) and bilinear interpolation
    "sensor": (0.0012, 0.0019),  # Kinect v1 axial noise, Nguyen, Izadi & Lovell 2012
}


@dataclasses.dataclass(frozen=True)
class SynthConfig(Settings):
    """A generated blurry sequence (``mbavo synth``)."""

    frames: int = setting(100, "number of frames", AT_LEAST_1)
    width: int = setting(640, "image width", at_least(16))
    height: int = setting(480, "image height", at_least(16))
    fps: float = setting(30.0, "frame rate", POSITIVE)
    exposure_ms: float = setting(20.0, "exposure time tau in ms", NONNEG)
    speed: float = setting(0.6, "peak camera speed (m/s)", NONNEG)
    rotation_rate: float = setting(60.0, "peak rotation rate (deg/s)", NONNEG)
    subframes: int = setting(64, "sub-frame renders per exposure", AT_LEAST_1)
    response_gamma: float = setting(2.2, "camera response: display = radiance^(1/gamma)", POSITIVE)
    noise: float = setting(0.002, "Gaussian noise std on [0, 1] intensities", NONNEG)
    seed: int = setting(0, "seed (the output is deterministic for a seed)", NONNEG)
    real_textures: bool = setting(True, "use photos from ../shared/data as textures when present")
    depth_model: str = setting("exact", "exact z-depth, or as a Kinect-class sensor writes it (noise, holes, dropouts)",
                               choices=tuple(DEPTH_SIGMA))
    scene: str = setting("room", "room: 8x5x9 m, 4 boxes; cluttered: the room with 26 boxes 1.6-5 m away; deep: a 6x4x46 m "
                         "hall, boxes 2-35 m; distant: every surface 25-80 m away (rotation dominates the blur); plane: one textured "
                         "plane 3 m ahead, its normal turned 30 deg and 10 deg from the view axis (a wall seen obliquely), a far "
                         "background where a view passes its edge", choices=("room", "cluttered", "deep", "distant", "plane"))
    texture: str = setting("mixed", "mixed: procedural noise, tiles and blobs (and photos from ../shared/data with real_textures); "
                           "photo: photo-like dead-leaves textures on every surface (occluding discs of power-law sizes: natural "
                           "images' 1/f amplitude spectrum and edges)", choices=("mixed", "photo"))
    blur_px: float = setting(0.0, "target mean blur (px) of the images: exposure_ms is scaled so that the sequence's mean blur is "
                             "this (the motion kept; measured on 8 frames); the blur reached is reported (mean_blur_px in synth.yaml "
                             "and mbavo synth's line); 0: exposure_ms as given", NONNEG)
    exposure_info: bool = setting(True, "write the exposure time (camera.yaml exposure_ms, times.txt); false: as TUM/EuRoC/KITTI "
                                        "data come, with the ground-truth exposure paths kept only as groundtruth_exposure.txt")
    readout_ms: float = setting(0.0, "rolling shutter: readout time in ms from the first row's exposure start to the last row's "
                                "(0 = global shutter); rows are rendered at their own times", NONNEG)
    shake_deg: float = setting(0.0, "handheld shake: amplitude (deg) of a rotation oscillation about the x and y axes added to the "
                               "path, so that an exposure spans a curved path (0 = none)", NONNEG)
    shake_hz: float = setting(12.0, "handheld shake: its frequency (Hz)", POSITIVE)
    imu: bool = setting(False, "simulate an IMU along the camera path: imu.txt (timestamp gx gy gz ax ay az), camera.yaml's imu "
                               "block (T_cam_imu, rate, time offset, noise), the true biases in imu_groundtruth.txt")
    imu_rate_hz: float = setting(200.0, "IMU: sample rate (Hz)", POSITIVE)
    imu_time_offset_ms: float = setting(0.0, "IMU: clock offset t_imu = t_cam + offset (ms; Kalibr's timeshift_cam_imu)", FINITE)
    imu_extrinsics: str = setting("0.03 -0.01 -0.02 0 0 0.7071068 0.7071068",
                                  "IMU: T_cam_imu, the IMU in the camera frame, 'tx ty tz qx qy qz qw' (m, unit quaternion)")
    imu_gyro_noise: float = setting(1.6968e-4, "IMU: gyroscope white noise density (rad/s/sqrt(Hz); EuRoC's ADIS16448)", NONNEG)
    imu_gyro_walk: float = setting(1.9393e-5, "IMU: gyroscope bias random walk (rad/s^2/sqrt(Hz))", NONNEG)
    imu_accel_noise: float = setting(2.0e-3, "IMU: accelerometer white noise density (m/s^2/sqrt(Hz))", NONNEG)
    imu_accel_walk: float = setting(3.0e-3, "IMU: accelerometer bias random walk (m/s^3/sqrt(Hz))", NONNEG)
    imu_gyro_bias: float = setting(0.005, "IMU: std (rad/s, per axis) of the gyroscope's initial bias", NONNEG)
    imu_accel_bias: float = setting(0.05, "IMU: std (m/s^2, per axis) of the accelerometer's initial bias", NONNEG)

    def imu_pose(self) -> list[float]:
        """``imu_extrinsics`` as 7 numbers [tx, ty, tz, qx, qy, qz, qw], the quaternion normalised;
        ConfigError when it is not 7 finite numbers with a quaternion of norm 1 (within 1e-3)."""
        try:
            v = [float(x) for x in self.imu_extrinsics.replace(",", " ").split()]
        except ValueError:
            v = []
        norm = math.sqrt(sum(x * x for x in v[3:])) if len(v) == 7 and all(map(math.isfinite, v)) else 0.0
        if abs(norm - 1.0) > 1e-3:
            raise ConfigError(f"imu_extrinsics: expected 'tx ty tz qx qy qz qw' with a unit quaternion, got {self.imu_extrinsics!r}")
        return v[:3] + [x / norm for x in v[3:]]

    def relations(self) -> list[str]:
        frame_ms, problems = 1000.0 / self.fps, []
        try:
            self.imu_pose()
        except ConfigError as exc:
            problems.append(str(exc))
        if self.readout_ms > frame_ms:
            problems.append(f"readout_ms ({self.readout_ms:g}) must not exceed the frame interval 1000/fps ({frame_ms:.3g} ms): "
                            "the sensor reads one frame at a time")
        if self.exposure_ms > frame_ms:
            problems.append(f"exposure_ms ({self.exposure_ms:g}) must not exceed the frame interval 1000/fps ({frame_ms:.3g} ms): "
                            "a frame's exposure ends before the next one starts")
        if self.blur_px > 0 and self.subframes == 1:
            problems.append(f"blur_px ({self.blur_px:g}) needs subframes > 1 to render a blur (e.g. --subframes 64)")
        return problems


# Mean blur length at 640x480 (``mbavo synth`` reports it): none 0 px, mild ~5, strong ~20, extreme ~40.
PRESETS: dict[str, dict] = {
    "none": dict(exposure_ms=0.0, subframes=1, speed=0.3, rotation_rate=25.0),
    "mild": dict(exposure_ms=20.0, speed=0.37, rotation_rate=30.5),
    "strong": dict(exposure_ms=25.0, speed=0.77, rotation_rate=103.0),
    "extreme": dict(exposure_ms=30.0, speed=1.2, rotation_rate=181.0),
}


HUBER_DRAWS = (TrackerConfig().huber, 0.035294, 0.03533, 0.03526, 0.03537, 0.03522, 0.0354)
"""Huber thresholds a part in a thousand apart, the default (9/255) first: the draws of ``bench mono --draws`` and
``scripts/ate_draws.py``. Each changes every robust weight by a rounding-sized amount and nothing else, so
the spread of a run's score over them is its noise floor."""


@dataclasses.dataclass(frozen=True)
class BenchConfig(Settings):
    """``mbavo bench tracking | odometry | mono | rolling-shutter``: which data, which methods."""

    frames: int = setting(20, "frame pairs (tracking) or frames per sequence (odometry)", AT_LEAST_1)
    preset: str = setting("strong,none", "tracking: comma-separated blur presets to generate and run")
    presets: str = setting("none,mild,strong,extreme", "odometry, mono: blur presets, or generated scene sequences by name: "
                           "<scene>[_photo]_b<px>[_<preset>] (e.g. plane_b10, plane_photo_b20_extreme: the scene, photo-like "
                           "textures, a mean blur of px pixels by the exposure, the preset's motion, strong unless named)")
    sensor_presets: str = setting("strong,extreme", "odometry: presets generated again with Kinect-class depth ('' to skip)")
    tum: str = setting("../shared/data/tum_fr1_xyz_head37", "odometry, mono: real RGB-D clip to blur ('' to skip; a path that is not "
                                                               "there is looked up by its name in the shared data folder)")
    tum_blur_px: str = setting("20", "odometry: mean blur (px) of the blurred TUM clip, comma-separated; one row "
                               "tum_blurred<px> each")
    kitti: str = setting("../shared/data/kitti07_head160", "mono: real monocular clip ('' to skip; looked up like --tum)")
    width: int = setting(640, "image width of generated sequences", at_least(16))
    height: int = setting(480, "image height of generated sequences", at_least(16))
    seed: int = setting(0, "seed of generated sequences", NONNEG)
    seeds: str = setting("", "mono, odometry: more seeds of the generated presets, comma-separated ('': none). mono: rows "
                         "<preset>_s<seed>_noexp, and the output adds each method's mean ATE over all seeds and its ratio to "
                         "mono_n1; odometry: rows named as with sizes")
    sizes: str = setting("", "odometry: more image sizes of the generated sequences, comma-separated WxH (e.g. 320x240,640x480); "
                         "with more than one size or seed in a run every generated row is named <name>_<w>x<h>_s<seed> "
                         "('': width x height only)")
    draws: int = setting(1, "mono: runs of each method on each sequence, each at another Huber draw (HUBER_DRAWS, scaled to "
                         "tracker.huber); above 1 the table adds each run's mean ATE over its draws, and the means over seeds use it",
                         AT_LEAST_1)
    dso: str = setting("", "mono: a dso_dataset binary (DSO built by ../shared/tools/build_dso.sh): adds the method dso, DSO run "
                       "on each sequence without photometric calibration ('': without DSO)")
    dso_timeout: float = setting(600.0, "mono: seconds DSO may run on one sequence", POSITIVE)
    out: str = setting("runs/bench_odometry", "odometry: output folder")
    methods: str = setting("", "odometry: comma-separated subset of the methods (default all)")
    depth_weight: float = setting(0.03, "odometry: tracker.depth_weight of the *_depth methods", NONNEG)
    no_peers: bool = setting(False, "skip Open3D and OpenCV")
    hide_exposure: str = setting("", "also run these sequences (table names, comma-separated, or 'all') with their exposure "
                                 "metadata removed, as <name>_noexp ('': none)")
    scenes: str = setting("", "odometry: also generate these scenes (cluttered, deep, distant; comma-separated) at scene_presets")
    scene_presets: str = setting("strong,extreme", "odometry: the blur presets of the extra scenes")
    peer_depth_max: float = setting(4.0, "depth range (m) of Open3D and OpenCV odometry (their own default; docs/benchmarks.md compares 20 m)", POSITIVE)
    speed_reps: int = setting(3, "speed: unprofiled runs each of ours and of n = 1, in turns after a warm-up; ratios of their medians",
                              AT_LEAST_1)
    startup: bool = setting(True, "speed: also time the start-up of fresh processes (empty cache, full cache, none)")
    compare: str = setting("", "speed: also run the loop with these settings ('section.key=value', ';'-separated), timed in turns "
                           "with ours and scored beside it (ATE, keyframes, keyframe PSNR); '': none")
    readouts: str = setting("0,15,30", "rolling-shutter: readout times (ms) of the generated sequences, comma-separated")
    shake_deg: float = setting(0.5, "rolling-shutter: handheld-shake amplitude (deg) of a second, curved-path set of sequences "
                               "(every preset and readout again; 0 = none)", NONNEG)

    def relations(self) -> list[str]:
        bad = [s for s in self.seeds.split(",") if s.strip() and not s.strip().isdigit()]
        out = [f"seeds: not a non-negative integer: {', '.join(bad)}"] if bad else []
        sizes = [s for s in self.sizes.split(",") if s.strip() and _size(s) is None]
        out += [f"sizes: not WxH with both at least 16: {', '.join(sizes)}"] if sizes else []
        blurs = [b for b in self.tum_blur_px.split(",") if b.strip() and _blur(b) is None]
        out += [f"tum_blur_px: not a number > 0: {', '.join(blurs)}"] if blurs else []
        return out + ([f"draws: at most {len(HUBER_DRAWS)}"] if self.draws > len(HUBER_DRAWS) else [])

    def seed_list(self) -> list[int]:
        """``seed`` and then the other ``seeds``, each once."""
        return list(dict.fromkeys([self.seed, *(int(s) for s in self.seeds.split(",") if s.strip())]))

    def size_list(self) -> list[tuple[int, int]]:
        """(width, height) and then the other ``sizes``, each once."""
        return list(dict.fromkeys([(self.width, self.height), *(_size(s) for s in self.sizes.split(",") if s.strip())]))

    def tum_blur_list(self) -> list[float]:
        """The blur amounts (px) of the blurred TUM clip's rows, each once."""
        return list(dict.fromkeys(_blur(b) for b in self.tum_blur_px.split(",") if b.strip()))


def _size(text: str) -> tuple[int, int] | None:
    """'640x480' as (640, 480); None unless two integers of at least 16."""
    parts = text.strip().lower().split("x")
    if len(parts) != 2 or not all(p.isdigit() for p in parts):
        return None
    w, h = int(parts[0]), int(parts[1])
    return (w, h) if min(w, h) >= 16 else None


def _blur(text: str) -> float | None:
    """A blur amount in px: a finite number > 0, else None."""
    try:
        v = float(text)
    except ValueError:
        return None
    return v if math.isfinite(v) and v > 0 else None


@dataclasses.dataclass(frozen=True)
class SweepConfig(Settings):
    """``mbavo sweep`` and ``mbavo bench odometry``: how the runs are executed (``mbavo_jax.sweep``)."""

    jobs: int = setting(1, "runs at once: worker processes (local), or what a Ray started here holds (not with address)", AT_LEAST_1)
    engine: str = setting("local", "local: a process pool on this machine; ray: Ray tasks (pip install -e '.[ray]')",
                          choices=("local", "ray"))
    address: str = setting("", "ray: address of a running cluster (e.g. auto, ray://head:10001); '': start Ray on this machine")
    threads: int = setting(0, "threads per run (XLA, OpenMP); 0: this machine's cores / jobs (local), 1 (ray)", NONNEG)
    rerun: bool = setting(False, "run again the runs an earlier call finished (default: keep their rows)")

    def relations(self) -> list[str]:
        return ["address needs engine: ray"] if self.address and self.engine != "ray" else []


# ------------------------------------------------------------------------------------ load, derive

SECTIONS = {f.name: f.default_factory for f in dataclasses.fields(RunConfig)}


def as_dict(obj) -> dict:
    """A settings object (or RunConfig) as plain YAML-ready data (tuples as lists)."""
    conv = lambda v: list(v) if isinstance(v, tuple) else v
    if isinstance(obj, RunConfig):
        return {name: as_dict(getattr(obj, name)) for name in SECTIONS}
    return {f.name: conv(getattr(obj, f.name)) for f in dataclasses.fields(obj)}


def load_config(path=None, overrides: list[str] | None = None, calibration: dict | None = None) -> RunConfig:
    """Defaults, then the YAML file at ``path``, then ``calibration`` (the tracker values a
    sequence's camera.yaml records: response_gamma, depth_sigma), then ``section.key=value``
    overrides. An unknown section or key, a wrong type or a value out of range raises ConfigError;
    so does a ``${...}`` anywhere (values are taken as written: no interpolation, no resolvers)."""
    from omegaconf import OmegaConf
    from omegaconf.errors import OmegaConfBaseException

    layers = []  # (where it comes from, values)
    if path is not None:
        layers.append((str(path), _read_yaml(pathlib.Path(path))))
    if calibration:
        layers.append(("camera.yaml", {"tracker": {k: list(v) if isinstance(v, tuple) else v for k, v in calibration.items()}}))
    for item in overrides or []:
        key = item.split("=", 1)[0]
        if "=" not in item or "." not in key:
            raise ConfigError(f"override '{item}' must look like section.key=value (e.g. tracker.n=32)")
        _no_interpolation(f"--set {item}", item, key)
        layers.append((f"--set {item}", OmegaConf.from_dotlist([item])))
    merged = OmegaConf.structured(RunConfig)
    for where, layer in layers:
        try:
            _strict_bools(layer)
            merged = OmegaConf.merge(merged, layer)
        except ConfigError:
            raise
        except (OmegaConfBaseException, TypeError, ValueError, KeyError) as exc:
            raise ConfigError(f"{where}: {_omegaconf_message(exc)}") from None
    try:
        return OmegaConf.to_object(merged)
    except ConfigError:
        raise
    except (OmegaConfBaseException, TypeError, ValueError) as exc:
        raise ConfigError(_omegaconf_message(exc)) from None


def calibration_of(meta: dict) -> dict:
    """The tracker settings a sequence's camera.yaml records: the response gamma, the depth noise
    and the rolling-shutter readout (``readout_ms`` → ``readout_s``)."""
    out = {}
    if "response_gamma" in meta:
        out["response_gamma"] = float(meta["response_gamma"])
    if "readout_ms" in meta:
        out["readout_s"] = float(meta["readout_ms"]) / 1000.0
    if "depth_sigma" in meta:
        out["depth_sigma"] = tuple(float(x) for x in meta["depth_sigma"])
    return out


def _strict_bools(layer, prefix: str = "") -> None:
    """OmegaConf turns 3 into true: a bool setting must be written true or false."""
    for section, values in (layer or {}).items():
        cls = SECTIONS.get(section)
        if cls is None or not hasattr(values, "items"):
            continue
        hints = typing.get_type_hints(cls)
        for k, v in values.items():
            if hints.get(k) is bool and not isinstance(v, bool):
                raise ConfigError(f"{section}.{k}: expected true or false, got {v!r}")


def _no_interpolation(where: str, value, key: str = "") -> None:
    """Refuse (one line) a ``${...}`` in a user's key or value: OmegaConf would resolve it (e.g.
    ``${oc.env:HOME}``: an environment variable copied into the run's config.yaml)."""
    if isinstance(value, dict):
        for k, v in value.items():
            _no_interpolation(where, k, key)
            _no_interpolation(where, v, f"{key}.{k}" if key else str(k))
    elif isinstance(value, (list, tuple)):
        for v in value:
            _no_interpolation(where, v, key)
    elif isinstance(value, str) and "${" in value:
        raise ConfigError(f"{where}: {key or 'a key'}: '${{' is not allowed: settings are taken as written (no interpolation)")


def refuse_command_line_only(where: str, value) -> None:
    """Refuse (one line) a ``runtime.cache_dir`` other than the default ('') in a file (a ``--config``
    YAML, a sweep file): the compilation cache holds compiled programs that run when loaded, so only
    the user's own ``--set`` (or the default folder) may say where they come from."""
    if isinstance(value, dict):
        for k, v in value.items():
            if (str(k) == "cache_dir" or str(k).endswith(".cache_dir")) and v not in ("", None):
                raise ConfigError(f"{where}: runtime.cache_dir cannot be set in a file (compiled programs run when loaded): "
                                  "use --set runtime.cache_dir=... on the command line")
            refuse_command_line_only(where, v)
    elif isinstance(value, (list, tuple)):
        for v in value:
            if isinstance(v, str) and "cache_dir=" in v:
                refuse_command_line_only(where, dict([v.split("=", 1)]))
            refuse_command_line_only(where, v)


def _read_yaml(p: pathlib.Path) -> dict:
    import yaml

    from .io import read_text

    if not p.is_file():
        raise ConfigError(f"{p}: config file not found")
    try:
        data = yaml.safe_load(read_text(p, "config file")) or {}
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict) or not all(isinstance(v, (dict, type(None))) for v in data.values()):
        raise ConfigError(f"{p}: expected sections {', '.join(f'{s}:' for s in SECTIONS)} holding key: value lines")
    _no_interpolation(str(p), data)
    refuse_command_line_only(str(p), data)
    return {k: v or {} for k, v in data.items()}


def _omegaconf_message(exc) -> str:
    """OmegaConf's error as one line naming the full key."""
    key = getattr(exc, "full_key", None)
    first = str(exc).splitlines()[0] if str(exc).strip() else type(exc).__name__
    if type(exc).__name__ == "ConfigKeyError":
        return f"unknown setting {key!r} (sections: {', '.join(SECTIONS)}; see configs/default.yaml)"
    if isinstance(exc.__cause__, ConfigError):  # raised by a dataclass check inside to_object
        return str(exc.__cause__)
    if "is not a TupleConfig" in first:
        return f"{key}: expected a list, one value per pyramid level (e.g. [8, 10, 12, 20]), got {first.split()[3]}"
    return f"{key}: {first}" if key else first


def _yaml_value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, float) and math.isinf(v):
        return ".inf" if v > 0 else "-.inf"
    if isinstance(v, tuple):
        return "[" + ", ".join(_yaml_value(x) for x in v) + "]"
    if v == "":
        return "''"  # YAML reads an empty value as null
    return repr(v) if isinstance(v, float) else str(v)


def default_yaml() -> str:
    """``configs/default.yaml``: every key of every section with its default and its help line."""
    lines = ["# mbavo track defaults: every setting, generated from mbavo_jax/config.py (`mbavo config`).",
             "# Why the defaults are what they are: docs/settings.md."]
    for name, cls in SECTIONS.items():
        lines.append(f"{name}:")
        for f in dataclasses.fields(cls):
            entry = f"  {f.name}: {_yaml_value(f.default)}"
            lines.append(f"{entry:<40} # {f.metadata['help']}")
    return "\n".join(lines) + "\n"


def settings_markdown() -> str:
    """The settings reference table of docs/settings.md (one table per section)."""
    out = []
    tables = {**{f"{k}` (config section)": v for k, v in SECTIONS.items()},
              "mbavo synth` flags": SynthConfig, "mbavo bench` flags": BenchConfig,
              "mbavo sweep` and `mbavo bench odometry` flags": SweepConfig}
    for name, cls in tables.items():
        doc = (cls.__doc__ or "").strip().replace("\n    ", " ").replace("``", "`")
        out += [f"### `{name}", "", doc, "",
                "| key | default | valid | what it does |", "|---|---|---|---|"]
        for f in dataclasses.fields(cls):
            check, choices = f.metadata.get("check"), f.metadata.get("choices")
            valid = " \\| ".join(choices) if choices else (check.text if check else "")
            out.append(f"| `{f.name}` | `{_yaml_value(f.default)}` | {valid} | {f.metadata['help'].replace('|', '/')} |")
        out.append("")
    return "\n".join(out)


# ----------------------------------------------------------------------------------------- argparse


def add_arguments(parser, cls, skip: tuple = ()) -> None:
    """One ``--field-name`` flag per field of ``cls`` (help and choices from the field; bools as
    on/off switches); defaults are None so that only given flags override (``from_arguments``)."""
    import argparse

    hints = typing.get_type_hints(cls)
    for f in dataclasses.fields(cls):
        if f.name in skip:
            continue
        flag = "--" + f.name.replace("_", "-")
        shown = f" (default {_yaml_value(f.default)})" if f.default not in ("", None) else ""
        hint, help_ = hints[f.name], f"{f.metadata['help']}{shown}".replace("%", "%%")
        if hint is bool:
            parser.add_argument(flag, dest=f.name, action=argparse.BooleanOptionalAction, default=None, help=help_)
        elif typing.get_origin(hint) is tuple:
            elem = [a for a in typing.get_args(hint) if a is not Ellipsis][0]
            parser.add_argument(flag, dest=f.name, type=elem, nargs="+", default=None, help=help_)
        else:
            parser.add_argument(flag, dest=f.name, type=hint, default=None, help=help_,
                                choices=f.metadata.get("choices") or None)


def from_arguments(cls, args, base: dict | None = None):
    """An instance of ``cls`` from ``base`` (e.g. a preset) and the flags given in ``args``."""
    values = dict(base or {})
    for f in dataclasses.fields(cls):
        v = getattr(args, f.name, None)
        if v is not None:
            values[f.name] = tuple(v) if isinstance(v, list) else v
    return cls(**values)
