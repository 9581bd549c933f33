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

from ..geometry import ExposureTrajectory, Pose
from ..mono.keyframes import Shift, point_shift
from ..tracking import Keyframe
from .stats import PointStats, point_view

__all__ = ["ViewStats", "in_view_stats"]


@dataclasses.dataclass(frozen=True)
class ViewStats(PointStats):
    """:class:`PointStats` over the points in view, with their DSO shift (pixels)."""

    shift: Shift = Shift()


@jax.jit
def _in_view_stats(cam, pixels, depths, valid, traj: ExposureTrajectory, prev: Pose, predicted: Pose):
    """Flow, visible fraction, blur, motion, jump (``stats.point_view`` in view) and the two shifts."""
    view = point_view(cam, pixels, depths, valid, traj, prev, predicted, in_view=True)
    return *view.values, *point_shift(cam, pixels, view.X, view.T_mid_kf, view.inside)


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
