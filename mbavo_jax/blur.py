"""The image-formation model (main paper Eq. 6, supplement §4-5): one function for every user.

A blurry image is the mean of n virtual sharp images along the exposure trajectory. Each pixel x of
the blurry frame, with unit ray π⁻¹(x) and plane depth d, is transferred for each virtual pose
``T_ref_i`` through the frontal-parallel plane Z_ref = d into the sharp image and sampled bilinearly:

    v_i(x) = I_ref(π(T_ref_i · plane(x, d)))            (Eqs. 61-68, :func:`virtual_sample`)
    B(x)   = 1/n Σ_i v_i(x)                              (Eq. 6, :func:`synthesize`)

With a rolling shutter (readout fraction ρ > 0, ``geometry.trajectory.row_times``) the virtual
poses depend on the pixel's row: a pose table (rows x n, :func:`virtual_pq_table`) is interpolated
once and each pixel gathers its row's poses; a table of one row is the global shutter.

:func:`synthesize` is the model; the tracker's residuals, :func:`reblur` (sparse pixels),
:func:`render_blurry` (whole images, in pixel chunks so memory stays bounded), deblurring (its
linear operator) and the generator's blurring of real clips all call it.
"""

from __future__ import annotations

from functools import partial

import math

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from .geometry.camera import PinholeCamera
from .geometry.pose import Pose
from .geometry.spline import ExposurePath
from .geometry.trajectory import ExposureTrajectory, row_times, virtual_times
from .geometry.transfer import plane_point, plane_transfer
from .image import bilinear_with_gradient

__all__ = ["virtual_pq", "virtual_pq_table", "virtual_sample", "per_pixel_poses", "synthesize", "blend", "reblur", "render_blurry",
           "plane_depths_from_keyframe", "blur_segments", "blur_lengths", "round_up_frames"]

RENDER_CHUNK = 4096  # pixels per chunk of ``render_blurry`` (n x chunk samples live at once)


def virtual_pq(trajectory: ExposurePath, n: int) -> Float[Array, "n 7"]:
    """The n virtual poses T_ref_i (Eqs. 43-44) as rows [t (3), q̄ (4)]: the global shutter's table."""
    def one(s):
        p = trajectory.at(s)
        return jnp.concatenate([p.t, p.q])

    return jax.vmap(one)(virtual_times(n, trajectory.start.q.dtype))


def virtual_pq_table(trajectory: ExposurePath, times: Float[Array, "B n"]) -> Float[Array, "B n 7"]:
    """The virtual poses at normalised times ``times`` (one row per row bucket), rows [t, q̄]."""
    def one(s):
        p = trajectory.at(s)
        return jnp.concatenate([p.t, p.q])

    return jax.vmap(jax.vmap(one))(times)


def is_rolling(readout) -> bool:
    """Whether ``readout`` (ρ) needs the per-row model: False only for a concrete 0 (a traced ρ
    may be anything), so the global shutter keeps its one-row program."""
    return isinstance(readout, jax.core.Tracer) or float(readout) != 0.0


def virtual_sample(image: Float[Array, "H W"], camera: PinholeCamera, pq: Float[Array, "7"], ray: Float[Array, "3"], d, row0=None):
    """v_i for one pixel at virtual pose pq = [t, q̄]: ``(value, ∇I at the sample (2,), the plane
    point in the reference frame (3,), valid)``. Invalid samples (ray misses the plane, point behind
    the reference camera, outside the image) have value 0 and finite derivatives. ``row0``: the
    reference is rows ``row0 .. row0 + camera.height - 1`` of ``image`` (a stack of images)."""
    p_ref, _, ok = plane_point(pq[3:], pq[:3], ray, d)
    ok = ok & (p_ref[2] > 1e-6)
    safe = jnp.where(ok, p_ref, jnp.array([0.0, 0.0, 1.0], p_ref.dtype))
    x = camera.project(safe)
    if row0 is not None:
        ok = ok & (x[1] >= 0) & (x[1] <= camera.height - 1)
        x = x + jnp.stack([jnp.zeros_like(x[1]), jnp.asarray(row0, x.dtype)])
    value, grad, inside = bilinear_with_gradient(image, x)
    return value, grad, safe, ok & inside


def per_pixel_poses(sample, pqs: Float[Array, "B n 7"], rows: Int[Array, " R"], rays: Float[Array, "R 3"], depths: Float[Array, " R"]):
    """``sample(pq, ray, d)`` for each virtual frame i and pixel r at its row bucket's pose
    ``pqs[rows[r], i]``: outputs stacked (n, R, ...). One bucket (the global shutter) needs no gather."""
    if pqs.shape[0] == 1:
        return jax.vmap(lambda pq: jax.vmap(lambda ray, d: sample(pq, ray, d))(rays, depths))(pqs[0])
    return jax.vmap(lambda pq: jax.vmap(sample)(pq, rays, depths), in_axes=1)(pqs[rows])


