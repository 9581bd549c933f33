"""The RGB-D pipeline's per-frame step: predict, track, deblur, decide keyframes, recover.

For each frame: predict its exposure path by constant velocity, track it against the current sharp
keyframe (``tracking.track``), and decide whether it becomes the next keyframe (mean point flow and
blur length, or too few visible points). A blurry frame that becomes a keyframe is deblurred with
its estimated exposure path first; a keyframe made without a path (the first frame, a reset after
drops) is deblurred once the first frame tracked against it gives the camera's velocity. A frame
whose tracking fails is dropped; after ``reset_after_drops`` drops in a row the current frame
becomes a keyframe at the last good pose. No file I/O happens here.
"""

from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from ..blur import blur_lengths
from ..config import OdometryConfig, RunConfig
from ..deblur import choose_deblur_n, deblur, exposure_blur_px
from ..geometry import ExposureTrajectory, PinholeCamera, Pose
from ..masked import count, masked_mean
from ..tracking import Keyframe, Status, TrackResult, constant_velocity_guess, exposure_from_velocity, track
from .state import FrameOutcome, KeyframeState, NewKeyframe, PendingDeblur, RunState, Triptych

__all__ = ["RGBDPipeline", "needs_keyframe", "keyframe_stats"]


@jax.jit
def _keyframe_stats(cam, pixels, depths, valid, traj: ExposureTrajectory):
    """Mean flow (pixels) of the keyframe's points into the frame at mid-exposure, the fraction
    that project inside it, and their mean blur length (one program per sequence)."""
    X = jax.vmap(cam.backproject)(pixels, depths)
    Xc = jax.vmap(traj.middle().inverse().apply)(X)
    x = jax.vmap(cam.project)(jnp.where(Xc[:, 2:3] > 1e-6, Xc, jnp.array([0.0, 0.0, 1.0])))
    inside = valid & (Xc[:, 2] > 1e-6) & jax.vmap(cam.in_image)(x)
    flow = masked_mean(jnp.linalg.norm(x - pixels, axis=1), inside)
    lengths, ok = blur_lengths(cam, pixels, depths, traj)
    ok = ok & valid
    return flow, inside.sum().astype(flow.dtype) / count(valid, flow.dtype), masked_mean(lengths, ok)


def keyframe_stats(kf: Keyframe, traj: ExposureTrajectory) -> tuple[float, float, float]:
    """(flow px, visible fraction, blur px) of the keyframe's points for a tracked exposure path."""
    pts = kf.points[0]
    if pts.count == 0:
        return float("inf"), 0.0, 0.0
    return tuple(float(v) for v in jax.device_get(_keyframe_stats(kf.cameras[0], *pts.on_device, traj)))


def needs_keyframe(flow_px: float, visible: float, blur_px: float, width: int, odo: OdometryConfig) -> bool:
    """Mean point flow beyond ``keyframe_flow`` of the width on a frame blurred at most
    ``keyframe_max_blur_px``, or beyond ``keyframe_flow_max`` whatever its blur, or fewer than
    ``keyframe_min_visible`` of the keyframe's points in view."""
    return bool(visible < odo.keyframe_min_visible or flow_px > odo.keyframe_flow_max * width
                or (flow_px > odo.keyframe_flow * width and blur_px <= odo.keyframe_max_blur_px))


