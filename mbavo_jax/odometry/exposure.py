"""The exposure time of a sequence whose files do not record it, estimated online.

Against a keyframe deblurred along an exposure of length g, a frame moving like the keyframe is
matched equally well by blur of length g whatever the true exposure: the start/end split alone
does not observe the exposure time. Two raw frames moving at different speeds do. A raw frame
blurred over e·s_a pixels (speed s_a px/s, exposure e s), reblurred by ℓ pixels, best matches a
raw frame blurred over e·s_b when ℓ = h(s_a/s_b)·e·s_b, where h is the least-squares fit of a box
on a box (:func:`reblur_fraction`), so tracking the faster frame against the slower one, as it was
recorded, gives one sample e = ℓ / (h·s_b). The estimate is the weighted median of the recent
samples (weight: h·s_b over one frame interval, in px), reported as a fraction of the frame
interval. With a rolling shutter (readout ``tracker.readout_s``) the tracked path spans readout
plus exposure; ℓ is then the blur of its middle row's own exposure
(``ExposureTrajectory.middle_row_path`` at ρ = R/(R+guess)), the readout's part left out.
``exposure_mode`` decides whether a sequence's exposure is known, estimated or taken as zero
(``odometry.exposure``).
"""

from __future__ import annotations

import dataclasses
import functools

import numpy as np

from ..config import OdometryConfig, TrackerConfig
from ..errors import MbavoError
from ..geometry import ExposureTrajectory, PinholeCamera, Pose, readout_fraction
from ..tracking import Keyframe, exposure_from_velocity, track
from .stats import keyframe_stats

__all__ = ["ExposureEstimate", "RawFrame", "adaptive_n", "blind", "exposure_mode", "prior_off", "pair_tracker", "pick_pair", "pair_sample",
           "point_speed", "reblur_fraction", "with_keyframe", "with_next"]


@functools.lru_cache(maxsize=16)
def prior_off(config: TrackerConfig) -> TrackerConfig:
    """``config`` without the exposure-motion prior (one object per config: the tracker's caches hit)."""
    return dataclasses.replace(config, blur_prior=0.0)


@functools.lru_cache(maxsize=16)
def pair_tracker(config: TrackerConfig, levels: int) -> TrackerConfig:
    """``config`` as a pair's frames are tracked against each other: without the exposure-motion
    prior, on at most ``levels`` finest pyramid levels, the Jacobian recomputed at every step (the
    blur length it measures starts from a guess, where a frozen one would be taken); one object per config."""
    return dataclasses.replace(prior_off(config), levels=min(levels, config.levels), fresh_jacobian_levels=config.levels)


@functools.lru_cache(maxsize=16)
def blind(config: TrackerConfig) -> TrackerConfig:
    """``config`` blind to blur (one virtual frame, start = end), one object per config."""
    return dataclasses.replace(config, blur_aware=False)


@functools.lru_cache(maxsize=16)
def adaptive_n(config: TrackerConfig) -> TrackerConfig:
    """``config`` with n chosen from each frame's predicted blur (``n_mode`` adaptive), one object per config."""
    return dataclasses.replace(config, n_mode="adaptive")


def exposure_mode(odo: OdometryConfig, recorded: bool) -> str:
    """``known``, ``estimate`` or ``none`` for a sequence that ``recorded`` exposure times or not:
    ``auto`` is known when the data (or ``exposure_s``) gives them and estimated otherwise."""
    given = recorded or odo.exposure_s > 0
    if odo.exposure == "known" and not given:
        raise MbavoError("odometry.exposure=known, but the sequence records no exposure times and odometry.exposure_s is 0 "
                         "(use exposure=auto to estimate them, or set odometry.exposure_s)")
    if odo.exposure == "auto":
        return "known" if given else "estimate"
    return odo.exposure


