"""Keyframe deblurring with the estimated exposure path (supplement §6: the back-end only sees
deblurred keyframes).

The blur operator A (``render_blurry`` with the frame as its own reference: the sharp image x at
the mid-exposure pose, transferred through the frame's depth planes) is linear in x. We solve

    min_x ‖A x − b‖² + λ ‖∇x‖²

by conjugate gradients on the normal equations, starting from b, for at most
``DeblurConfig.iterations`` steps (fewer once the residual has fallen to ``DeblurConfig.tolerance``
of the first), with one of two forms of A (``DeblurConfig.solver``):

* ``table`` (default): every sample's plane transfer is done once per frame; a
  :class:`SamplingTable` keeps its bilinear cell (int32) and position in the cell (2 x uint16),
  8 bytes per sample (n x H x W of them). A is then one gather of four cell corners per sample
  and Aᵀ one scatter-add per virtual frame (:func:`table_blur`, :func:`table_blur_adjoint`);
* ``render``: the reference; A is ``render_blurry`` itself (every transfer redone at every
  application) and Aᵀ its ``jax.linear_transpose``.

Both honour a rolling-shutter readout (each row's own virtual times) and give the same image up
to float32 rounding. With ``DeblurConfig.coarse_to_fine`` (default) the problem is solved first at
half resolution (half the virtual frames), and its solution, upsampled, starts a few
full-resolution steps (``DeblurConfig.fine_iterations``).
"""

from __future__ import annotations

from collections.abc import Callable
from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int, UInt16

from .blur import blur_lengths, plane_depths_from_keyframe, render_blurry, round_up_frames, virtual_pq, virtual_pq_table, virtual_sample
from .config import DeblurConfig
from .geometry.camera import PinholeCamera
from .geometry.pose import Pose
from .geometry.spline import ExposurePath
from .geometry.trajectory import row_times
from .image import cell_position, delinearize, downsample, lerp_cell, linearize

__all__ = ["deblur", "choose_deblur_n", "exposure_blur_px", "psnr", "ssim", "SamplingTable", "sampling_table", "table_blur", "table_seen",
           "table_blur_adjoint"]

FRACTION_ONE = 65535  # a sample's position inside its bilinear cell is stored as uint16 k / FRACTION_ONE


def exposure_blur_px(depth, camera: PinholeCamera, trajectory: ExposurePath, stride: int = 8,
                     readout: float = 0.0) -> tuple[float, float]:
    """Blur length of a frame in pixels, (mean, 95th percentile), over every ``stride``-th pixel with
    valid depth (``blur.blur_lengths`` about the path's own mid pose; with a rolling shutter of
    readout fraction ``readout``, the middle row's own exposure). (0, 0) where no depth is valid."""
    trajectory = trajectory.middle_row_path(readout)
    d = jnp.asarray(np.asarray(depth, np.float32)[::stride, ::stride])
    v, u = np.mgrid[0 : depth.shape[0] : stride, 0 : depth.shape[1] : stride]
    pixels = jnp.asarray(np.stack([u.ravel(), v.ravel()], 1), jnp.float32)
    lengths, valid = jax.device_get(_blur_lengths(camera, pixels, d.ravel(), trajectory.about_middle()))
    lengths = lengths[valid]
    if lengths.size == 0:
        return 0.0, 0.0
    return float(lengths.mean()), float(np.percentile(lengths, 95))


_blur_lengths = jax.jit(blur_lengths)


def choose_deblur_n(depth, camera: PinholeCamera, trajectory: ExposurePath, config: DeblurConfig = DeblurConfig(),
                    readout: float = 0.0) -> int:
    """``config.n`` if positive, else one virtual frame per pixel of the frame's 95th-percentile blur
    (gaps between virtual frames make the deconvolution ring), in [n_min, n_max]: a power of two,
    or above ``n_step`` a multiple of it (``blur.round_up_frames``)."""
    if config.n > 0:
        return config.n
    return round_up_frames(exposure_blur_px(depth, camera, trajectory, readout=readout)[1], config.n_min, config.n_max,
                           config.n_step)


def _grad_ops(x):
    gx = x[:, 1:] - x[:, :-1]
    gy = x[1:, :] - x[:-1, :]
    return gx, gy


class SamplingTable(eqx.Module):
    """The blur operator A of one frame (Eq. 6 with every transfer done once): for virtual frame i
    and pixel p (flattened), the flat index of the top-left pixel of the bilinear cell its sample
    falls in (``corner``) and the position inside that cell (``frac``: fu, fv in units of
    1/``FRACTION_ONE``: uint16 halves the memory and decodes faster than float16); ``valid``
    marks the pixels whose n samples all land in the image (``blur.synthesize``'s rule)."""

    corner: Int[Array, "n P"]
    frac: UInt16[Array, "n P 2"]
    valid: Bool[Array, "H W"]


