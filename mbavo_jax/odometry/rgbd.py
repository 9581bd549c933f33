"""The RGB-D pipeline's per-frame step: predict, track, deblur, decide keyframes, recover.

For each frame: predict its exposure path by constant velocity, track it against the current sharp
keyframe (``tracking.track``), and decide whether it becomes the next keyframe (mean point flow and
blur length, or too few visible points). A blurry frame that becomes a keyframe is deblurred with
its estimated exposure path first; a keyframe made without a path (the first frame, a reset after
drops) is deblurred once the first frame tracked against it gives the camera's velocity. A frame
whose tracking fails, or whose fit is implausible next to the frames before it (residual far above
theirs, pose far from the prediction), is dropped; after ``reset_after_drops`` drops in a row the current frame
becomes a keyframe at the last good pose. No file I/O happens here.
"""

from __future__ import annotations

import dataclasses
import functools
import time

import numpy as np

from ..config import OdometryConfig, RunConfig, TrackerConfig
from ..deblur import choose_deblur_n, deblur, exposure_blur_px
from ..geometry import ExposurePath, ExposureTrajectory, PinholeCamera, Pose, readout_fraction
from ..image import quantize16
from ..progress import bar
from ..tracking import Keyframe, Status, TrackResult, constant_velocity_guess, exposure_from_velocity, predicted_blur_px, track
from .exposure import (ExposureEstimate, RawFrame, adaptive_n, blind, exposure_mode, pair_sample, pick_pair, point_speed,
                       prior_off, with_keyframe, with_next)
from .stats import PointStats, keyframe_stats
from .state import ExposureReport, Fit, FrameOutcome, KeyframeState, NewKeyframe, Pairing, PendingDeblur, RunState, Triptych

__all__ = ["RGBDPipeline", "PointStats", "needs_keyframe", "keyframe_stats", "implausible", "residual_too_large", "far_from_prediction"]


SETTLED_SAMPLES = 6  # the estimate's last samples that ``odometry.exposure_settled`` compares


def needs_keyframe(stats: PointStats, width: int, odo: OdometryConfig) -> bool:
    """Mean point flow beyond ``keyframe_flow`` of the width on a frame blurred at most
    ``keyframe_max_blur_px``, or beyond ``keyframe_flow_max`` whatever its blur, or fewer than
    ``keyframe_min_visible`` of the keyframe's points in view."""
    flow = stats.flow_px
    return bool(stats.visible < odo.keyframe_min_visible or flow > odo.keyframe_flow_max * width
                or (flow > odo.keyframe_flow * width and stats.blur_px <= odo.keyframe_max_blur_px))


@functools.lru_cache(maxsize=16)
def local(config: TrackerConfig) -> TrackerConfig:
    """``config`` without the motion hypotheses: local descent from the guess alone (one object per
    config, so the tracker's caches hit)."""
    return dataclasses.replace(config, hypotheses=False)


def residual_too_large(fit: Fit, recent: tuple[Fit, ...], odo: OdometryConfig) -> str | None:
    """Why the fit's RMS is beyond ``reject_rms_ratio`` times the largest of the ``recent`` fits' (None: it is not)."""
    rms = max((h.rms for h in recent), default=float("inf"))
    if odo.reject_rms_ratio > 0 and fit.rms > odo.reject_rms_ratio * rms:
        return f"residual RMS {fit.rms / max(rms, 1e-12):.1f}x the largest of the last {len(recent)} frames"
    return None


def far_from_prediction(fit: Fit, recent: tuple[Fit, ...], odo: OdometryConfig, steps: float = 1.0) -> str | None:
    """Why the fit's pose lies beyond ``reject_jump_ratio`` times the ``recent`` fits' median distance
    from their prediction plus ``reject_jump_px``, per frame interval predicted over (None: it does not)."""
    jumps = [h.jump_px for h in recent if h.jump_px is not None]
    if odo.reject_jump_ratio > 0 and fit.jump_px is not None and len(jumps) >= 3:
        limit = (odo.reject_jump_ratio * float(np.median(jumps)) + odo.reject_jump_px) * max(steps, 1.0)
        if fit.jump_px > limit:
            return f"pose {fit.jump_px:.1f} px from the prediction (limit {limit:.1f} px)"
    return None


