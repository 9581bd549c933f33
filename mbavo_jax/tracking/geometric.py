"""Optional geometric residuals for RGB-D input: the current frame's own depth map.

MBA-VO aligns images only; an RGB-D camera also measures depth at (about) mid-exposure, and ICP-style
peers (Open3D's hybrid term, OpenCV's RGB_DEPTH) use it. This module adds that constraint to the
blur-aware tracker without touching its photometric model. A keyframe point X (pixel x, depth d)
seen from the mid-exposure pose T_ref_mid should lie on the current depth map:

    X' = T_ref_mid⁻¹ · π⁻¹(x, d),      r(x) = (D_cur(π(X')) − X'_z) / σ(X'_z)

(DVO-SLAM's depth residual, Kerl et al. 2013), in units of the sensor's depth noise
σ(z) = a + b·(z − 0.4)² metres (the axial noise model of Nguyen, Izadi & Lovell 2012 for
Kinect-class structured-light sensors: a = 1.2 mm, b = 1.9 mm/m²; σ is held fixed in the
derivative, as in iteratively reweighted least squares). The residual depends only on
the middle pose, so it constrains where the exposure is, not how long it is; the photometric blur
model stays in charge of the start/end split. D_cur is sampled bilinearly and a sample counts only
when its four neighbours are valid and agree to ``edge_rel``, so depth edges (where bilinear depth
is meaningless) drop out. Keyframe points for this term sit on a regular grid away from depth edges
(``select_depth_points``): gradient-selected photometric points cluster on edges, the worst place
for a depth residual.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float

from ..geometry.camera import PinholeCamera
from ..geometry.pose import Pose
from ..image import bilinear_cell, lerp_cell
from .points import LevelPoints

__all__ = ["select_depth_points", "depth_residuals", "sample_depth"]


def select_depth_points(depth: np.ndarray, stride: int, edge_rel: float = 0.02, border: int = 2) -> LevelPoints:
    """One keyframe point per ``stride`` x ``stride`` cell (its centre) where the depth is valid and
    smooth (the 3x3 neighbourhood spans less than ``edge_rel`` of the depth). Fixed size: one slot
    per cell of the image, padded with ``valid = False``."""
    dep = np.asarray(depth, np.float32)
    h, w = dep.shape
    stride = max(1, int(stride))
    vs = np.arange(border + stride // 2, h - border, stride)
    us = np.arange(border + stride // 2, w - border, stride)
    if vs.size == 0 or us.size == 0:  # tiny level: a single centre point
        vs, us = np.array([h // 2]), np.array([w // 2])
    vv, uu = np.meshgrid(vs, us, indexing="ij")
    vv, uu = vv.ravel(), uu.ravel()
    d = dep[vv, uu]
    ok = np.isfinite(d) & (d > 0)
    lo = np.full_like(d, np.inf)
    hi = np.full_like(d, -np.inf)
    for dv in (-1, 0, 1):
        for du in (-1, 0, 1):
            nb = dep[np.clip(vv + dv, 0, h - 1), np.clip(uu + du, 0, w - 1)]
            good = np.isfinite(nb) & (nb > 0)
            ok &= good
            lo = np.minimum(lo, np.where(good, nb, np.inf))
            hi = np.maximum(hi, np.where(good, nb, -np.inf))
    with np.errstate(invalid="ignore"):
        ok &= (hi - lo) < edge_rel * np.where(ok, d, 1.0)
    pixels = np.stack([uu, vv], axis=1).astype(np.float32)
    return LevelPoints(pixels, np.where(ok, d, 1.0).astype(np.float32), ok)


def sample_depth(depth: Float[Array, "H W"], x: Float[Array, "2"], edge_rel: float | Float[Array, ""]):
    """Bilinear depth at x and its validity: inside, all four neighbours > 0 and within ``edge_rel``
    of each other (0 marks a missing measurement)."""
    inside, fu, fv, corners = bilinear_cell(depth, x)
    nb = jnp.stack(corners)
    lo, hi = jnp.min(nb), jnp.max(nb)
    valid = inside & (lo > 0) & (hi - lo < edge_rel * jnp.maximum(lo, 1e-6))
    return jnp.where(valid, lerp_cell(fu, fv, corners)[0], 1.0), valid


def depth_residuals(
    mid: Pose,
    camera: PinholeCamera,
    cur_depth: Float[Array, "H W"],
    pixels: Float[Array, "N 2"],
    depths: Float[Array, "N"],
    pvalid: Bool[Array, "N"],
    edge_rel: float | Float[Array, ""],
    sigma: tuple = (0.0012, 0.0019),
    outlier: float | Float[Array, ""] = float("inf"),
) -> tuple[Float[Array, "N"], Bool[Array, "N"]]:
    """Depth residuals (D_cur(π(X')) − X'_z) / σ(X'_z) of the keyframe points seen from
    ``mid`` = T_ref_mid, and their validity (invalid residuals are 0). ``cur_depth`` uses 0 for
    missing depth; ``sigma`` = (a, b) of σ(z) = a + b·(z − 0.4)²; residuals are truncated at
    ±``outlier`` σ (occlusions, a point hidden behind a nearer surface, stop pulling the pose, and
    no pose gains by pushing a point past the cut). Differentiable in ``mid`` (plain autodiff: N
    residuals of one pose)."""
    T_cur_ref = mid.inverse()

    def one(x, d):
        p = T_cur_ref.apply(camera.backproject(x, d))
        in_front = p[2] > 1e-3
        z = jnp.where(in_front, p[2], 1.0)
        safe = jnp.where(in_front, p, jnp.array([0.0, 0.0, 1.0], p.dtype))
        dm, ok = sample_depth(cur_depth, camera.project(safe), edge_rel)
        ok = ok & in_front
        sd = jax.lax.stop_gradient(sigma[0] + sigma[1] * (z - 0.4) ** 2)
        r = jnp.clip((dm - z) / sd, -outlier, outlier)
        return jnp.where(ok, r, 0.0), ok

    r, ok = jax.vmap(one)(pixels, depths)
    ok = ok & pvalid
    return jnp.where(ok, r, 0.0), ok