def _pose_table(traj: ExposurePath, n: int, h: int, readout, rolling: bool) -> Float[Array, "B n 7"]:
    """The virtual poses [t, q̄] per row bucket: one bucket for the global shutter, one per image
    row with a rolling shutter (``render_blurry``'s table)."""
    if not rolling:
        return virtual_pq(traj, n)[None]
    return virtual_pq_table(traj, row_times(n, jnp.arange(h, dtype=traj.start.q.dtype), h, readout))


TABLE_MAX_PIXELS = 2**31 - 1  # the table solver's limit: int32 flat indices (:func:`deblur` falls back to the render solver above it)
COARSE_MIN_SIZE = 16  # smaller images are solved at full resolution only (coarse_to_fine ignored)


def sampling_table(planes: Float[Array, "H W"], camera: PinholeCamera, traj: ExposurePath, n: int, readout,
                   rolling: bool) -> SamplingTable:
    """The :class:`SamplingTable` of a frame with plane depths ``planes`` (NaN: none) along ``traj``
    (its own mid pose the reference), one virtual frame at a time: ``blur.virtual_sample``'s plane
    point and validity, and its cell (``image.cell_position``)."""
    h, w = planes.shape
    if h * w >= TABLE_MAX_PIXELS:
        raise ValueError(f"the table solver takes images below 2^31 pixels, got {w}x{h} (deblur.solver = render has no limit)")
    d = planes.ravel()
    d_ok = jnp.isfinite(d) & (d > 0)
    v, u = jnp.meshgrid(jnp.arange(h, dtype=planes.dtype), jnp.arange(w, dtype=planes.dtype), indexing="ij")
    rays = jax.vmap(camera.unit_ray)(jnp.stack([u.ravel(), v.ravel()], -1))
    depths = jnp.where(d_ok, d, 1.0)
    pqs = _pose_table(traj, n, h, readout, rolling)

    def pixel(pq, ray, depth):  # the sample's value is not used: its gathers are dead code under jit
        _, _, p_ref, ok = virtual_sample(planes, camera, pq, ray, depth)
        _, u0, v0, fu, fv = cell_position(camera.project(p_ref), h, w)
        return v0 * w + u0, jnp.round(jnp.stack([fu, fv]) * FRACTION_ONE).astype(jnp.uint16), ok

    def frame(pq_rows):  # (B, 7): this virtual frame's pose per row bucket; each pose's rotation built once
        if pq_rows.shape[0] == 1:
            return jax.vmap(pixel, in_axes=(None, 0, 0))(pq_rows[0], rays, depths)
        per_row = jax.vmap(jax.vmap(pixel, in_axes=(None, 0, 0)))(pq_rows, rays.reshape(h, w, 3), depths.reshape(h, w))
        return jax.tree.map(lambda a: a.reshape(h * w, *a.shape[2:]), per_row)

    corner, frac, ok = jax.lax.map(frame, jnp.swapaxes(pqs, 0, 1))
    return SamplingTable(corner, frac, (jnp.all(ok, axis=0) & d_ok).reshape(h, w))


def _fractions(frac: UInt16[Array, "P 2"], dtype) -> tuple[Float[Array, " P"], Float[Array, " P"]]:
    """(fu, fv) of a table's stored fractions."""
    scaled = frac.astype(dtype) * (1.0 / FRACTION_ONE)
    return scaled[:, 0], scaled[:, 1]


def table_blur(table: SamplingTable, x: Float[Array, "H W"]) -> Float[Array, "H W"]:
    """A x: the mean over virtual frames of the bilinear samples the table points at (one gather of
    a pixel's four cell corners per sample); invalid pixels are 0."""
    h, w = x.shape
    p = h * w
    flat = jnp.pad(x.ravel(), (0, w + 1))
    cells = jnp.stack([flat[:p], flat[1 : p + 1], flat[w : p + w], flat[w + 1 : p + w + 1]], axis=-1)

    def add(acc, sample):
        corner, frac = sample
        c = cells.at[corner].get(mode="promise_in_bounds")
        return acc + lerp_cell(*_fractions(frac, x.dtype), (c[:, 0], c[:, 1], c[:, 2], c[:, 3]))[0], None

    total, _ = jax.lax.scan(add, jnp.zeros(p, x.dtype), (table.corner, table.frac))
    return jnp.where(table.valid, total.reshape(h, w) / table.corner.shape[0], 0.0)


