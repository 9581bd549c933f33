"""Pose rows ``[tx, ty, tz, qx, qy, qz, qw]`` as NumPy float64 arrays for evaluation: 4x4 matrices
and interpolation, computed by the geometry module's quaternion functions (one implementation) in
float64."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..geometry import quaternion as quat

__all__ = ["pose_matrices", "slerp"]


def _rotations(q: np.ndarray) -> np.ndarray:
    with jax.enable_x64(True):
        return np.asarray(jax.vmap(quat.to_matrix)(jnp.asarray(q, jnp.float64)))


def _slerp(q0: np.ndarray, q1: np.ndarray, s: np.ndarray) -> np.ndarray:
    def one(a, b, si):
        return quat.product(a, quat.exp(si * quat.log(quat.product(quat.inverse(a), b))))  # Eq. 43

    with jax.enable_x64(True):
        f64 = lambda x: jnp.asarray(x, jnp.float64)
        return np.asarray(jax.vmap(one)(f64(q0), f64(q1), f64(s)))


def pose_matrices(poses: np.ndarray) -> np.ndarray:
    """(N, 7) [t, q] → (N, 4, 4); quaternions are normalised first."""
    poses = np.asarray(poses, np.float64).reshape(-1, 7)
    T = np.tile(np.eye(4), (len(poses), 1, 1))
    if len(poses):
        T[:, :3, :3] = _rotations(poses[:, 3:] / np.linalg.norm(poses[:, 3:], axis=1, keepdims=True))
    T[:, :3, 3] = poses[:, :3]
    return T


def slerp(q0: np.ndarray, q1: np.ndarray, s) -> np.ndarray:
    """Shortest-path interpolation of unit quaternions [qx, qy, qz, qw] at fractions ``s``: rows
    (N, 4) with s (N,), or single quaternions with a scalar s."""
    single = np.ndim(q0) == 1
    q0, q1 = np.atleast_2d(q0), np.atleast_2d(q1)
    out = _slerp(q0, q1, np.broadcast_to(np.asarray(s, np.float64), (len(q0),)))
    return out[0] if single else out
