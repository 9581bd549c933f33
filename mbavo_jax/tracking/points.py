"""Point selection on a sharp keyframe: the gradient-strongest pixel per grid cell, per pyramid level.

Shapes never change between keyframes: each level holds exactly ``max_points`` slots, padded with
``valid = False``. Depths come from the keyframe's depth map (NaN or ≤ 0 → not selected).
"""

from __future__ import annotations

import dataclasses
import functools

import jax.numpy as jnp
import numpy as np

__all__ = ["PATTERN", "LevelPoints", "select_points", "given_points", "downsample_depth", "gradient_magnitude"]

# DSO's 8-pixel residual pattern (offsets in pixels, (du, dv)).
PATTERN = np.array([[0, -2], [-1, -1], [1, -1], [-2, 0], [0, 0], [2, 0], [-1, 1], [0, 2]], dtype=np.float32)


@dataclasses.dataclass(frozen=True)
class LevelPoints:
    """Selected keyframe points of one pyramid level: pixels (N, 2), depths (N,), valid (N,)."""

    pixels: np.ndarray
    depths: np.ndarray
    valid: np.ndarray

    @property
    def count(self) -> int:
        return int(self.valid.sum())

    @functools.cached_property
    def on_device(self) -> tuple:
        """(pixels, depths, valid) as device arrays, copied once per keyframe rather than per frame."""
        return jnp.asarray(self.pixels), jnp.asarray(self.depths), jnp.asarray(self.valid)


def gradient_magnitude(img: np.ndarray) -> np.ndarray:
    gx = np.zeros_like(img)
    gy = np.zeros_like(img)
    gx[:, 1:-1] = 0.5 * (img[:, 2:] - img[:, :-2])
    gy[1:-1, :] = 0.5 * (img[2:, :] - img[:-2, :])
    return np.sqrt(gx * gx + gy * gy)


def downsample_depth(depth: np.ndarray) -> np.ndarray:
    """2x2 downsampling of a depth map: mean of the valid depths of each block (NaN if none)."""
    h, w = depth.shape[0] // 2, depth.shape[1] // 2
    d = depth[: 2 * h, : 2 * w].reshape(h, 2, w, 2)
    ok = np.isfinite(d) & (d > 0)
    cnt = ok.sum(axis=(1, 3))
    tot = np.where(ok, d, 0.0).sum(axis=(1, 3))
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(cnt > 0, tot / np.maximum(cnt, 1), np.nan).astype(np.float32)


def select_points(
    image: np.ndarray,
    depth: np.ndarray,
    max_points: int,
    cell: int = 16,
    grad_threshold: float = 8.0 / 255.0,
    border: int = 4,
) -> LevelPoints:
    """The strongest-gradient pixel of each ``cell`` x ``cell`` block whose gradient magnitude
    exceeds ``grad_threshold`` (intensities in [0, 1]) and whose depth is valid; the ``max_points``
    strongest of those, padded to exactly ``max_points`` slots."""
    img = np.asarray(image, np.float32)
    dep = np.asarray(depth, np.float32)
    h, w = img.shape
    g = gradient_magnitude(img)
    ok = np.isfinite(dep) & (dep > 0) & (g > grad_threshold)
    ok[:border, :] = ok[-border:, :] = False
    ok[:, :border] = ok[:, -border:] = False
    score = np.where(ok, g, -1.0)
    hc, wc = h // cell, w // cell
    if hc == 0 or wc == 0:
        cell = max(1, min(h, w))
        hc, wc = h // cell, w // cell
    blocks = score[: hc * cell, : wc * cell].reshape(hc, cell, wc, cell).transpose(0, 2, 1, 3).reshape(hc, wc, -1)
    arg = blocks.argmax(-1)
    best = np.take_along_axis(blocks, arg[..., None], -1)[..., 0]
    rows = (np.arange(hc)[:, None] * cell + arg // cell).ravel()
    cols = (np.arange(wc)[None, :] * cell + arg % cell).ravel()
    best = best.ravel()
    keep = np.nonzero(best > 0)[0]
    keep = keep[np.argsort(-best[keep], kind="stable")][:max_points]
    pixels = np.zeros((max_points, 2), np.float32)
    depths = np.ones(max_points, np.float32)
    valid = np.zeros(max_points, bool)
    k = len(keep)
    pixels[:k, 0] = cols[keep]
    pixels[:k, 1] = rows[keep]
    depths[:k] = dep[rows[keep], cols[keep]]
    valid[:k] = True
    return LevelPoints(pixels, depths, valid)


def given_points(image: np.ndarray, pixels: np.ndarray, depths: np.ndarray, max_points: int, border: int = 2) -> LevelPoints:
    """Points given with their depths (pixels (N, 2) of this level, z-depths (N,)): one per pixel
    (the nearest; kept at its exact position), those inside ``border`` with a positive depth, the strongest image gradients first,
    padded to exactly ``max_points`` slots."""
    h, w = image.shape
    x = np.rint(pixels).astype(np.int64)
    ok = (depths > 0) & np.isfinite(depths) & (x[:, 0] >= border) & (x[:, 1] >= border) & (x[:, 0] < w - border) & (x[:, 1] < h - border)
    x, d, exact = x[ok], depths[ok], np.asarray(pixels, np.float32)[ok]
    g = gradient_magnitude(np.asarray(image, np.float32))[x[:, 1], x[:, 0]]
    order = np.argsort(-g, kind="stable")
    _, first = np.unique((x[order, 1] * w + x[order, 0]), return_index=True)  # one point per pixel: its strongest
    keep = order[np.sort(first)][:max_points]
    out = LevelPoints(np.zeros((max_points, 2), np.float32), np.ones(max_points, np.float32), np.zeros(max_points, bool))
    out.pixels[: len(keep)] = exact[keep]
    out.depths[: len(keep)] = d[keep]
    out.valid[: len(keep)] = True
    return out