def table_blur_adjoint(table: SamplingTable, y: Float[Array, "H W"]) -> Float[Array, "H W"]:
    """Aᵀ y (the transpose of :func:`table_blur`): each valid pixel's value, over n, splatted onto
    its samples' four cell corners with their bilinear weights (one scatter-add per virtual frame)."""
    h, w = y.shape
    p = h * w
    share = jnp.where(table.valid, y, 0.0).ravel() / table.corner.shape[0]

    def add(acc, sample):
        corner, frac = sample
        fu, fv = _fractions(frac, y.dtype)
        weights = jnp.stack([(1 - fu) * (1 - fv), fu * (1 - fv), (1 - fu) * fv, fu * fv], axis=-1)
        return acc.at[corner].add(weights * share[:, None], mode="promise_in_bounds"), None

    cells, _ = jax.lax.scan(add, jnp.zeros((p, 4), y.dtype), (table.corner, table.frac))
    flat = jnp.pad(cells, ((w + 1, 0), (0, 0)))  # corner k of cell q is pixel q + (0, 1, w, w + 1)[k]
    total = flat[w + 1 :, 0] + flat[w : p + w, 1] + flat[1 : p + 1, 2] + flat[: p, 3]
    return total.reshape(h, w)


def _cg(op, r, x, iterations: int, tolerance=0.0):
    """Conjugate-gradient steps on op(x) = rhs (op symmetric positive) from x, given the residual
    r = rhs − op(x) there: ``iterations`` of them, fewer once the residual is below ``tolerance``
    times the first one. Returns (x, steps)."""
    rs0 = jnp.sum(r * r)

    def cond(state):
        i, _, _, _, rs = state
        return (i < iterations) & (rs > tolerance * tolerance * rs0)

    def body(state):
        i, x, r, p, rs = state
        Ap = op(p)
        alpha = rs / jnp.maximum(jnp.sum(p * Ap), 1e-20)
        x = x + alpha * p
        r = r - alpha * Ap
        rs_new = jnp.sum(r * r)
        p = r + (rs_new / jnp.maximum(rs, 1e-30)) * p
        return i + 1, x, r, p, rs_new

    i, x, *_ = jax.lax.while_loop(cond, body, (jnp.int32(0), x, r, r, rs0))
    return x, i


class BlurOperator(eqx.Module):
    """A frame's blur operator for the solve: A (``blur``), Aᵀ (``adjoint``), the pixels whose
    samples all land in the image (``valid``) and the pixels some valid pixel's samples touch
    (``seen``: the unknowns; the others keep the blurry value)."""

    blur: Callable
    adjoint: Callable
    valid: Bool[Array, "H W"]
    seen: Bool[Array, "H W"]


def _solve(op: BlurOperator, blurry: Float[Array, "H W"], x0: Float[Array, "H W"], lam, iterations: int, tolerance=0.0):
    """min ‖A x − b‖² + λ‖∇x‖² over the valid pixels of b by CG on the normal equations from x0
    (:func:`_cg`), the unseen pixels held at b. Returns (x, CG steps)."""
    reg = jax.grad(lambda z: 0.5 * sum(jnp.sum(g * g) for g in _grad_ops(z)))
    normal = lambda x: jnp.where(op.seen, op.adjoint(jnp.where(op.valid, op.blur(x), 0.0)) + lam * reg(x), x)
    x0 = jnp.where(op.seen, x0, blurry)
    r0 = op.adjoint(jnp.where(op.valid, blurry - op.blur(x0), 0.0)) - lam * reg(x0)  # Aᵀ(b − A x0) − λ∇ᵀ∇x0: one adjoint
    return _cg(normal, jnp.where(op.seen, r0, 0.0), x0, iterations, tolerance)


def _render_operator(planes, camera, traj, n: int, readout, rolling: bool) -> BlurOperator:
    """The reference form of A (``render_blurry``, every transfer redone at every application), Aᵀ
    (its ``jax.linear_transpose``); seen: Aᵀ of the valid mask is positive."""
    blur = lambda x: render_blurry(x, planes, camera, traj, n, readout)[0]
    adjoint = lambda y: jax.linear_transpose(blur, planes)(y)[0]
    valid = render_blurry(jnp.ones_like(planes), planes, camera, traj, n, readout)[1]
    return BlurOperator(blur, adjoint, valid, adjoint(valid.astype(planes.dtype)) > 1e-6)