@dataclasses.dataclass(frozen=True)
class RawFrame:
    """A tracked frame as it was recorded, kept for pairing: its image and depth, its mid-exposure
    pose and the previous tracked frame's (camera-to-world), ``dt`` seconds apart, and its point
    speed (px/s, measured on the keyframe it was tracked against)."""

    stamp: float
    image: np.ndarray
    depth: np.ndarray | None
    T_world_mid: Pose
    T_world_prev: Pose
    dt: float
    speed: float
    keyframe: Keyframe | None = None  # the frame as a keyframe, made when it is first paired (``with_keyframe``)
    T_world_next: Pose | None = None  # the next tracked frame's mid pose, ``dt_next`` s later (``with_next``)
    dt_next: float = 0.0

    def velocity(self) -> tuple[Pose, Pose, float]:
        """(from, to, seconds) of the motion about this frame's exposure: previous to next mid pose
        (a central difference) once the next is known, else previous to this one."""
        if self.T_world_next is None:
            return self.T_world_prev, self.T_world_mid, self.dt
        return self.T_world_prev, self.T_world_next, self.dt + self.dt_next


def with_next(frame: RawFrame, T_world_next: Pose, dt_next: float, speed: float) -> RawFrame:
    """``frame`` once the next frame is tracked: its speed (px/s) about its own exposure, ``speed``."""
    return dataclasses.replace(frame, T_world_next=T_world_next, dt_next=dt_next, speed=speed)


def with_keyframe(frame: RawFrame, camera: PinholeCamera, tracker: TrackerConfig) -> RawFrame:
    """``frame`` with its image and depth as a keyframe, made once."""
    if frame.keyframe is not None:
        return frame
    return dataclasses.replace(frame, keyframe=Keyframe.create(frame.image, frame.depth, camera, tracker))


def pick_pair(recent: tuple[RawFrame, ...], current: RawFrame, ratio: float) -> tuple[RawFrame, RawFrame] | None:
    """(slower, faster) of ``current`` and the recent frame whose speeds differ most, when the
    faster moves at least ``ratio`` times as fast; else None."""
    best, best_ratio = None, ratio
    for other in recent:
        slow, fast = (other, current) if other.speed < current.speed else (current, other)
        r = fast.speed / max(slow.speed, 1e-9)
        if r >= best_ratio:
            best, best_ratio = (slow, fast), r
    return best


def point_speed(kf: Keyframe, T_ref_world: Pose, frame: RawFrame) -> float:
    """The mean speed (px/s) of the keyframe's points over ``frame``'s motion (:meth:`RawFrame.velocity`;
    ``T_ref_world``: world to the keyframe)."""
    a, b, seconds = frame.velocity()
    to = T_ref_world.compose(b)
    return keyframe_stats(kf, ExposureTrajectory(to, to), T_ref_world.compose(a)).motion_px / seconds


def _extra_blur(ref: RawFrame, kf: Keyframe, other: RawFrame, tracker: TrackerConfig, guess_s: float) -> float | None:
    """The blur length (px, on ``kf``'s points) that the raw frame ``ref`` needs to match the raw
    frame ``other``: ``other`` tracked against it (``tracker``: :func:`pair_tracker`), from ``guess_s``
    exposure (plus the readout) at ``other``'s velocity; the middle row's blur; None when the tracking fails."""
    T_ref = ref.T_world_mid.inverse()
    mid = T_ref.compose(other.T_world_mid)
    rho = readout_fraction(tracker.readout_s, guess_s)
    a, b, seconds = other.velocity()
    path = exposure_from_velocity(a.inverse().compose(b), seconds, guess_s + tracker.readout_s)
    res = track(kf, other.image, ExposureTrajectory(mid.compose(path.start), mid.compose(path.end)),
                tracker, depth=other.depth, readout=rho)
    return keyframe_stats(kf, res.trajectory.middle_row_path(rho)).blur_px if res.status.ok else None


def reblur_fraction(rho: float, spectrum: float = 1.0) -> float:
    """h(ρ): the length, as a fraction of b, of the box blur that turns a box blur of ρ·b into the
    closest match of a box blur of b, in least squares over an image whose power falls as
    1/f^``spectrum`` (f up to 12 cycles per b: b = 24 px). h(0) = 1, h(1) = 0; a box on a box is a
    trapezoid, so h exceeds the √(1 − ρ²) of added variances (0.85 against 0.74 at ρ = 0.67)."""
    f = np.linspace(1e-3, 12.0, 600)
    ell = np.linspace(0.0, 1.0, 201)  # a 4x finer grid in both moves h by under 1e-5
    err = (f ** -spectrum * (np.sinc(rho * f) * np.sinc(np.outer(ell, f)) - np.sinc(f)) ** 2).sum(axis=1)
    k = int(np.clip(np.argmin(err), 1, len(ell) - 2))
    a, b, c = err[k - 1:k + 2]
    bend = a - 2 * b + c  # the parabola through the three nearest grid points, for a sub-grid minimum
    return float(np.clip(ell[k] + (0.5 * (a - c) / bend if bend > 0 else 0.0) * (ell[1] - ell[0]), 0.0, 1.0))


