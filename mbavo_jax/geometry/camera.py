"""Pinhole camera: projection π (Eq. 85's model) and unit back-projection π⁻¹ (Eq. 62)."""

from __future__ import annotations

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["PinholeCamera", "principal_point_problem"]


def principal_point_problem(cx: float, cy: float, width: int, height: int) -> str:
    """What is wrong with a principal point outside the image (pixel centres 0 .. size-1), or ''."""
    for key, c, size, name in (("cx", cx, width, "width"), ("cy", cy, height, "height")):
        if not 0 <= c <= size - 1:
            return f"principal point {key} = {c:g} is outside the image (0 <= {key} <= {size - 1} for {name} {size})"
    return ""


class PinholeCamera(eqx.Module):
    """Intrinsics fx, fy, cx, cy (pixels, pixel centres at integer coordinates) and image size.

    ``width``/``height`` are static so that image shapes stay fixed under ``jit``.
    """

    fx: Float[Array, ""]
    fy: Float[Array, ""]
    cx: Float[Array, ""]
    cy: Float[Array, ""]
    width: int = eqx.field(static=True)
    height: int = eqx.field(static=True)

    @staticmethod
    def create(fx, fy, cx, cy, width: int, height: int, dtype=jnp.float32) -> "PinholeCamera":
        vals = [float(v) for v in (fx, fy, cx, cy)]
        if not all(jnp.isfinite(jnp.array(vals))):
            raise ValueError(f"camera intrinsics must be finite, got fx,fy,cx,cy={vals}")
        if vals[0] <= 0 or vals[1] <= 0:
            raise ValueError(f"focal lengths must be positive, got fx={vals[0]}, fy={vals[1]}")
        if int(width) <= 0 or int(height) <= 0:
            raise ValueError(f"image size must be positive, got {width}x{height}")
        problem = principal_point_problem(vals[2], vals[3], int(width), int(height))
        if problem:
            raise ValueError(problem)
        return PinholeCamera(*(jnp.asarray(v, dtype) for v in vals), int(width), int(height))

    def K(self) -> Float[Array, "3 3"]:
        z = jnp.zeros_like(self.fx)
        o = jnp.ones_like(self.fx)
        return jnp.array([[self.fx, z, self.cx], [z, self.fy, self.cy], [z, z, o]])

    def project(self, p: Float[Array, "3"]) -> Float[Array, "2"]:
        """π: x = [fx X/Z + cx, fy Y/Z + cy] (its Jacobian is Eq. 85)."""
        return jnp.array([self.fx * p[0] / p[2] + self.cx, self.fy * p[1] / p[2] + self.cy])

    def unit_ray(self, x: Float[Array, "2"]) -> Float[Array, "3"]:
        """Eq. 62: π⁻¹(x), the unit-length ray through pixel x."""
        ray = jnp.array([(x[0] - self.cx) / self.fx, (x[1] - self.cy) / self.fy, jnp.ones_like(self.fx)])
        return ray / jnp.linalg.norm(ray)

    def backproject(self, x: Float[Array, "2"], depth) -> Float[Array, "3"]:
        """The 3D point at z-depth ``depth`` through pixel x."""
        return jnp.array([(x[0] - self.cx) / self.fx, (x[1] - self.cy) / self.fy, 1.0]) * depth

    def in_image(self, x: Float[Array, "2"], border: float = 0.0):
        return (
            (x[0] >= border)
            & (x[1] >= border)
            & (x[0] <= self.width - 1 - border)
            & (x[1] <= self.height - 1 - border)
        )

    def as_dict(self) -> dict:
        """fx, fy, cx, cy (floats), width, height: camera.yaml's keys."""
        return {"fx": float(self.fx), "fy": float(self.fy), "cx": float(self.cx), "cy": float(self.cy),
                "width": self.width, "height": self.height}

    def scaled(self, level: int) -> "PinholeCamera":
        """The camera of pyramid level ``level`` (each level halves the image, pixel centres kept)."""
        f = 0.5**level
        w = max(1, self.width >> level)
        h = max(1, self.height >> level)
        return PinholeCamera(
            self.fx * f, self.fy * f, (self.cx + 0.5) * f - 0.5, (self.cy + 0.5) * f - 0.5, w, h
        )