def table_seen(table: SamplingTable) -> Bool[Array, "H W"]:
    """The pixels that are a corner of a bilinear cell some valid pixel's sample falls in (one
    uint8 scatter-max per virtual frame, not a float scatter-add as Aᵀ of the valid mask)."""
    h, w = table.valid.shape
    p = h * w
    mark = table.valid.ravel().astype(jnp.uint8)
    hit, _ = jax.lax.scan(lambda acc, corner: (acc.at[corner].max(mark, mode="promise_in_bounds"), None),
                          jnp.zeros(p, jnp.uint8), table.corner)
    flat = jnp.pad(hit, (w + 1, 0))  # pixel q is corner k of the cells q - (0, 1, w, w + 1)[k]
    return ((flat[w + 1 :] | flat[w : p + w] | flat[1 : p + 1] | flat[:p]) > 0).reshape(h, w)


def _table_operator(planes, camera, traj, n: int, readout, rolling: bool) -> BlurOperator:
    """A and Aᵀ from a :class:`SamplingTable` built once (:func:`table_blur`,
    :func:`table_blur_adjoint`), the valid pixels and :func:`table_seen`."""
    table = sampling_table(planes, camera, traj, n, readout, rolling)
    return BlurOperator(partial(table_blur, table), partial(table_blur_adjoint, table), table.valid, table_seen(table))


def _upsample(x: Float[Array, "h w"], shape: tuple[int, int]) -> Float[Array, "H W"]:
    """Bilinear upsampling by two (``image.downsample``'s pixel centres), an odd last row or column
    copied from its neighbour."""
    h, w = x.shape
    up = jax.image.resize(x, (2 * h, 2 * w), "linear")
    return jnp.pad(up, ((0, shape[0] - 2 * h), (0, shape[1] - 2 * w)), mode="edge")


@partial(jax.jit, static_argnames=("solver", "n", "iterations", "rolling", "coarse_n", "fine_iterations"))
def _deblur(blurry, planes, camera, traj, lam, readout, tolerance, *, solver: str, n: int, iterations: int,
            rolling: bool, coarse_n: int, fine_iterations: int):
    """The solve of :func:`deblur` in linear radiance with operator form ``solver``. With
    ``coarse_n`` > 0, first at half resolution (box-averaged image, every other plane depth, that
    many virtual frames), upsampled as the start of ``fine_iterations`` full-resolution CG steps.
    Returns (image, full-resolution CG steps)."""
    operator = _render_operator if solver == "render" else _table_operator
    readout = readout if rolling else 0.0  # a concrete 0: the global shutter's one-row program
    x0 = blurry
    if coarse_n:
        small = downsample(blurry)
        h, w = small.shape
        coarse = operator(planes[: 2 * h : 2, : 2 * w : 2], camera.scaled(1), traj, coarse_n, readout, rolling)
        x0 = _upsample(jnp.clip(_solve(coarse, small, small, lam, iterations, tolerance)[0], 0.0, 1.0), blurry.shape)
        iterations, tolerance = fine_iterations, 0.0
    x, steps = _solve(operator(planes, camera, traj, n, readout, rolling), blurry, x0, lam, iterations, tolerance)
    return jnp.clip(x, 0.0, 1.0), steps


def deblur(blurry, depth, camera: PinholeCamera, trajectory: ExposurePath, config: DeblurConfig = DeblurConfig(),
           response_gamma: float = 1.0, readout: float = 0.0) -> np.ndarray:
    """Sharp mid-exposure image of a blurry frame, given its depth (metres, NaN = none) and its
    exposure path (any reference frame: it is re-expressed about its own mid pose; with a rolling
    shutter of readout fraction ``readout`` the path spans the whole frame time and the image is
    the global-shutter one at its middle). Works in linear radiance (``response_gamma``) and
    returns display intensities in [0, 1]. ``config.solver`` picks the operator (module docstring);
    ``config.coarse_to_fine`` solves at half resolution first."""
    n = choose_deblur_n(depth, camera, trajectory, config, readout)
    planes = plane_depths_from_keyframe(jnp.asarray(np.asarray(depth, np.float32)), camera, Pose.identity())
    huge = blurry.shape[0] * blurry.shape[1] >= TABLE_MAX_PIXELS  # the table's int32 flat indices would overflow
    coarse = config.coarse_to_fine and min(blurry.shape) >= COARSE_MIN_SIZE
    x, _ = _deblur(jnp.asarray(linearize(blurry, response_gamma)), planes, camera, trajectory.about_middle(),
                   jnp.float32(config.regularization), jnp.float32(readout), jnp.float32(config.tolerance),
                   solver="render" if huge else config.solver, n=n, iterations=config.iterations, rolling=readout > 0,
                   coarse_n=max(n // 2, 1) if coarse else 0, fine_iterations=config.fine_iterations)
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
