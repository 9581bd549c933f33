"""The camera's recent frame-to-frame motions, kept so that a restart after a loss goes on at the
lost window's speed: the motion of median speed carries the last good pose over the gap to the
new start's reference frame, and the new two-view start is scaled to that speed."""

from __future__ import annotations

import dataclasses

import numpy as np

from ..geometry import Pose
from ..tracking.motion import pose_power

__all__ = ["Motion", "Motions", "PoseAt"]


@dataclasses.dataclass(frozen=True)
class PoseAt:
    """A world pose (camera to world) at a time stamp (s)."""

    stamp: float
    pose: Pose


@dataclasses.dataclass(frozen=True)
class Motion:
    """The camera's motion ``T_prev_cur`` (body frame) over ``dt`` seconds."""

    T: Pose
    dt: float

    @property
    def speed(self) -> float:
        """Translation per second (the world's units)."""
        return float(np.linalg.norm(np.asarray(self.T.t))) / self.dt

    def carry(self, start: PoseAt, stamp: float) -> Pose:
        """``start``'s pose moved on at this motion until ``stamp``."""
        return start.pose.compose(pose_power(self.T, (stamp - start.stamp) / self.dt))


@dataclasses.dataclass(frozen=True)
class Motions:
    """The last ``keep`` frame-to-frame motions, oldest first."""

    items: tuple[Motion, ...] = ()
    keep: int = 9

    def add(self, a: PoseAt, b: PoseAt) -> "Motions":
        """With the motion from ``a`` to ``b`` (the oldest dropped beyond ``keep``); unchanged when
        ``b`` is not later than ``a``."""
        if not b.stamp > a.stamp:
            return self
        motion = Motion(a.pose.inverse().compose(b.pose), b.stamp - a.stamp)
        return dataclasses.replace(self, items=(*self.items, motion)[-self.keep:])

    def typical(self) -> Motion | None:
        """The motion of median speed (the lower middle of an even count; None when none is kept)."""
        if not self.items:
            return None
        order = np.argsort([m.speed for m in self.items], kind="stable")
        return self.items[int(order[(len(order) - 1) // 2])]