def synthesize(
    image: Float[Array, "H W"], camera: PinholeCamera, pqs: Float[Array, "B n 7"], rays: Float[Array, "R 3"], depths: Float[Array, " R"],
    rows: Int[Array, " R"], row0=None,
) -> tuple[Float[Array, " R"], Bool[Array, " R"]]:
    """Eq. 6: blurry intensities at R pixels (unit rays, plane depths) from the sharp ``image`` and
    the pose table ``pqs`` (pixel r uses row bucket ``rows[r]``); a pixel is valid only if all n
    samples are (invalid pixels are 0). ``row0``: as in :func:`virtual_sample`."""
    sample = lambda pq, ray, d: virtual_sample(image, camera, pq, ray, d, row0)
    values, _, _, ok = per_pixel_poses(sample, pqs, rows, rays, depths)  # (n, R)
    return blend(values, ok)


def blend(values: Float[Array, "n R"], ok: Bool[Array, "n R"]) -> tuple[Float[Array, " R"], Bool[Array, " R"]]:
    """Eq. 6 from the n virtual samples of each pixel: their mean, valid only if all n samples are
    (invalid pixels are 0)."""
    valid = jnp.all(ok, axis=0)
    return jnp.where(valid, jnp.mean(values, axis=0), 0.0), valid


def reblur(
    keyframe: Float[Array, "H W"],
    camera: PinholeCamera,
    trajectory: ExposurePath,
    pixels: Float[Array, "P 2"],
    depths: Float[Array, " P"],
    n: int,
    readout=0.0,
) -> tuple[Float[Array, " P"], Bool[Array, " P"]]:
    """:func:`synthesize` at ``pixels`` of the current frame with plane depths ``depths`` (Z in the
    keyframe) along ``trajectory`` with n virtual frames; ``readout`` is ρ (each pixel's own row
    times, continuous rows allowed)."""
    return _reblur(keyframe, camera, trajectory, pixels, depths, jnp.asarray(readout, pixels.dtype), n, is_rolling(readout))


@partial(jax.jit, static_argnames=("n", "rolling"))
def _reblur(keyframe, camera: PinholeCamera, trajectory, pixels, depths, readout, n: int, rolling: bool):
    rays = jax.vmap(camera.unit_ray)(pixels)
    if not rolling:
        return synthesize(keyframe, camera, virtual_pq(trajectory, n)[None], rays, depths, jnp.zeros(pixels.shape[0], jnp.int32))
    times = row_times(n, pixels[:, 1], camera.height, readout)
    rows = jnp.arange(pixels.shape[0], dtype=jnp.int32)
    return synthesize(keyframe, camera, virtual_pq_table(trajectory, times), rays, depths, rows)


def _pixel_grid(width: int, height: int, dtype):
    u, v = jnp.meshgrid(jnp.arange(width, dtype=dtype), jnp.arange(height, dtype=dtype))
    return jnp.stack([u.ravel(), v.ravel()], axis=-1)


@partial(jax.jit, static_argnames=("iterations",))
def plane_depths_from_keyframe(
    keyframe_depth: Float[Array, "H W"], camera: PinholeCamera, T_ref_cur: Pose, iterations: int = 3
) -> Float[Array, "H W"]:
    """Per-pixel plane depths for the current frame's pixel grid from the keyframe's depth map.

    Fixed-point iteration: start from d = D_ref(x), transfer x through the plane at d with
    ``T_ref_cur`` and read D_ref (nearest valid) there. Pixels without depth get NaN.
    """
    h, w = keyframe_depth.shape
    grid = _pixel_grid(w, h, keyframe_depth.dtype)
    depth_ok = jnp.where(jnp.isfinite(keyframe_depth) & (keyframe_depth > 0), keyframe_depth, 0.0)

    def lookup(x):
        col = jnp.clip(jnp.round(x[0]), 0, w - 1).astype(jnp.int32)
        row = jnp.clip(jnp.round(x[1]), 0, h - 1).astype(jnp.int32)
        inside = (x[0] > -0.5) & (x[1] > -0.5) & (x[0] < w - 0.5) & (x[1] < h - 0.5)
        return jnp.where(inside, depth_ok[row, col], 0.0)

    def step(d, _):
        def one(x, di):
            safe_d = jnp.where(di > 0, di, 1.0)
            x_ref, ok = plane_transfer(T_ref_cur, camera, x, safe_d)
            new = lookup(x_ref)
            return jnp.where(ok & (new > 0), new, di)

        return jax.vmap(one)(grid, d), None

    d0 = depth_ok.ravel()
    d, _ = jax.lax.scan(step, d0, None, length=iterations)
    return jnp.where(d > 0, d, jnp.nan).reshape(h, w)


