"""Reductions over masked arrays (fixed shapes: padding is masked, never removed)."""

from __future__ import annotations

import jax.numpy as jnp

__all__ = ["count", "masked_mean"]


def count(mask, dtype=jnp.float32, axis=None):
    """The number of True entries, at least 1, as ``dtype`` (safe to divide by)."""
    return jnp.maximum(mask.sum(axis), 1).astype(dtype)


def masked_mean(values, mask, axis=None):
    """The mean of ``values`` where ``mask`` is True (0 where nothing is)."""
    return jnp.sum(jnp.where(mask, values, 0.0), axis) / count(mask, values.dtype, axis)
