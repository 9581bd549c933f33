"""What a tracked frame's exposure path says about the keyframe's points: flow, visibility, blur
length, the motion since the previous frame and the distance from the predicted pose, in
full-resolution pixels (one program per sequence)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ..blur import blur_lengths
from ..geometry import ExposureTrajectory, Pose
from ..masked import count, masked_mean
from ..tracking import Keyframe

__all__ = ["PointStats", "keyframe_stats"]


@dataclasses.dataclass(frozen=True)
class PointStats:
    """The keyframe's points seen by a tracked frame (full-resolution pixels): mean flow to the
    mid-exposure pose, fraction in view, mean blur length (start to end), and mean motion from
    the previous frame's mid-exposure pose to this one's, and mean distance between where the
    predicted and the tracked mid-exposure poses see them (how far the fit jumped from the prediction)."""

    flow_px: float
    visible: float
    blur_px: float
    motion_px: float
    jump_px: float = 0.0


@jax.jit
def _keyframe_stats(cam, pixels, depths, valid, traj: ExposureTrajectory, prev: Pose, predicted: Pose):
    """Flow, visible fraction, blur, motion and jump of :class:`PointStats` (one program per sequence)."""
    X = jax.vmap(cam.backproject)(pixels, depths)
    Xc = jax.vmap(traj.middle().inverse().apply)(X)
    x = jax.vmap(cam.project)(jnp.where(Xc[:, 2:3] > 1e-6, Xc, jnp.array([0.0, 0.0, 1.0])))
    inside = valid & (Xc[:, 2] > 1e-6) & jax.vmap(cam.in_image)(x)
    flow = masked_mean(jnp.linalg.norm(x - pixels, axis=1), inside)
    lengths, ok = blur_lengths(cam, pixels, depths, traj)
    motion, moved = blur_lengths(cam, pixels, depths, ExposureTrajectory(prev, traj.middle()))
    jump, seen = blur_lengths(cam, pixels, depths, ExposureTrajectory(predicted, traj.middle()))
    visible = inside.sum().astype(flow.dtype) / count(valid, flow.dtype)
    return flow, visible, masked_mean(lengths, ok & valid), masked_mean(motion, moved & valid), masked_mean(jump, seen & valid)


def keyframe_stats(kf: Keyframe, traj: ExposureTrajectory, prev: Pose | None = None, predicted: Pose | None = None) -> PointStats:
    """:class:`PointStats` of the keyframe's points for a tracked exposure path ``traj``, the
    previous frame's mid-exposure pose ``prev`` and the predicted one ``predicted`` (all relative
    to the keyframe; None: no motion, no jump)."""
    pts = kf.points[0]
    if pts.count == 0:
        return PointStats(float("inf"), 0.0, 0.0, 0.0)
    prev = traj.middle() if prev is None else prev
    predicted = traj.middle() if predicted is None else predicted
    return PointStats(*(float(v) for v in jax.device_get(_keyframe_stats(kf.cameras[0], *pts.on_device, traj, prev, predicted))))
