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

__all__ = ["PointStats", "keyframe_stats", "point_view"]


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


@dataclasses.dataclass(frozen=True)
class _View:
    """The keyframe points seen from a tracked frame (traced): their keyframe coordinates ``X``, the
    frame's mid pose ``T_mid_kf``, which lie ``inside`` its image, and the :class:`PointStats` values."""

    X: jax.Array
    T_mid_kf: Pose
    inside: jax.Array
    values: tuple


def point_view(cam, pixels, depths, valid, traj: ExposureTrajectory, prev: Pose, predicted: Pose, in_view: bool) -> _View:
    """Flow, visible fraction, blur, motion and jump of the keyframe's points: the last three means
    over the ``valid`` points, or with ``in_view`` over those with a usable depth that lie in front of
    the camera and inside the image at the mid-exposure pose (traceable)."""
    usable = valid & jnp.isfinite(depths) & (depths > 0) if in_view else valid
    X = jax.vmap(cam.backproject)(pixels, jnp.where(usable, depths, 1.0))
    T_mid_kf = traj.middle().inverse()
    Xc = jax.vmap(T_mid_kf.apply)(X)
    front = Xc[:, 2] > 1e-6
    x = jax.vmap(cam.project)(jnp.where(front[:, None], Xc, jnp.array([0.0, 0.0, 1.0])))
    inside = usable & front & jax.vmap(cam.in_image)(x)
    flow = masked_mean(jnp.linalg.norm(x - pixels, axis=1), inside)
    lengths, ok = blur_lengths(cam, pixels, depths, traj)
    motion, moved = blur_lengths(cam, pixels, depths, ExposureTrajectory(prev, traj.middle()))
    jump, seen = blur_lengths(cam, pixels, depths, ExposureTrajectory(predicted, traj.middle()))
    visible = inside.sum().astype(flow.dtype) / count(valid, flow.dtype)
    mask = inside if in_view else valid
    means = (masked_mean(lengths, ok & mask), masked_mean(motion, moved & mask), masked_mean(jump, seen & mask))
    return _View(X, T_mid_kf, inside, (flow, visible, *means))


@jax.jit
def _keyframe_stats(cam, pixels, depths, valid, traj: ExposureTrajectory, prev: Pose, predicted: Pose):
    """Flow, visible fraction, blur, motion and jump of :class:`PointStats` (one program per sequence)."""
    return point_view(cam, pixels, depths, valid, traj, prev, predicted, in_view=False).values


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