def implausible(fit: Fit, history: tuple[Fit, ...], odo: OdometryConfig, steps: float = 1.0) -> str | None:
    """Why a usable fit disagrees with the last ``reject_window`` accepted ones (None: it does not):
    :func:`residual_too_large` or :func:`far_from_prediction`. Needs 3 of them."""
    recent = history[-odo.reject_window:]
    if len(recent) < 3:
        return None
    return residual_too_large(fit, recent, odo) or far_from_prediction(fit, recent, odo, steps)


@dataclasses.dataclass(frozen=True)
class RGBDPipeline:
    """Blur-aware RGB-D odometry: images tracked against deblurred keyframes with sensor depth."""

    camera: PinholeCamera
    config: RunConfig = RunConfig()
    probe: bool = False  # an exposure probe's run (``start_state``): new keyframes are not deblurred

    def step(self, state: RunState, frame, index: int) -> tuple[RunState, FrameOutcome]:
        t0 = time.perf_counter()
        if state.keyframe is None:
            state, outcome = self._first(state, frame, index)
        else:
            state, outcome = self._track(state, frame, index)
        return state, dataclasses.replace(outcome, seconds=time.perf_counter() - t0)

    # ------------------------------------------------------------------------------ the pieces

    def make_keyframe(self, state: RunState, image, depth, T_world_kf: Pose) -> Keyframe:
        """The keyframe frames are tracked against, from its (sharp) image and its depth map."""
        return Keyframe.create(image, depth, self.camera, self.config.tracker)

    def exposure_mode(self, frame) -> str:
        """How this frame's exposure time is had: ``known``, ``estimate`` or ``none`` (also for a
        tracker that is not blur-aware: it has no use for one)."""
        mode = exposure_mode(self.config.odometry, frame.exposure is not None)
        return mode if self.config.tracker.blur_aware or mode != "estimate" else "none"

    def estimate(self, state: RunState) -> ExposureEstimate:
        """The running exposure estimate (a fresh one before the first sample)."""
        odo = self.config.odometry
        return state.exposure or ExposureEstimate(odo.exposure_guess, odo.exposure_window)

    def start_state(self, seq, progress: bool = False) -> RunState:
        """The loop's first state. With an estimated exposure, the first :meth:`probe_frames` frames
        (fewer once :meth:`probe_done`) are run once beforehand (nothing written; tracked blind to
        blur, one pose a frame, no keyframe deblurred: their pairs need only their poses and speeds)
        and the run starts from the pairs' samples instead of the uninformative guess: its first
        keyframes are then deblurred along an estimated exposure, and those frames are not paired
        again. Deterministic, so ``--resume`` repeats it."""
        k = min(self.probe_frames(), len(seq))
        if k < 2 or self.exposure_mode(seq[0]) != "estimate":
            return RunState()
        probe, state = dataclasses.replace(self, probe=True), RunState()
        with bar(k, "exposure probe", progress) as pbar:
            for index in range(k):
                state, _ = probe.step(state, seq[index], index)
                pbar.update()
                if self.probe_done(state):
                    k = index + 1
                    break
        est = self.estimate(state)
        return RunState(exposure=est, probed_until=seq[k - 1].timestamp) if est.count else RunState()

    def probe_frames(self) -> int:
        """The most frames the exposure probe runs (``odometry.exposure_probe``)."""
        return self.config.odometry.exposure_probe

    def probe_done(self, state: RunState) -> bool:
        """Whether the exposure probe may stop before ``probe_frames``: its estimate has settled
        (``odometry.exposure_settled``). A path whose speed changes slowly gives its first sample late,
        and a run started from the guess instead tracks and deblurs those frames along a wrong exposure."""
        return self.estimate(state).settled(SETTLED_SAMPLES, self.config.odometry.exposure_settled)

    def exposure_of(self, state: RunState, frame, frame_dt: float) -> float:
        """The frame's exposure time (s): recorded in the data (else ``odometry.exposure_s``) when
        known, the running estimate (``frame_dt``: the frame interval) when estimated, else 0."""
        mode = self.exposure_mode(frame)
        if mode == "known":
            return frame.exposure if frame.exposure is not None else self.config.odometry.exposure_s
        return self.estimate(state).seconds(frame_dt) if mode == "estimate" else 0.0

    def frame_interval(self, state: RunState, frame) -> float:
        """The frame interval (s): between the last two tracked frames, else since the last one."""
        if len(state.mids) >= 2:
            return max(state.mids[-1][0] - state.mids[-2][0], 1e-6)
        return max(frame.timestamp - state.mids[-1][0], 1e-6) if state.mids else 0.0

    def readout_of(self, exposure_s: float) -> float:
        """The readout fraction ρ = R/(R+τ) of a frame exposed ``exposure_s`` (R: ``tracker.readout_s``)."""
        return readout_fraction(self.config.tracker.readout_s, exposure_s)

    def frame_readout(self, state: RunState, frame) -> float:
        """This frame's readout fraction ρ, from its exposure time (known or estimated)."""
        return self.readout_of(self.exposure_of(state, frame, self.frame_interval(state, frame)))

    def pending_of(self, frame) -> PendingDeblur | None:
        """What deblurring a keyframe made from ``frame`` without an exposure path needs, or None
        when it will not be deblurred."""
        cfg = self.config
        exposure = None if self.exposure_mode(frame) == "estimate" else self.exposure_of(RunState(), frame, 0.0)
        wait = (cfg.odometry.deblur_first_keyframe and cfg.tracker.blur_aware and not self.probe and frame.depth is not None
                and exposure != 0.0)
        return PendingDeblur(frame.image, frame.depth, exposure) if wait else None

    def tracker_config(self, frame, informed: bool, state: RunState | None = None) -> TrackerConfig:
        """The tracker's settings for this frame: as configured, but with an estimated exposure the
        exposure-motion prior is off while the guess carries no velocity (``informed`` false), so
        that nothing pins a frame sharp for want of knowledge; and a frame predicted by a velocity
        whose exposure (in ``state``) is short, known or estimated, is tracked with adaptive n,
        which its small predicted blur keeps small."""
        tracker = self.config.tracker
        if self.probe:
            return blind(tracker)
        if not informed:
            return tracker if self.exposure_mode(frame) != "estimate" else prior_off(tracker)
        if tracker.blur_aware and state is not None and state.mids and self.short_exposure(state, frame):
            return adaptive_n(tracker)
        return tracker

    def frame_tracker(self, state: RunState, frame, init: ExposureTrajectory, informed: bool,
                      readout: float) -> tuple[TrackerConfig, float | None]:
        """The tracker's settings for this frame (:meth:`tracker_config`), and the blur (px) its guess
        ``init`` predicts on the keyframe's points when the rule below read it (``track``'s
        ``blur_px``, so it is computed once; else None). A global-shutter frame is tracked as sharp
        (one pose, start = end) when no velocity ``informed`` its guess (a path of zero length is a
        stationary point of the blur model to first order: from it, start and end barely separate,
        whatever n). A frame predicted under ``odometry.adaptive_below_px`` (0 = never) is tracked
        with adaptive n (few virtual frames for a little blur), and, with adaptive n, as sharp under
        ``sharp_blur_px``."""
        tracker, odo = self.tracker_config(frame, informed, state), self.config.odometry
        if not tracker.blur_aware or readout > 0 or tracker.trajectory != "linear":
            return tracker, None
        if not informed:
            return blind(tracker), None
        if tracker.n_mode != "adaptive" and odo.adaptive_below_px <= 0:
            return tracker, None
        blur = predicted_blur_px(state.keyframe.keyframe, init)
        if tracker.n_mode != "adaptive" and blur >= odo.adaptive_below_px:
            return tracker, blur
        return (blind(tracker) if blur < odo.sharp_blur_px else adaptive_n(tracker)), blur

    def short_exposure(self, state: RunState, frame) -> bool:
        """Whether the frame's exposure is at most ``odometry.short_exposure`` of the frame interval,
        known or estimated (the exposure probe's samples give an estimate from the first frame)."""
        odo, dt = self.config.odometry, self.frame_interval(state, frame)
        return dt > 0 and self.exposure_of(state, frame, dt) <= odo.short_exposure * dt

    def keyframe_without_path(self, state: RunState, frame, T_world_kf: Pose) -> tuple[RunState, NewKeyframe]:
        """A keyframe at ``T_world_kf`` from a frame whose exposure path is not known yet: used as it
        is, and deblurred once the next frame tracked against it gives the velocity."""
        image = quantize16(frame.image)
        kf = KeyframeState(self.make_keyframe(state, image, frame.depth, T_world_kf), T_world_kf, frame.timestamp)
        state = state.replace(keyframe=kf, pending=self.pending_of(frame), keyframes=state.keyframes + 1)
        return state, NewKeyframe(frame.timestamp, T_world_kf, image)

    def _first(self, state: RunState, frame, index: int) -> tuple[RunState, FrameOutcome]:
        """The first frame: the world frame, taken as sharp until its blur is known."""
        T_w = Pose.identity()
        state, new = self.keyframe_without_path(state, frame, T_w)
        state = state.replace(mids=((frame.timestamp, T_w),), tracked=state.tracked + 1)
        report = self.exposure_report(state, frame, 0.0)
        return state, FrameOutcome(index, frame.timestamp, "keyframe", T_w, T_w, T_w, new_keyframe=new, exposure=report)

    def predict(self, state: RunState, frame, gap: float | None = None) -> tuple[ExposureTrajectory, bool]:
        """The frame's exposure path in the keyframe, by constant velocity from the last two mid
        poses (over the whole frame time: exposure plus readout) ``gap`` seconds on from the last
        (default: up to the frame's time), or the last pose (no motion) when the velocity is not
        known; and whether it was known."""
        T_w_kf = state.keyframe.T_world_kf
        if len(state.mids) >= 2:
            (ta, Ta), (tb, Tb) = state.mids[-2], state.mids[-1]
            dt = max(tb - ta, 1e-6)
            span = self.exposure_of(state, frame, dt) + self.config.tracker.readout_s
            return constant_velocity_guess(T_w_kf, Ta, Tb, dt, span, frame.timestamp - tb if gap is None else gap), True
        last = T_w_kf.inverse().compose(state.mids[-1][1])
        return ExposureTrajectory(last, last), False

    def _track(self, state: RunState, frame, index: int) -> tuple[RunState, FrameOutcome]:
        replaced, t0, result, fit, stats, informed = (), time.perf_counter(), None, None, None, False
        if frame.depth is None or np.isfinite(frame.depth).any():  # else nothing to place the frame with
            init, informed = self.predict(state, frame)
            rho = self.frame_readout(state, frame)
            tracker, blur = self.frame_tracker(state, frame, init, informed, rho)
            first = track(state.keyframe.keyframe, frame.image, init, tracker, depth=frame.depth, readout=rho, blur_px=blur)
            stats = self.frame_stats(state, first, init.middle() if informed else None) if first.status.ok else None
            result, fit = self.checked(state, frame, first, stats, informed)
            if state.pending is not None and result.status.ok:
                state, result, replaced = self.deblur_pending(state, frame, result, rho)
                informed = informed or result is not first  # tracked again from a velocity
                fit = dataclasses.replace(fit, rms=float(result.diagnostics["rms"]))
                stats = self.frame_stats(state, result, None) if replaced else stats  # the keyframe was replaced
        track_seconds = time.perf_counter() - t0
        if result is not None and result.status.ok:
            state, outcome = self._tracked(state, frame, index, result, informed, fit, stats)
        else:
            state, outcome = self._dropped(state, frame, index, result)
        return state, dataclasses.replace(outcome, replaced_images=replaced, track_seconds=track_seconds, fit=fit)

    def frame_stats(self, state: RunState, result: TrackResult, predicted: Pose | None) -> PointStats:
        """:class:`PointStats` of a tracking result on the current keyframe: the motion since the last
        tracked frame and the distance from the ``predicted`` T_kf_mid (None: no prediction); its
        blur is the middle row's (the readout's part of the path left out)."""
        kf = state.keyframe
        path = result.trajectory.middle_row_path(result.diagnostics.get("readout", 0.0))
        return self.point_stats(kf.keyframe, path, kf.T_world_kf.inverse().compose(state.mids[-1][1]), predicted)

    def point_stats(self, keyframe: Keyframe, path: ExposurePath, prev: Pose, predicted: Pose | None) -> PointStats:
        """The statistics :meth:`frame_stats` computes (``keyframe_stats``; poses relative to the keyframe)."""
        return keyframe_stats(keyframe, path, prev, predicted)

    def wants_keyframe(self, stats: PointStats) -> bool:
        """Whether a tracked frame with these :meth:`frame_stats` becomes the next keyframe (``needs_keyframe``)."""
        return needs_keyframe(stats, self.camera.width, self.config.odometry)

    def checked(self, state: RunState, frame, result: TrackResult, stats: PointStats | None,
                informed: bool) -> tuple[TrackResult, Fit | None]:
        """A usable result's fit (its distance from the prediction only when ``informed`` by a
        velocity), and the result marked IMPLAUSIBLE, with the reason in its diagnostics, when it
        disagrees with the frames before it (``implausible``), unless only its distance from the
        prediction does and a second start confirms it (:meth:`confirmed`)."""
        if not result.status.ok:
            return result, None
        fit, steps = Fit(float(result.diagnostics["rms"]), stats.jump_px if informed else None), 1.0
        if len(state.mids) >= 2:  # frame intervals predicted over (more after an implausible frame)
            steps = (frame.timestamp - state.mids[-1][0]) / max(state.mids[-1][0] - state.mids[-2][0], 1e-6)
        odo = self.config.odometry
        reason = implausible(fit, state.fits, odo, steps)
        if reason is not None and odo.confirm_jumps and not residual_too_large(fit, state.fits[-odo.reject_window:], odo):
            apart = self.confirmed(state, frame, result)
            if apart is not None:
                note = f"{reason}; kept: a second start's fit is {apart:.1f} px from it"
                return dataclasses.replace(result, diagnostics={**result.diagnostics, "confirmed": note}), fit
            reason = f"{reason}; a second start did not confirm it"
        if reason is not None:
            result = dataclasses.replace(result, status=Status.IMPLAUSIBLE, diagnostics={**result.diagnostics, "implausible": reason})
        return result, fit

    def confirmed(self, state: RunState, frame, result: TrackResult) -> float | None:
        """The distance (mean px over the keyframe's points) between ``result``'s mid-exposure pose and
        the frame's fit from a second start, the last tracked frame's mid pose, by local descent
        alone (:func:`local`), when the two starts lie at least and the two fits at most
        ``odometry.reject_jump_px`` apart (None: otherwise, or the second track failed)."""
        odo, kf, rho = self.config.odometry, state.keyframe.keyframe, result.diagnostics.get("readout", 0.0)
        first, _ = self.predict(state, frame)
        init, _ = self.predict(state, frame, gap=0.0)
        if self.point_stats(kf, init, init.middle(), first.middle()).jump_px < odo.reject_jump_px:
            return None  # the second start would retrace the first
        tracker, blur = self.frame_tracker(state, frame, init, True, rho)
        second = track(kf, frame.image, init, local(tracker), depth=frame.depth, readout=rho, blur_px=blur)
        if not second.status.ok:
            return None
        apart = self.frame_stats(state, second, result.trajectory.middle_row_path(rho).middle()).jump_px
        return apart if apart <= odo.reject_jump_px else None

    def deblurred(self, image, depth, path: ExposurePath, readout: float = 0.0) -> tuple[np.ndarray, int]:
        """(sharp image as stored, virtual frames used): ``image`` deconvolved along its exposure
        ``path`` (readout fraction ``readout``: the path spans the whole frame time)."""
        n = choose_deblur_n(depth, self.camera, path, self.config.deblur, readout)
        cfg = dataclasses.replace(self.config.deblur, n=n)
        return quantize16(deblur(image, depth, self.camera, path, cfg, self.config.tracker.response_gamma, readout)), n

    def velocity_path(self, T_ref_cur: Pose, dt: float, exposure: float) -> tuple[ExposureTrajectory, float]:
        """(exposure path about its middle, readout fraction) of a frame exposed ``exposure`` s when the
        camera moves by ``T_ref_cur`` every ``dt`` s: the path spans exposure plus readout."""
        span = exposure + self.config.tracker.readout_s
        return exposure_from_velocity(T_ref_cur, max(dt, 1e-6), span), self.readout_of(exposure)

    def deblur_pending(self, state: RunState, frame, result: TrackResult, readout: float = 0.0):
        """The waiting keyframe deblurred along the constant-velocity path that this frame's motion
        gives, and this frame (readout fraction ``readout``) tracked again against it from the same
        velocity. Returns (state, result, replaced images). A keyframe blurred less than
        ``deblur_min_blur_px`` stays as it is; when the second tracking fails, the first result is
        kept (with the deblurred keyframe)."""
        kf, pending = state.keyframe, state.pending
        exposure = pending.exposure if pending.exposure is not None else self.estimate(state).seconds(frame.timestamp - kf.stamp)
        state = state.replace(pending=None)
        mid = result.trajectory.middle()  # T_kf_mid of this frame: the motion over frame.timestamp - stamp
        path, rho = self.velocity_path(mid, frame.timestamp - kf.stamp, exposure)
        if exposure_blur_px(pending.depth, self.camera, path, readout=rho)[0] <= self.config.odometry.deblur_min_blur_px:
            return state, result, ()
        sharp, _ = self.deblurred(pending.image, pending.depth, path, rho)
        keyframe = self.make_keyframe(state, sharp, pending.depth, kf.T_world_kf)
        state = state.replace(keyframe=dataclasses.replace(kf, keyframe=keyframe))
        init = ExposureTrajectory(mid.compose(path.start), mid.compose(path.end))  # same velocity: T_kf_mid ∘ path
        again = track(keyframe, frame.image, init, self.tracker_config(frame, True, state), depth=frame.depth, readout=readout)
        return state, (again if again.status.ok else result), ((kf.stamp, sharp),)

    def exposure_report(self, state: RunState, frame, dt: float, pairing: Pairing | None = None,
                        speed: float | None = None) -> ExposureReport:
        """This frame's exposure record; when estimated, the ``pairing``'s sample (if any) is added to
        ``state.exposure`` and the report carries the result, the frame's point ``speed`` and the
        central speed it completed."""
        mode = self.exposure_mode(frame)
        if mode != "estimate":
            seconds = self.exposure_of(state, frame, dt)
            return ExposureReport(mode, seconds, seconds / dt if dt > 0 else None)
        sample = None if pairing is None else pairing.sample
        est = self.estimate(state).add(sample, dt)
        return ExposureReport(mode, est.seconds(dt), est.fraction(), None if sample is None else (*sample, dt), est, speed,
                              None if pairing is None else pairing.completed_speed)

    def sample_due(self, state: RunState, stamp: float) -> bool:
        """Whether the frame at ``stamp`` is paired for an exposure sample: not when the exposure probe
        paired it already; else every frame until the estimate has settled (``odometry.exposure_settled``),
        then every ``exposure_thin``-th tracked frame."""
        odo = self.config.odometry
        if stamp <= state.probed_until:
            return False
        return state.tracked % odo.exposure_thin == 0 or not self.estimate(state).settled(SETTLED_SAMPLES, odo.exposure_settled)

    def exposure_pairing(self, state: RunState, frame, T_w_mid: Pose, speed: float, dt: float) -> Pairing:
        """The raw frames kept for an estimated exposure, with this one (speed since the previous
        tracked frame), and a sample. This frame completes the previous raw frame's central speed
        (previous to next mid pose), which pairing compares: the previous frame is paired with the
        recent one whose central speed differs most. Before the first sample (n from the guess's
        blur) and with a short estimate, the pair is tracked with adaptive n; with a short one,
        chosen from an exposure of at least ``odometry.exposure_guess`` until the estimate has
        settled (``odometry.exposure_settled``), from the estimate after."""
        odo = self.config.odometry
        current = RawFrame(frame.timestamp, frame.image, frame.depth, T_w_mid, state.mids[-1][1], dt, speed)
        last = state.recent[-1] if state.recent else None
        if last is None or last.stamp != state.mids[-1][0]:
            return Pairing((*state.recent, current)[-odo.exposure_pair_frames:])
        last = with_next(last, T_w_mid, dt, last.speed)
        last = dataclasses.replace(last, speed=point_speed(state.keyframe.keyframe, state.keyframe.T_world_kf.inverse(), last))
        recent = (*state.recent[:-1], last, current)[-odo.exposure_pair_frames:]
        central = tuple(f for f in state.recent[:-1] if f.T_world_next is not None)
        pair = pick_pair(central, last, odo.exposure_pair_ratio) if self.sample_due(state, last.stamp) else None
        if pair is None:
            return Pairing(recent, None, last.speed)
        pair = (with_keyframe(pair[0], self.camera, self.config.tracker), pair[1])  # the slow frame's, kept for its next pairs
        recent = tuple(pair[0] if f.stamp == pair[0].stamp else f for f in recent)
        est, tracker = self.estimate(state), self.config.tracker
        guess = est.seconds(pair[1].dt)
        if not est.count or self.short_exposure(state, frame):
            tracker = adaptive_n(tracker)
            if est.count and not est.settled(SETTLED_SAMPLES, odo.exposure_settled):
                guess = max(guess, odo.exposure_guess * pair[1].dt)
        sample = pair_sample(*pair, self.camera, tracker, guess, odo.exposure_pair_ratio, odo.exposure_pair_levels)
        return Pairing(recent, sample, last.speed)

    def _tracked(self, state: RunState, frame, index: int, result: TrackResult, informed: bool, fit: Fit,
                 stats: PointStats) -> tuple[RunState, FrameOutcome]:
        """A tracked frame (``stats``: its :meth:`frame_stats`): its poses, its fit remembered, a
        sample for an estimated exposure, perhaps a new keyframe."""
        T_w_kf, traj = state.keyframe.T_world_kf, result.trajectory
        T_w_mid = T_w_kf.compose(traj.middle())
        dt = frame.timestamp - state.mids[-1][0]
        paced = informed or state.dropped == 0  # else the interval since the last tracked frame spans drops
        speed = stats.motion_px / dt if paced and dt > 0 and self.exposure_mode(frame) == "estimate" else None
        pairing = self.exposure_pairing(state, frame, T_w_mid, speed, dt) if speed is not None else Pairing(state.recent)
        report = self.exposure_report(state, frame, dt, pairing, speed)
        state = state.replace(mids=(*state.mids, (frame.timestamp, T_w_mid))[-2:], tracked=state.tracked + 1, consecutive_drops=0,
                              exposure=report.estimate or state.exposure, recent=pairing.recent,
                              fits=(*state.fits, fit)[-self.config.odometry.reject_window:])
        new = None
        if self.wants_keyframe(stats) and frame.depth is not None:
            state, new = self._new_keyframe(state, frame, traj, T_w_mid, stats.blur_px, result.diagnostics.get("readout", 0.0))
        outcome = FrameOutcome(index, frame.timestamp, result.status.name.lower(), T_w_mid, T_w_kf.compose(traj.start),
                               T_w_kf.compose(traj.end), new_keyframe=new, result=result, exposure=report)
        return state, outcome

    def _new_keyframe(self, state: RunState, frame, traj: ExposurePath, T_w_mid: Pose, blur: float, readout: float = 0.0):
        """This frame as the next keyframe, deblurred along its tracked exposure path ``traj`` (mean
        blur ``blur`` px, readout fraction ``readout``) when blurred enough."""
        sharp, triptych = quantize16(frame.image), None
        if blur > self.config.odometry.deblur_min_blur_px and self.config.tracker.blur_aware and not self.probe:
            sharp, n = self.deblurred(frame.image, frame.depth, traj, readout)
            if state.triptychs < self.config.odometry.triptychs:
                triptych = Triptych(frame.image, sharp, frame.depth, traj, n, readout)
                state = state.replace(triptychs=state.triptychs + 1)
        kf = KeyframeState(self.make_keyframe(state, sharp, frame.depth, T_w_mid), T_w_mid, frame.timestamp)
        state = state.replace(keyframe=kf, keyframes=state.keyframes + 1)
        return state, NewKeyframe(frame.timestamp, T_w_mid, sharp, triptych)

    def _dropped(self, state: RunState, frame, index: int, result: TrackResult | None) -> tuple[RunState, FrameOutcome]:
        """No pose; the velocity is forgotten, except after an implausible fit (an odd frame: the motion
        goes on); after ``reset_after_drops`` drops in a row a frame with depth and texture becomes a
        keyframe at the last good pose."""
        odo = self.config.odometry
        odd = result is not None and result.status == Status.IMPLAUSIBLE
        state = state.replace(dropped=state.dropped + 1, consecutive_drops=state.consecutive_drops + 1,
                              mids=state.mids if odd else state.mids[-1:])
        new = None
        usable = frame.depth is not None and np.isfinite(frame.depth).any() and np.std(frame.image) > odo.reset_min_image_std
        if state.consecutive_drops >= odo.reset_after_drops and usable:
            state, new = self.keyframe_without_path(state, frame, state.mids[-1][1])
            state = state.replace(consecutive_drops=0, fits=())  # a new start: earlier fits do not compare
        status = (result.status if result is not None else Status.TOO_FEW_POINTS).name.lower()
        report = self.exposure_report(state, frame, 0.0)
        return state, FrameOutcome(index, frame.timestamp, status, new_keyframe=new, result=result, exposure=report)
