"""Images: bilinear sampling with validity masks (the one sampler of the project), 2x2 pyramids and
the photometric calibration (display intensities <-> linear radiance)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float

__all__ = ["to_uint16", "from_uint16", "quantize16", "bilinear_cell", "lerp_cell", "bilinear", "bilinear_with_gradient", "bilinear_wrapped", "downsample",
           "pyramid", "linearize", "delinearize"]


def cell_position(x: Float[Array, "2"], h: int, w: int, border: float = 0.0):
    """The bilinear cell of x = (col, row) in an h x w image (pixel centres at integers): ``(valid,
    u0, v0, fu, fv)``, the cell's top-left pixel (int32) and the position inside it. Outside
    ``[border, size-1-border]`` valid is False (NaN too: it fails every comparison) and the cell is
    the top-left one (coordinates are replaced before use, so gradients stay finite). Written per
    component, without a reduction over x, so that it fuses with the arithmetic around it."""
    valid = (x[0] >= border) & (x[1] >= border) & (x[0] <= w - 1 - border) & (x[1] <= h - 1 - border)
    u = jnp.clip(jnp.where(valid, x[0], 0.0), 0.0, w - 1.0)
    v = jnp.clip(jnp.where(valid, x[1], 0.0), 0.0, h - 1.0)
    fu0 = jnp.clip(jnp.floor(u), 0, w - 2)
    fv0 = jnp.clip(jnp.floor(v), 0, h - 2)
    return valid, fu0.astype(jnp.int32), fv0.astype(jnp.int32), u - fu0, v - fv0


def bilinear_cell(image: Float[Array, "H W"], x: Float[Array, "2"], border: float = 0.0):
    """The pixel cell around x (:func:`cell_position`): ``(valid, fu, fv, corners)`` with corners =
    (i00, i01, i10, i11) = image at (v0, u0), (v0, u0+1), (v0+1, u0), (v0+1, u0+1)."""
    valid, u0, v0, fu, fv = cell_position(x, *image.shape, border)
    corners = (image[v0, u0], image[v0, u0 + 1], image[v0 + 1, u0], image[v0 + 1, u0 + 1])
    return valid, fu, fv, corners


def lerp_cell(fu, fv, corners):
    """The bilinear interpolant inside a cell: ``(value, top, bottom)`` (rows v0 and v0+1 at fu)."""
    i00, i01, i10, i11 = corners
    top = i00 + fu * (i01 - i00)
    bottom = i10 + fu * (i11 - i10)
    return top + fv * (bottom - top), top, bottom


def bilinear(image: Float[Array, "H W"], x: Float[Array, "2"], border: float = 0.0):
    """Bilinear sample of ``image`` at x = (col, row); pixel centres at integers.

    Returns ``(value, valid)``; outside ``[border, size-1-border]`` the sample is masked: valid is
    False and value is 0, with finite gradients (coordinates are clipped before use).
    """
    valid, fu, fv, corners = bilinear_cell(image, x, border)
    value, _, _ = lerp_cell(fu, fv, corners)
    return jnp.where(valid, value, jnp.zeros_like(value)), valid


def bilinear_with_gradient(image: Float[Array, "H W"], x: Float[Array, "2"]):
    """Bilinear sample, its exact spatial derivative (the derivative of the interpolant), validity."""
    valid, fu, fv, (i00, i01, i10, i11) = bilinear_cell(image, x)
    value, top, bottom = lerp_cell(fu, fv, (i00, i01, i10, i11))
    du = (1 - fv) * (i01 - i00) + fv * (i11 - i10)
    dv = bottom - top
    zero = jnp.zeros_like(value)
    return jnp.where(valid, value, zero), jnp.where(valid, jnp.stack([du, dv]), jnp.zeros(2, value.dtype)), valid


def bilinear_wrapped(image: Float[Array, "S S"], u, v):
    """Bilinear sample of a periodic (tiling) image at (u, v), any real coordinates; vectorised."""
    s = image.shape[0]
    u, v = jnp.mod(u, s), jnp.mod(v, s)
    fu0, fv0 = jnp.floor(u), jnp.floor(v)
    u0, v0 = fu0.astype(jnp.int32), fv0.astype(jnp.int32)
    fu, fv = u - fu0, v - fv0
    u1, v1 = (u0 + 1) % s, (v0 + 1) % s
    u0, v0 = u0 % s, v0 % s
    return lerp_cell(fu, fv, (image[v0, u0], image[v0, u1], image[v1, u0], image[v1, u1]))[0]


def downsample(image: Float[Array, "H W"]) -> Float[Array, "h w"]:
    """2x2 box average (pixel centre (i, j) of level l+1 sits at (2i+0.5, 2j+0.5) of level l)."""
    h, w = image.shape[0] // 2, image.shape[1] // 2
    im = image[: 2 * h, : 2 * w]
    return 0.25 * (im[0::2, 0::2] + im[1::2, 0::2] + im[0::2, 1::2] + im[1::2, 1::2])


def pyramid(image: Float[Array, "H W"] | Float[np.ndarray, "H W"], levels: int) -> list:
    """``levels`` images, each the 2x2 box average of the one before (level 0 = ``image``)."""
    out = [jnp.asarray(image, jnp.float32)]
    for _ in range(levels - 1):
        out.append(downsample(out[-1]))
    return out


def linearize(image, gamma: float) -> np.ndarray:
    """Photometric calibration by an inverse gamma response: display I -> radiance clip(I, 0, 1)^γ."""
    image = np.clip(np.asarray(image, np.float32), 0.0, 1.0)
    return image if gamma == 1.0 else image ** np.float32(gamma)


def delinearize(radiance, gamma: float) -> np.ndarray:
    """The camera response: radiance -> display intensity r^(1/γ)."""
    radiance = np.asarray(radiance, np.float32)
    return radiance if gamma == 1.0 else radiance ** np.float32(1.0 / gamma)


def to_uint16(image) -> np.ndarray:
    """A [0, 1] image as 16-bit integers (how keyframe images are stored)."""
    return np.clip(np.round(np.asarray(image, np.float32) * 65535), 0, 65535).astype(np.uint16)


def from_uint16(image) -> np.ndarray:
    """16-bit integers as a float32 [0, 1] image."""
    return np.asarray(image, np.uint16).astype(np.float32) / np.float32(65535)


def quantize16(image) -> np.ndarray:
    """``image`` as it reads back from a 16-bit file: the odometry tracks against keyframe images
    as stored, so that a resumed run sees exactly what the interrupted one saw."""
    return from_uint16(to_uint16(image))