def pair_sample(slow: RawFrame, fast: RawFrame, camera: PinholeCamera, tracker: TrackerConfig, guess_s: float,
                ratio: float, levels: int | None = None) -> tuple[float, float] | None:
    """(exposure s, weight px) of a pair of raw frames: e = ℓ / (h(s_slow/s_fast)·s_fast), with ℓ
    the extra blur the slow frame needs to match the fast one (:func:`reblur_fraction`). None when
    the speeds, measured on the slow frame's points, differ by less than ``ratio`` or the tracking
    fails. The track uses :func:`pair_tracker` (``levels``: finest levels, None: all). The slow
    frame's keyframe is made here unless it carries one (``with_keyframe``)."""
    slow = with_keyframe(slow, camera, tracker)
    tracker = pair_tracker(tracker, levels or tracker.levels)
    kf = slow.keyframe
    s_slow, s_fast = point_speed(kf, slow.T_world_mid.inverse(), slow), point_speed(kf, slow.T_world_mid.inverse(), fast)
    if not (np.isfinite(s_slow) and np.isfinite(s_fast)) or s_fast < ratio * max(s_slow, 1e-9):
        return None
    extra = _extra_blur(slow, kf, fast, tracker, guess_s)
    if extra is None:
        return None
    rate = s_fast * reblur_fraction(s_slow / s_fast)  # px of extra blur per second of exposure
    return float(min(extra / rate, fast.dt)), rate * fast.dt


def _weighted_median(values: np.ndarray, weights: np.ndarray) -> float:
    """The weighted median, interpolated between the samples' weight midpoints (two samples of
    equal weight: their mean)."""
    order = np.argsort(values)
    v, w = values[order], weights[order]
    return float(np.interp(0.5 * w.sum(), np.cumsum(w) - 0.5 * w, v))


@dataclasses.dataclass(frozen=True)
class ExposureEstimate:
    """The recent samples (exposure seconds, weight, frame interval seconds), newest last, at most
    ``window``; ``guess``: the fraction of the frame interval assumed before the first sample."""

    guess: float
    window: int
    samples: tuple[tuple[float, float, float], ...] = ()

    def add(self, sample: tuple[float, float] | None, dt: float) -> "ExposureEstimate":
        if sample is None:
            return self
        return dataclasses.replace(self, samples=(*self.samples, (*sample, dt))[-self.window:])

    @property
    def count(self) -> int:
        return len(self.samples)

    def settled(self, count: int, tolerance: float) -> bool:
        """Whether the estimate (as a fraction of the frame interval) moved by at most ``tolerance``
        over its last ``count`` samples (computed once per estimate: a frame asks several times)."""
        return _settled(self, count, tolerance)

    def seconds(self, frame_dt: float) -> float:
        """The exposure time: the samples' weighted median, or ``guess`` · ``frame_dt`` before any."""
        if not self.samples:
            return self.guess * frame_dt
        s = np.asarray(self.samples)
        return _weighted_median(s[:, 0], s[:, 1])

    def fraction(self) -> float:
        """The exposure time over the median frame interval of the samples (``guess`` before any)."""
        if not self.samples:
            return self.guess
        return self.seconds(0.0) / float(np.median(np.asarray(self.samples)[:, 2]))


@functools.lru_cache(maxsize=64)
def _settled(est: ExposureEstimate, count: int, tolerance: float) -> bool:
    if est.count < count:
        return False
    seen = [dataclasses.replace(est, samples=est.samples[:k]).fraction() for k in range(est.count - count + 1, est.count + 1)]
    return max(seen) - min(seen) <= tolerance
