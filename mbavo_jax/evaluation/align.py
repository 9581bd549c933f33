"""Umeyama alignment (Umeyama 1991, Eqs. 38-42), with the rank check and the reflection fix."""

from __future__ import annotations

import numpy as np

from ..errors import MbavoError

__all__ = ["umeyama"]


def umeyama(x: np.ndarray, y: np.ndarray, with_scale: bool = False):
    """Least-squares (R, t, s) with y ≈ s R x + t for point sets x, y of shape (N, 3)."""
    x = np.asarray(x, np.float64)
    y = np.asarray(y, np.float64)
    if x.shape != y.shape or x.ndim != 2 or x.shape[1] != 3:
        raise ValueError(f"umeyama needs two (N, 3) arrays, got {x.shape} and {y.shape}")
    n = x.shape[0]
    if n < 3:
        raise MbavoError(f"alignment needs at least 3 matched poses, got {n}")
    mx, my = x.mean(0), y.mean(0)
    xc, yc = x - mx, y - my
    var_x = np.mean(np.sum(xc**2, 1))
    cov = yc.T @ xc / n
    U, D, Vt = np.linalg.svd(cov)
    if np.linalg.matrix_rank(cov) < 2:
        raise MbavoError("degenerate alignment: the matched positions are (nearly) collinear or identical")
    S = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        S[2, 2] = -1  # reflection fix
    R = U @ S @ Vt
    s = float(np.trace(np.diag(D) @ S) / var_x) if with_scale else 1.0
    t = my - s * R @ mx
    return R, t, s
