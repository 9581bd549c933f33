"""Depth maps of a monocular window's points seen from one camera: sparse (for the tracker's point
selection) and filled (for deblurring and blur lengths, which need a depth at every pixel)."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

from ..geometry import PinholeCamera, Pose
from .window import pad_rows, padded_length

__all__ = ["project_points", "sparse_depth", "filled_depth"]


@jax.jit
def _project(camera: PinholeCamera, T_cam_world: Pose, xyz: Float[Array, "N 3"]):
    """``project_points`` compiled (jax arrays, no padding)."""
    Xc = jax.vmap(T_cam_world.apply)(xyz)
    z = Xc[:, 2]
    safe = jnp.where(z[:, None] > 1e-6, Xc, jnp.array([0.0, 0.0, 1.0], Xc.dtype))
    x = jax.vmap(camera.project)(safe)
    ok = (z > 1e-6) & jax.vmap(camera.in_image)(x)
    return x, z, ok


def project_points(camera: PinholeCamera, T_cam_world: Pose, xyz) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixels (N, 2) and z-depths (N,) of world points (N, 3) in a camera; ``ok`` (N,): in front and
    in view. NumPy results; the points are padded (``window.padded_length``) so that a varying N
    compiles a few programs only."""
    xyz = np.asarray(xyz, np.float32).reshape(-1, 3)
    n = xyz.shape[0]
    x, z, ok = jax.device_get(_project(camera, T_cam_world, pad_rows(xyz, padded_length(n))))
    return x[:n], z[:n], ok[:n]


def sparse_depth(camera: PinholeCamera, T_world_cam: Pose, xyz: np.ndarray) -> np.ndarray:
    """(H, W) float32 z-depth at the pixel each world point projects to (the nearest where two
    meet), NaN elsewhere."""
    depth = np.full((camera.height, camera.width), np.inf, np.float32)
    if len(xyz):
        x, z, ok = project_points(camera, T_world_cam.inverse(), xyz)
        u, v = np.rint(x[ok, 0]).astype(int), np.rint(x[ok, 1]).astype(int)
        np.minimum.at(depth, (v, u), z[ok].astype(np.float32))
    depth[~np.isfinite(depth)] = np.nan
    return depth


def filled_depth(sparse: np.ndarray, cell: int = 16) -> np.ndarray:
    """(H, W) float32 depth everywhere: the median inverse depth of each ``cell`` x ``cell`` block of
    ``sparse``, empty blocks filled from their nearest non-empty one, smoothly upsampled. All NaN
    when ``sparse`` holds no depth."""
    h, w = sparse.shape
    hc, wc = -(-h // cell), -(-w // cell)
    pad = np.full((hc * cell, wc * cell), np.nan, np.float32)
    pad[:h, :w] = 1.0 / sparse
    blocks = pad.reshape(hc, cell, wc, cell).transpose(0, 2, 1, 3).reshape(hc, wc, -1)
    empty = ~np.isfinite(blocks).any(-1)
    if empty.all():
        return np.full((h, w), np.nan, np.float32)
    with np.errstate(all="ignore"):
        grid = np.where(empty, 0.0, np.nanmedian(np.where(empty[..., None], 0.0, blocks), axis=-1)).astype(np.float32)
    if empty.any():  # nearest non-empty block (a distance transform's indices)
        import scipy.ndimage as ndi

        idx = ndi.distance_transform_edt(empty, return_distances=False, return_indices=True)
        grid = grid[idx[0], idx[1]]
    inv = cv2.resize(grid, (wc * cell, hc * cell), interpolation=cv2.INTER_LINEAR)[:h, :w]
    return (1.0 / np.maximum(inv, 1e-6)).astype(np.float32)
