"""Keyframe deblurring with the estimated exposure path (supplement §6: the back-end only sees
deblurred keyframes).

The blur operator A (``render_blurry`` with the frame as its own reference: the sharp image x at
the mid-exposure pose, transferred through the frame's depth planes) is linear in x. We solve

    min_x ‖A x − b‖² + λ ‖∇x‖²

by conjugate gradients on the normal equations (Aᵀ from ``jax.linear_transpose``), starting from b.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from .blur import blur_lengths, plane_depths_from_keyframe, render_blurry, round_up_pow2
from .config import DeblurConfig
from .geometry.camera import PinholeCamera
from .geometry.pose import Pose
from .geometry.trajectory import ExposureTrajectory
from .image import delinearize, linearize

__all__ = ["deblur", "choose_deblur_n", "exposure_blur_px", "psnr", "ssim"]


def exposure_blur_px(depth, camera: PinholeCamera, trajectory: ExposureTrajectory, stride: int = 8) -> tuple[float, float]:
    """Blur length of a frame in pixels, (mean, 95th percentile), over every ``stride``-th pixel with
    valid depth (``blur.blur_lengths`` about the path's own mid pose). (0, 0) where no depth is valid."""
    d = jnp.asarray(np.asarray(depth, np.float32)[::stride, ::stride])
    v, u = np.mgrid[0 : depth.shape[0] : stride, 0 : depth.shape[1] : stride]
    pixels = jnp.asarray(np.stack([u.ravel(), v.ravel()], 1), jnp.float32)
    lengths, valid = jax.device_get(_blur_lengths(camera, pixels, d.ravel(), trajectory.about_middle()))
    lengths = lengths[valid]
    if lengths.size == 0:
        return 0.0, 0.0
    return float(lengths.mean()), float(np.percentile(lengths, 95))


_blur_lengths = jax.jit(blur_lengths)


def choose_deblur_n(depth, camera: PinholeCamera, trajectory: ExposureTrajectory, config: DeblurConfig = DeblurConfig()) -> int:
    """``config.n`` if positive, else one virtual frame per pixel of the frame's 95th-percentile blur
    (gaps between virtual frames make the deconvolution ring), a power of two in [n_min, n_max]."""
    if config.n > 0:
        return config.n
    return round_up_pow2(exposure_blur_px(depth, camera, trajectory)[1], config.n_min, config.n_max)


def _grad_ops(x):
    gx = x[:, 1:] - x[:, :-1]
    gy = x[1:, :] - x[:-1, :]
    return gx, gy


@partial(jax.jit, static_argnames=("n", "iterations"))
def _deblur(blurry, planes, camera, traj, lam, n, iterations):
    def A(x):
        return render_blurry(x, planes, camera, traj, n)[0]

    valid = render_blurry(jnp.ones_like(blurry), planes, camera, traj, n)[1]
    At = jax.linear_transpose(A, blurry)
    b = jnp.where(valid, blurry, 0.0)

    def normal(x):
        (atax,) = At(jnp.where(valid, A(x), 0.0))
        reg = jax.grad(lambda z: 0.5 * sum(jnp.sum(g * g) for g in _grad_ops(z)))(x)
        return atax + lam * reg

    (rhs,) = At(b)
    # pixels that no valid blurry pixel sees keep the blurry value (the identity on them)
    seen = At(valid.astype(blurry.dtype))[0] > 1e-6
    rhs = jnp.where(seen, rhs, blurry)
    op = lambda x: jnp.where(seen, normal(x), x)

    x = blurry
    r = rhs - op(x)
    p = r
    rs = jnp.sum(r * r)

    def body(_, state):
        x, r, p, rs = state
        Ap = op(p)
        alpha = rs / jnp.maximum(jnp.sum(p * Ap), 1e-20)
        x = x + alpha * p
        r = r - alpha * Ap
        rs_new = jnp.sum(r * r)
        p = r + (rs_new / jnp.maximum(rs, 1e-30)) * p
        return x, r, p, rs_new

    x, *_ = jax.lax.fori_loop(0, iterations, body, (x, r, p, rs))
    return jnp.clip(x, 0.0, 1.0)


def deblur(blurry, depth, camera: PinholeCamera, trajectory: ExposureTrajectory, config: DeblurConfig = DeblurConfig(),
           response_gamma: float = 1.0) -> np.ndarray:
    """Sharp mid-exposure image of a blurry frame, given its depth (metres, NaN = none) and its
    exposure path (any reference frame: it is re-expressed about its own mid pose). Works in
    linear radiance (``response_gamma``) and returns display intensities in [0, 1]."""
    n = choose_deblur_n(depth, camera, trajectory, config)
    planes = plane_depths_from_keyframe(jnp.asarray(np.asarray(depth, np.float32)), camera, Pose.identity())
    x = _deblur(jnp.asarray(linearize(blurry, response_gamma)), planes, camera, trajectory.about_middle(),
                jnp.float32(config.regularization), n, config.iterations)
    return delinearize(np.asarray(x), response_gamma)


def psnr(a, b, mask=None) -> float:
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    m = np.ones(a.shape, bool) if mask is None else np.asarray(mask, bool)
    mse = np.mean((a[m] - b[m]) ** 2)
    return float(10 * np.log10(1.0 / max(mse, 1e-12)))


def ssim(a, b) -> float:
    """Mean SSIM (Wang et al. 2004) with an 11x11 Gaussian window (σ 1.5), intensities in [0, 1]."""
    import cv2

    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    c1, c2 = 0.01**2, 0.03**2
    blur = lambda x: cv2.GaussianBlur(x, (11, 11), 1.5)
    mu_a, mu_b = blur(a), blur(b)
    saa = blur(a * a) - mu_a**2
    sbb = blur(b * b) - mu_b**2
    sab = blur(a * b) - mu_a * mu_b
    s = ((2 * mu_a * mu_b + c1) * (2 * sab + c2)) / ((mu_a**2 + mu_b**2 + c1) * (saa + sbb + c2))
    return float(s[5:-5, 5:-5].mean())
