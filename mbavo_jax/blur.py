"""Blur image formation (main paper Eq. 6, supplement §4-5).

A blurry image is the mean of n virtual sharp images along the exposure trajectory. Each pixel x of
the blurry frame is transferred, for each virtual pose ``T_ref_i``, through the frontal-parallel
plane Z_ref = d into the sharp keyframe and sampled bilinearly:

    B(x) = 1/n Σ_i I_ref(π(T_ref_i · plane(x, d)))

``reblur`` is the sparse form used by the tracker (vmapped over virtual poses and pixels, n
static). ``render_blurry`` renders a whole image (scan over virtual poses, so memory stays O(H·W)).
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .geometry.camera import PinholeCamera
from .geometry.pose import Pose
from .geometry.trajectory import ExposureTrajectory, virtual_poses
from .geometry.transfer import plane_transfer
from .image import bilinear

__all__ = ["reblur", "render_blurry", "sample_through_plane", "plane_depths_from_keyframe", "blur_lengths"]


def sample_through_plane(keyframe, camera: PinholeCamera, T_ref_i: Pose, x, d):
    """One virtual sample: I_ref at the transfer of pixel x through the plane at depth d."""
    x_ref, ok = plane_transfer(T_ref_i, camera, x, d)
    value, inside = bilinear(keyframe, x_ref)
    valid = ok & inside
    return jnp.where(valid, value, 0.0), valid


@partial(jax.jit, static_argnames=("n",))
def reblur(
    keyframe: Float[Array, "H W"],
    camera: PinholeCamera,
    trajectory: ExposureTrajectory,
    pixels: Float[Array, "P 2"],
    depths: Float[Array, "P"],
    n: int,
) -> tuple[Float[Array, "P"], Bool[Array, "P"]]:
    """Synthesise blurry intensities at ``pixels`` of the current frame (Eq. 6 of the paper).

    ``depths`` are the plane depths d (Z in the keyframe). A pixel is valid only if all n samples
    are valid; invalid pixels return 0 (never NaN).
    """
    poses = virtual_poses(trajectory, n)
    per_pose = jax.vmap(lambda T: jax.vmap(lambda x, d: sample_through_plane(keyframe, camera, T, x, d))(pixels, depths))
    values, valid = per_pose(poses)  # (n, P)
    all_valid = jnp.all(valid, axis=0)
    return jnp.where(all_valid, jnp.mean(values, axis=0), 0.0), all_valid


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


@partial(jax.jit, static_argnames=("n",))
def render_blurry(
    keyframe: Float[Array, "H W"],
    plane_depths: Float[Array, "H W"],
    camera: PinholeCamera,
    trajectory: ExposureTrajectory,
    n: int,
) -> tuple[Float[Array, "H W"], Bool[Array, "H W"]]:
    """Render a whole blurry image of the current frame (same size as the keyframe).

    ``plane_depths`` holds d for every pixel of the current frame (e.g. from
    ``plane_depths_from_keyframe``); NaN or non-positive depth marks a pixel invalid. Returns the
    image and a validity mask (every virtual sample inside the keyframe); invalid pixels are 0.
    """
    h, w = keyframe.shape
    grid = _pixel_grid(w, h, keyframe.dtype)
    d = plane_depths.ravel()
    d_ok = jnp.isfinite(d) & (d > 0)
    d_safe = jnp.where(d_ok, d, 1.0)
    poses = virtual_poses(trajectory, n)

    def accumulate(carry, T):
        total, valid = carry
        vals, ok = jax.vmap(lambda x, di: sample_through_plane(keyframe, camera, T, x, di))(grid, d_safe)
        return (total + vals, valid & ok), None

    init = (jnp.zeros(h * w, keyframe.dtype), d_ok)
    (total, valid), _ = jax.lax.scan(accumulate, init, poses)
    image = jnp.where(valid, total / n, 0.0)
    return image.reshape(h, w), valid.reshape(h, w)


def blur_lengths(
    camera: PinholeCamera, pixels: Float[Array, "N 2"], depths: Float[Array, " N"], trajectory: ExposureTrajectory
) -> tuple[Float[Array, " N"], Bool[Array, " N"]]:
    """Blur length of each point (pixels): the distance between its projections at the exposure's
    start and end, for points at ``pixels``/``depths`` of the trajectory's reference frame. Returns
    (lengths, valid); invalid (no depth, behind a camera) lengths are 0, never NaN."""
    ok_d = jnp.isfinite(depths) & (depths > 0)
    P = jax.vmap(camera.backproject)(pixels, jnp.where(ok_d, depths, 1.0))

    def at(T: Pose):
        X = jax.vmap(T.inverse().apply)(P)
        front = X[:, 2] > 1e-6
        return jax.vmap(camera.project)(jnp.where(front[:, None], X, jnp.array([0.0, 0.0, 1.0]))), front

    xs, fs = at(trajectory.start)
    xe, fe = at(trajectory.end)
    valid = ok_d & fs & fe
    return jnp.where(valid, jnp.linalg.norm(xs - xe, axis=1), 0.0), valid
