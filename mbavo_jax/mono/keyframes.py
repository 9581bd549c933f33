"""DSO's shift rule for new keyframes: how far the keyframe's points have moved in the frame.

DSO (Engel, Koltun and Cremers 2018; ``FullSystem::addActiveFrame`` with the flow indicators of
``CoarseTracker::calcRes``) asks for a keyframe when a weighted sum of root-mean-square point
shifts, relative to the image size w + h, exceeds 1: the shift from the translation alone (the
frame's rotation taken out, so that turning on the spot does not ask for one) weighted
0.04 (640 + 480), and the full shift weighted 0.02 (640 + 480). Each shift is pooled over the motion
and the motion with its translation reversed, so that forward and backward motion count alike.
``mono.keyframe_shift`` scales DSO's weights.
"""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from ..geometry import PinholeCamera, Pose

__all__ = ["Shift", "SHIFT_WEIGHT_T", "SHIFT_WEIGHT_RT", "point_shift", "shift_score", "wants_keyframe"]

SHIFT_WEIGHT_T = 0.04 * (640 + 480)  # DSO's weight of the translation-only shift (setting_maxShiftWeightT)
SHIFT_WEIGHT_RT = 0.02 * (640 + 480)  # DSO's weight of the full shift (setting_maxShiftWeightRT)


@dataclasses.dataclass(frozen=True)
class Shift:
    """Root-mean-square shift (pixels) of the keyframe's points in a frame: from the frame's
    translation alone and from its whole motion."""

    translation_px: float = 0.0
    full_px: float = 0.0


def _squared_flow(cam: PinholeCamera, pixels, X, mask):
    """Squared distances between ``pixels`` and the projections of ``X`` (N, 3), 0 where not used,
    and which are used: ``mask`` and in front of the camera."""
    front = X[:, 2] > 1e-6
    x = jax.vmap(cam.project)(jnp.where(front[:, None], X, jnp.array([0.0, 0.0, 1.0])))
    use = mask & front
    return jnp.where(use, jnp.sum((x - pixels) ** 2, axis=1), 0.0), use


def _rms(cam: PinholeCamera, pixels, moved: tuple, mask):
    """RMS flow of the points at each of the positions ``moved`` (pooled)."""
    flows = [_squared_flow(cam, pixels, X, mask) for X in moved]
    total = sum(sq.sum() for sq, _ in flows)
    return jnp.sqrt(total / jnp.maximum(sum(use.sum() for _, use in flows), 1).astype(total.dtype))


def point_shift(
    cam: PinholeCamera, pixels: Float[Array, "N 2"], X: Float[Array, "N 3"], T_frame_kf: Pose, mask: Bool[Array, " N"]
) -> tuple[Float[Array, ""], Float[Array, ""]]:
    """(translation-only, full) RMS shift (pixels) of keyframe points at ``pixels`` (keyframe
    coordinates ``X``) seen from a frame at ``T_frame_kf``, over ``mask``; each pooled over the
    motion and the motion with its translation reversed (traceable)."""
    RX = X @ T_frame_kf.rotation().T
    t = T_frame_kf.t
    return _rms(cam, pixels, (X + t, X - t), mask), _rms(cam, pixels, (RX + t, RX - t), mask)


def shift_score(shift: Shift, width: int, height: int, weight: float) -> float:
    """DSO's keyframe score of a frame's ``shift`` on a ``width`` x ``height`` image, its weights
    scaled by ``weight``: a keyframe is due above 1."""
    return weight * (SHIFT_WEIGHT_T * shift.translation_px + SHIFT_WEIGHT_RT * shift.full_px) / (width + height)


def wants_keyframe(shift: Shift, width: int, height: int, weight: float) -> bool:
    """Whether the shift rule asks for a new keyframe (never with ``weight`` 0)."""
    return weight > 0 and shift_score(shift, width, height, weight) > 1.0
