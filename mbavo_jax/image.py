"""Image sampling and pyramids: bilinear interpolation with validity masks, 2x2 pyramids."""

from __future__ import annotations

import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

__all__ = ["bilinear_cell", "bilinear", "bilinear_many", "downsample", "pyramid", "gradient_magnitude"]


def bilinear_cell(image: Float[Array, "H W"], x: Float[Array, "2"], border: float = 0.0):
    """The pixel cell around x = (col, row) (pixel centres at integers): ``(valid, fu, fv, corners)``
    with corners = (i00, i01, i10, i11) = image at (v0, u0), (v0, u0+1), (v0+1, u0), (v0+1, u0+1)
    and (fu, fv) the position inside the cell. Outside ``[border, size-1-border]`` valid is False and
    the cell is the top-left one (coordinates are replaced before use, so gradients stay finite)."""
    h, w = image.shape
    valid = (
        jnp.isfinite(x).all()
        & (x[0] >= border)
        & (x[1] >= border)
        & (x[0] <= w - 1 - border)
        & (x[1] <= h - 1 - border)
    )
    safe = jnp.where(valid, x, jnp.zeros_like(x))
    u = jnp.clip(safe[0], 0.0, w - 1.0)
    v = jnp.clip(safe[1], 0.0, h - 1.0)
    u0 = jnp.clip(jnp.floor(u), 0, w - 2).astype(jnp.int32)
    v0 = jnp.clip(jnp.floor(v), 0, h - 2).astype(jnp.int32)
    corners = (image[v0, u0], image[v0, u0 + 1], image[v0 + 1, u0], image[v0 + 1, u0 + 1])
    return valid, u - u0, v - v0, corners


def bilinear(image: Float[Array, "H W"], x: Float[Array, "2"], border: float = 0.0):
    """Bilinear sample of ``image`` at x = (col, row); pixel centres at integers.

    Returns ``(value, valid)``; outside ``[border, size-1-border]`` the sample is masked: valid is
    False and value is 0, with finite gradients (coordinates are clipped before use).
    """
    valid, fu, fv, (i00, i01, i10, i11) = bilinear_cell(image, x, border)
    top = i00 + fu * (i01 - i00)
    bottom = i10 + fu * (i11 - i10)
    value = top + fv * (bottom - top)
    return jnp.where(valid, value, jnp.zeros_like(value)), valid


def bilinear_many(image, xs: Float[Array, "N 2"], border: float = 0.0):
    return jax.vmap(lambda x: bilinear(image, x, border))(xs)


def downsample(image: Float[Array, "H W"]) -> Float[Array, "h w"]:
    """2x2 box average (pixel centre (i, j) of level l+1 sits at (2i+0.5, 2j+0.5) of level l)."""
    h, w = image.shape[0] // 2, image.shape[1] // 2
    im = image[: 2 * h, : 2 * w]
    return 0.25 * (im[0::2, 0::2] + im[1::2, 0::2] + im[0::2, 1::2] + im[1::2, 1::2])


def pyramid(image, levels: int) -> list:
    out = [jnp.asarray(image)]
    for _ in range(levels - 1):
        out.append(downsample(out[-1]))
    return out


def gradient_magnitude(image: Float[Array, "H W"]) -> Float[Array, "H W"]:
    """Central-difference gradient magnitude (zero on the one-pixel border)."""
    gx = jnp.zeros_like(image).at[:, 1:-1].set(0.5 * (image[:, 2:] - image[:, :-2]))
    gy = jnp.zeros_like(image).at[1:-1, :].set(0.5 * (image[2:, :] - image[:-2, :]))
    return jnp.sqrt(gx * gx + gy * gy)


