"""Frame statistics over the keyframe points in the frame's view (the monocular pipeline's).

As ``odometry.stats.keyframe_stats`` (flow, visible fraction, blur, motion, distance from the
prediction), but every mean is over the keyframe points that lie in front of the camera and inside
the image at the frame's mid-exposure pose. Moving forward, the camera passes close to points that
then project far outside the image; one such point would otherwise dominate the means. The
statistics also carry DSO's point shift (``mono.keyframes``) over the same points. One compiled
program per sequence (fixed shapes, masks).
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp

from ..blur import blur_lengths
from ..geometry import ExposureTrajectory, Pose
from ..masked import count, masked_mean
from ..mono.keyframes import Shift, point_shift
from ..tracking import Keyframe
from .stats import PointStats

__all__ = ["ViewStats", "in_view_stats"]


@dataclasses.dataclass(frozen=True)
class ViewStats(PointStats):
    """:class:`PointStats` over the points in view, with their DSO shift (pixels)."""

    shift: Shift = Shift()


@jax.jit
def _in_view_stats(cam, pixels, depths, valid, traj: ExposureTrajectory, prev: Pose, predicted: Pose):
    """Flow, visible fraction, blur, motion, jump and the two shifts, means over the points in view."""
    ok_d = valid & jnp.isfinite(depths) & (depths > 0)
    X = jax.vmap(cam.backproject)(pixels, jnp.where(ok_d, depths, 1.0))
    T_mid_kf = traj.middle().inverse()
    Xc = jax.vmap(T_mid_kf.apply)(X)
    front = Xc[:, 2] > 1e-6
    x = jax.vmap(cam.project)(jnp.where(front[:, None], Xc, jnp.array([0.0, 0.0, 1.0])))
    inside = ok_d & front & jax.vmap(cam.in_image)(x)
    flow = masked_mean(jnp.linalg.norm(x - pixels, axis=1), inside)
    lengths, ok = blur_lengths(cam, pixels, depths, traj)
    motion, moved = blur_lengths(cam, pixels, depths, ExposureTrajectory(prev, traj.middle()))
    jump, seen = blur_lengths(cam, pixels, depths, ExposureTrajectory(predicted, traj.middle()))
    visible = inside.sum().astype(flow.dtype) / count(valid, flow.dtype)
    shift_t, shift_rt = point_shift(cam, pixels, X, T_mid_kf, inside)
    means = (masked_mean(lengths, ok & inside), masked_mean(motion, moved & inside), masked_mean(jump, seen & inside))
    return flow, visible, *means, shift_t, shift_rt


def in_view_stats(kf: Keyframe, traj: ExposureTrajectory, prev: Pose | None = None, predicted: Pose | None = None) -> ViewStats:
    """:class:`ViewStats` of the keyframe's points for a tracked exposure path ``traj``, the previous
    frame's mid-exposure pose ``prev`` and the predicted one ``predicted`` (all relative to the
    keyframe; None: no motion, no jump)."""
    pts = kf.points[0]
    if pts.count == 0:
        return ViewStats(float("inf"), 0.0, 0.0, 0.0)
    prev = traj.middle() if prev is None else prev
    predicted = traj.middle() if predicted is None else predicted
    *values, shift_t, shift_rt = (float(v) for v in jax.device_get(_in_view_stats(kf.cameras[0], *pts.on_device, traj, prev, predicted)))
    return ViewStats(*values, shift=Shift(shift_t, shift_rt))