def render_blurry(
    keyframe: Float[Array, "H W"],
    plane_depths: Float[Array, "H W"],
    camera: PinholeCamera,
    trajectory: ExposurePath,
    n: int,
    readout=0.0,
) -> tuple[Float[Array, "H W"], Bool[Array, "H W"]]:
    """A whole blurry image of the current frame (same size as the keyframe): :func:`synthesize` on
    every pixel, in chunks of ``RENDER_CHUNK`` pixels, each row at its own times (``readout``: ρ).
    ``plane_depths`` holds d per pixel (e.g. from :func:`plane_depths_from_keyframe`); NaN or
    non-positive depth marks a pixel invalid. Returns the image and its validity mask; invalid
    pixels are 0."""
    return _render_blurry(keyframe, plane_depths, camera, trajectory, jnp.asarray(readout, keyframe.dtype), n, is_rolling(readout))


@partial(jax.jit, static_argnames=("n", "rolling"))
def _render_blurry(keyframe, plane_depths, camera: PinholeCamera, trajectory, readout, n: int, rolling: bool):
    h, w = keyframe.shape
    d = plane_depths.ravel()
    d_ok = jnp.isfinite(d) & (d > 0)
    grid = _pixel_grid(w, h, keyframe.dtype)
    rays = jax.vmap(camera.unit_ray)(grid)
    if rolling:
        pqs = virtual_pq_table(trajectory, row_times(n, jnp.arange(h, dtype=keyframe.dtype), h, readout))
        rows = grid[:, 1].astype(jnp.int32)
    else:
        pqs, rows = virtual_pq(trajectory, n)[None], jnp.zeros(h * w, jnp.int32)
    pad = (-h * w) % RENDER_CHUNK
    rays = jnp.pad(rays, ((0, pad), (0, 0)), constant_values=1.0).reshape(-1, RENDER_CHUNK, 3)
    depths = jnp.pad(jnp.where(d_ok, d, 1.0), (0, pad), constant_values=1.0).reshape(-1, RENDER_CHUNK)
    rows = jnp.pad(rows, (0, pad)).reshape(-1, RENDER_CHUNK)
    values, valid = jax.lax.map(lambda rdv: synthesize(keyframe, camera, pqs, *rdv), (rays, depths, rows))
    values, valid = values.ravel()[: h * w], valid.ravel()[: h * w] & d_ok
    return jnp.where(valid, values, 0.0).reshape(h, w), valid.reshape(h, w)


def blur_segments(
    camera: PinholeCamera, pixels: Float[Array, "N 2"], depths: Float[Array, " N"], trajectory: ExposureTrajectory
) -> tuple[Float[Array, "N 2"], Bool[Array, " N"]]:
    """Blur kernel of each point as a segment (pixels): its projection at the exposure's end minus
    that at the start, for points at ``pixels``/``depths`` of the trajectory's reference frame.
    Returns (segments, valid); invalid (no depth, behind a camera) segments are 0, never NaN."""
    ok_d = jnp.isfinite(depths) & (depths > 0)
    P = jax.vmap(camera.backproject)(pixels, jnp.where(ok_d, depths, 1.0))

    def at(T: Pose):
        X = jax.vmap(T.inverse().apply)(P)
        front = X[:, 2] > 1e-6
        return jax.vmap(camera.project)(jnp.where(front[:, None], X, jnp.array([0.0, 0.0, 1.0]))), front

    xs, fs = at(trajectory.start)
    xe, fe = at(trajectory.end)
    valid = ok_d & fs & fe
    return jnp.where(valid[:, None], xe - xs, 0.0), valid


def blur_lengths(
    camera: PinholeCamera, pixels: Float[Array, "N 2"], depths: Float[Array, " N"], trajectory: ExposureTrajectory
) -> tuple[Float[Array, " N"], Bool[Array, " N"]]:
    """Blur length of each point (pixels): the length of its :func:`blur_segments` segment.
    Returns (lengths, valid); invalid lengths are 0, never NaN, and so is the gradient of a zero
    length (a double ``where`` around the square root)."""
    segments, valid = blur_segments(camera, pixels, depths, trajectory)
    sq = jnp.sum(segments * segments, axis=1)
    moved = valid & (sq > 0)
    return jnp.where(moved, jnp.sqrt(jnp.where(moved, sq, 1.0)), 0.0), valid


def round_up_frames(need: float, lo: int, hi: int, step: int = 0) -> int:
    """Virtual frames for ``need`` samples: the next power of two at or above max(need, lo), or,
    where that power exceeds ``step`` (> 0), the next multiple of ``step``; at most ``hi``. Few
    distinct values keep the compiled programs few."""
    need = max(lo, math.ceil(max(need, 0.0)))
    n = 2 ** math.ceil(math.log2(need))
    if step > 0 and n > step:
        n = step * math.ceil(need / step)
    return int(min(hi, n))
