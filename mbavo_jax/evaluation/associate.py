"""Timestamp association and pose interpolation (numpy, float64)."""

from __future__ import annotations

import numpy as np

__all__ = ["associate", "interpolate_poses", "slerp"]


def associate(stamps_est: np.ndarray, stamps_ref: np.ndarray, max_diff: float = 0.01, offset: float = 0.0):
    """Indices (i_est, i_ref) pairing each estimate with its nearest reference stamp within
    ``max_diff`` seconds (after adding ``offset`` to the reference), as evo does."""
    stamps_est = np.asarray(stamps_est, np.float64)
    ref = np.asarray(stamps_ref, np.float64) + offset
    j = np.clip(np.searchsorted(ref, stamps_est), 1, max(len(ref) - 1, 1))
    left = np.clip(j - 1, 0, len(ref) - 1)
    right = np.clip(j, 0, len(ref) - 1)
    pick = np.where(np.abs(ref[left] - stamps_est) <= np.abs(ref[right] - stamps_est), left, right)
    ok = np.abs(ref[pick] - stamps_est) <= max_diff
    return np.nonzero(ok)[0], pick[ok]


def slerp(q0: np.ndarray, q1: np.ndarray, s: float) -> np.ndarray:
    """Shortest-path spherical interpolation of unit quaternions [qx, qy, qz, qw]."""
    d = float(np.dot(q0, q1))
    if d < 0:
        q1, d = -q1, -d
    if d > 1 - 1e-9:
        q = q0 + s * (q1 - q0)
        return q / np.linalg.norm(q)
    a = np.arccos(d)
    return (np.sin((1 - s) * a) * q0 + np.sin(s * a) * q1) / np.sin(a)


def interpolate_poses(stamps: np.ndarray, poses: np.ndarray, query: np.ndarray) -> np.ndarray:
    """Poses (N, 7) [t, q] interpolated at ``query`` (linear t, slerp q); NaN outside the range."""
    out = np.full((len(query), 7), np.nan)
    for k, t in enumerate(query):
        j = np.searchsorted(stamps, t)
        if j == 0 and t == stamps[0]:
            out[k] = poses[0]
        elif 0 < j < len(stamps) or (j == len(stamps) and t == stamps[-1]):
            j = min(j, len(stamps) - 1)
            t0, t1 = stamps[j - 1], stamps[j]
            s = 0.0 if t1 == t0 else (t - t0) / (t1 - t0)
            out[k, :3] = (1 - s) * poses[j - 1, :3] + s * poses[j, :3]
            out[k, 3:] = slerp(poses[j - 1, 3:], poses[j, 3:], s)
    return out
