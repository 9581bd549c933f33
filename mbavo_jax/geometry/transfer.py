"""Pixel transfer through a frontal-parallel plane (supplement §5, Eqs. 61-68).

A pixel x of virtual frame i is cast along its unit ray, intersected with the plane Z_ref = d of
the reference (keyframe) camera, and projected into the reference image.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from . import quaternion as quat
from .camera import PinholeCamera
from .pose import Pose

__all__ = ["plane_point", "plane_transfer"]


def plane_point(q: Float[Array, "4"], p: Float[Array, "3"], ray: Float[Array, "3"], d):
    """Eqs. 61-67: the plane intersection in the reference frame and its validity.

    ``(q, p)`` is ``T_ref_i`` (the virtual camera in the reference frame), ``ray`` is π⁻¹(x) of
    Eq. 62 and ``d`` the plane depth. Returns ``(p'_3d, lam, valid)`` where ``lam`` is λ of Eq. 64
    and ``valid`` says that the ray meets the plane in front of the virtual camera (λ > 0,
    d − p_z > 0). Invalid rays get a finite, unused point (the double-``where`` trick).
    """
    x, y, z = ray
    qx, qy, qz, qw = q
    lam = 2 * x * (qx * qz - qw * qy) + 2 * y * (qx * qw + qy * qz) + z * (qw * qw - qx * qx - qy * qy + qz * qz)  # Eq. 64
    d_prime = d - p[2]  # Eq. 61
    eps = 1e-6 if lam.dtype == jnp.float32 else 1e-12
    valid = (lam > eps) & (d_prime > 0)
    safe_lam = jnp.where(valid, lam, jnp.ones_like(lam))
    length = d_prime / safe_lam  # Eq. 65
    p3d = length * ray  # Eq. 66
    p_ref = quat.rotate(q, p3d) + p  # Eq. 67
    return p_ref, lam, valid


def plane_transfer(
    T_ref_i: Pose, camera: PinholeCamera, x: Float[Array, "2"], d
) -> tuple[Float[Array, "2"], Bool[Array, ""]]:
    """Eqs. 61-68: pixel x of virtual frame i → pixel of the reference image, with validity.

    Valid means: the ray hits the plane in front of the virtual camera and the plane point is in
    front of the reference camera. Projection into the image bounds is checked by the sampler.
    """
    p_ref, _, valid = plane_point(T_ref_i.q, T_ref_i.t, camera.unit_ray(x), d)
    valid = valid & (p_ref[2] > 0)
    safe_p = jnp.where(valid, p_ref, jnp.array([0.0, 0.0, 1.0], p_ref.dtype))
    return camera.project(safe_p), valid  # Eq. 68