@dataclasses.dataclass(frozen=True)
class RGBDPipeline:
    """Blur-aware RGB-D odometry: images tracked against deblurred keyframes with sensor depth."""

    camera: PinholeCamera
    config: RunConfig = RunConfig()

    def step(self, state: RunState, frame, index: int) -> tuple[RunState, FrameOutcome]:
        t0 = time.perf_counter()
        if state.keyframe is None:
            state, outcome = self._first(state, frame, index)
        else:
            state, outcome = self._track(state, frame, index)
        return state, dataclasses.replace(outcome, seconds=time.perf_counter() - t0)

    # ------------------------------------------------------------------------------ the pieces

    def exposure_of(self, frame) -> float:
        """The frame's exposure time: recorded in the data, else ``odometry.exposure_s``."""
        return frame.exposure if frame.exposure is not None else self.config.odometry.exposure_s

    def pending_of(self, frame) -> PendingDeblur | None:
        """What deblurring a keyframe made from ``frame`` without an exposure path needs, or None
        when it will not be deblurred."""
        cfg = self.config
        wait = cfg.odometry.deblur_first_keyframe and cfg.tracker.blur_aware and self.exposure_of(frame) > 0 and frame.depth is not None
        return PendingDeblur(frame.image, frame.depth, self.exposure_of(frame)) if wait else None

    def keyframe_without_path(self, state: RunState, frame, T_world_kf: Pose) -> tuple[RunState, NewKeyframe]:
        """A keyframe at ``T_world_kf`` from a frame whose exposure path is not known yet: used as it
        is, and deblurred once the next frame tracked against it gives the velocity."""
        kf = KeyframeState(Keyframe.create(frame.image, frame.depth, self.camera, self.config.tracker), T_world_kf, frame.timestamp)
        state = state.replace(keyframe=kf, pending=self.pending_of(frame), keyframes=state.keyframes + 1)
        return state, NewKeyframe(frame.timestamp, T_world_kf, frame.image)

    def _first(self, state: RunState, frame, index: int) -> tuple[RunState, FrameOutcome]:
        """The first frame: the world frame, taken as sharp until its blur is known."""
        T_w = Pose.identity()
        state, new = self.keyframe_without_path(state, frame, T_w)
        state = state.replace(mids=((frame.timestamp, T_w),), tracked=state.tracked + 1)
        return state, FrameOutcome(index, frame.timestamp, "keyframe", T_w, T_w, T_w, new_keyframe=new)

    def predict(self, state: RunState, frame) -> ExposureTrajectory:
        """The frame's exposure path in the keyframe, by constant velocity from the last two mid
        poses, or the last pose (no motion) when the velocity is not known."""
        T_w_kf = state.keyframe.T_world_kf
        if len(state.mids) >= 2:
            (ta, Ta), (tb, Tb) = state.mids[-2], state.mids[-1]
            return constant_velocity_guess(T_w_kf, Ta, Tb, max(tb - ta, 1e-6), self.exposure_of(frame), frame.timestamp - tb)
        last = T_w_kf.inverse().compose(state.mids[-1][1])
        return ExposureTrajectory(last, last)

    def _track(self, state: RunState, frame, index: int) -> tuple[RunState, FrameOutcome]:
        replaced, t0 = (), time.perf_counter()
        if frame.depth is not None and not np.isfinite(frame.depth).any():
            result = None  # nothing to place the frame with
        else:
            result = track(state.keyframe.keyframe, frame.image, self.predict(state, frame), self.config.tracker, depth=frame.depth)
            if state.pending is not None and result.status.ok:
                state, result, replaced = self.deblur_pending(state, frame, result)
        track_seconds = time.perf_counter() - t0
        if result is not None and result.status.ok:
            state, outcome = self._tracked(state, frame, index, result)
        else:
            state, outcome = self._dropped(state, frame, index, result)
        return state, dataclasses.replace(outcome, replaced_images=replaced, track_seconds=track_seconds)

    def deblurred(self, image, depth, path: ExposureTrajectory) -> tuple[np.ndarray, int]:
        """(sharp image, virtual frames used): ``image`` deconvolved along its exposure ``path``."""
        n = choose_deblur_n(depth, self.camera, path, self.config.deblur)
        cfg = dataclasses.replace(self.config.deblur, n=n)
        return deblur(image, depth, self.camera, path, cfg, self.config.tracker.response_gamma), n

    def deblur_pending(self, state: RunState, frame, result: TrackResult):
        """The waiting keyframe deblurred along the constant-velocity path that this frame's motion
        gives, and this frame tracked again against it from the same velocity. Returns (state,
        result, replaced images). A keyframe blurred less than ``deblur_min_blur_px`` stays as it
        is; when the second tracking fails, the first result is kept (with the deblurred keyframe)."""
        kf, pending = state.keyframe, state.pending
        state = state.replace(pending=None)
        mid = result.trajectory.middle()  # T_kf_mid of this frame: the motion over frame.timestamp - stamp
        path = exposure_from_velocity(mid, max(frame.timestamp - kf.stamp, 1e-6), pending.exposure)
        if exposure_blur_px(pending.depth, self.camera, path)[0] <= self.config.odometry.deblur_min_blur_px:
            return state, result, ()
        sharp, _ = self.deblurred(pending.image, pending.depth, path)
        keyframe = Keyframe.create(sharp, pending.depth, self.camera, self.config.tracker)
        state = state.replace(keyframe=dataclasses.replace(kf, keyframe=keyframe))
        init = ExposureTrajectory(mid.compose(path.start), mid.compose(path.end))  # same velocity: T_kf_mid ∘ path
        again = track(keyframe, frame.image, init, self.config.tracker, depth=frame.depth)
        return state, (again if again.status.ok else result), ((kf.stamp, sharp),)

    def _tracked(self, state: RunState, frame, index: int, result: TrackResult) -> tuple[RunState, FrameOutcome]:
        T_w_kf, traj = state.keyframe.T_world_kf, result.trajectory
        T_w_mid = T_w_kf.compose(traj.middle())
        state = state.replace(mids=(*state.mids, (frame.timestamp, T_w_mid))[-2:], tracked=state.tracked + 1, consecutive_drops=0)
        flow, visible, blur = keyframe_stats(state.keyframe.keyframe, traj)
        new = None
        if needs_keyframe(flow, visible, blur, self.camera.width, self.config.odometry) and frame.depth is not None:
            state, new = self._new_keyframe(state, frame, traj, T_w_mid, blur)
        outcome = FrameOutcome(index, frame.timestamp, result.status.name.lower(), T_w_mid, T_w_kf.compose(traj.start),
                               T_w_kf.compose(traj.end), new_keyframe=new, result=result)
        return state, outcome

    def _new_keyframe(self, state: RunState, frame, traj: ExposureTrajectory, T_w_mid: Pose, blur: float):
        """This frame as the next keyframe, deblurred along its path when blurred enough."""
        sharp, triptych = frame.image, None
        if blur > self.config.odometry.deblur_min_blur_px and self.config.tracker.blur_aware:
            sharp, n = self.deblurred(frame.image, frame.depth, traj)
            if state.triptychs < self.config.odometry.triptychs:
                triptych = Triptych(frame.image, sharp, frame.depth, traj, n)
                state = state.replace(triptychs=state.triptychs + 1)
        kf = KeyframeState(Keyframe.create(sharp, frame.depth, self.camera, self.config.tracker), T_w_mid, frame.timestamp)
        state = state.replace(keyframe=kf, keyframes=state.keyframes + 1)
        return state, NewKeyframe(frame.timestamp, T_w_mid, sharp, triptych)

    def _dropped(self, state: RunState, frame, index: int, result: TrackResult | None) -> tuple[RunState, FrameOutcome]:
        """No pose; the velocity is forgotten; after ``reset_after_drops`` drops in a row a frame with
        depth and texture becomes a keyframe at the last good pose."""
        odo = self.config.odometry
        state = state.replace(dropped=state.dropped + 1, consecutive_drops=state.consecutive_drops + 1, mids=state.mids[-1:])
        new = None
        usable = frame.depth is not None and np.isfinite(frame.depth).any() and np.std(frame.image) > odo.reset_min_image_std
        if state.consecutive_drops >= odo.reset_after_drops and usable:
            state, new = self.keyframe_without_path(state, frame, state.mids[-1][1])
            state = state.replace(consecutive_drops=0)
        status = (result.status if result is not None else Status.TOO_FEW_POINTS).name.lower()
        return state, FrameOutcome(index, frame.timestamp, status, new_keyframe=new, result=result)
