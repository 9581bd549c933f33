"""Timestamp association and pose interpolation (numpy, float64)."""

from __future__ import annotations

import numpy as np

from .poses import slerp

__all__ = ["associate", "interpolate_poses"]


def associate(stamps_est: np.ndarray, stamps_ref: np.ndarray, max_diff: float = 0.01, offset: float = 0.0):
    """Indices (i_est, i_ref) pairing each estimate with its nearest reference stamp within
    ``max_diff`` seconds (after adding ``offset`` to the reference), as evo does. ``stamps_ref``
    must be sorted; on a tie the earlier reference wins; a reference may pair with several
    estimates."""
    stamps_est = np.asarray(stamps_est, np.float64)
    ref = np.asarray(stamps_ref, np.float64) + offset
    if len(ref) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    j = np.clip(np.searchsorted(ref, stamps_est), 1, max(len(ref) - 1, 1))
    left = np.clip(j - 1, 0, len(ref) - 1)
    right = np.clip(j, 0, len(ref) - 1)
    pick = np.where(np.abs(ref[left] - stamps_est) <= np.abs(ref[right] - stamps_est), left, right)
    ok = np.abs(ref[pick] - stamps_est) <= max_diff
    return np.nonzero(ok)[0], pick[ok]


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses (N, 7) [t, q] interpolated at ``query`` (linear t, slerp q); NaN outside the range."""
    stamps, poses, query = np.asarray(stamps), np.asarray(poses, np.float64), np.asarray(query)
    out = np.full((len(query), 7), np.nan)
    inside = (query >= stamps[0]) & (query <= stamps[-1]) if len(stamps) else np.zeros(len(query), bool)
    if not inside.any():
        return out
    t = query[inside]
    j = np.clip(np.searchsorted(stamps, t), 1, max(len(stamps) - 1, 1))
    if len(stamps) == 1:  # a single pose: only its own stamp is inside
        out[inside] = poses[0]
        return out
    t0, t1 = stamps[j - 1], stamps[j]
    s = np.where(t1 == t0, 0.0, (t - t0) / np.where(t1 == t0, 1.0, t1 - t0))
    out[inside, :3] = (1 - s)[:, None] * poses[j - 1, :3] + s[:, None] * poses[j, :3]
    out[inside, 3:] = slerp(poses[j - 1, 3:], poses[j, 3:], s)
    return out
