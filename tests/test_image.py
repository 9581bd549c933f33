"""The one bilinear sampler's cell rule: what is valid, where the cell is, finite gradients."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from mbavo_jax.image import bilinear, cell_position


def test_cell_position_marks_nan_infinite_and_outside_points_invalid():
    h, w = 6, 8
    points = {
        (2.25, 3.5): (True, 2, 3, 0.25, 0.5),
        (0.0, 0.0): (True, 0, 0, 0.0, 0.0),
        (7.0, 5.0): (True, 6, 4, 1.0, 1.0),  # the last pixel: the last cell, at its far corner
        (-0.01, 2.0): (False, 0, 0, 0.0, 0.0),
        (7.01, 2.0): (False, 0, 0, 0.0, 0.0),
        (3.0, 5.5): (False, 0, 0, 0.0, 0.0),
        (np.nan, 2.0): (False, 0, 0, 0.0, 0.0),
        (2.0, np.nan): (False, 0, 0, 0.0, 0.0),
        (np.inf, 2.0): (False, 0, 0, 0.0, 0.0),
        (2.0, -np.inf): (False, 0, 0, 0.0, 0.0),
    }
    for x, want in points.items():
        got = cell_position(jnp.asarray(x, jnp.float32), h, w)
        assert bool(got[0]) == want[0], x
        assert (int(got[1]), int(got[2])) == want[1:3], x
        np.testing.assert_allclose([float(got[3]), float(got[4])], want[3:], atol=1e-6, err_msg=str(x))
    for x, want in {(1.5, 2.0): False, (2.0, 2.0): True, (5.0, 3.0): True, (5.01, 3.0): False, (5.0, 3.01): False}.items():
        valid, *_ = cell_position(jnp.asarray(x, jnp.float32), h, w, border=2.0)  # valid: [2, w - 3] x [2, h - 3]
        assert bool(valid) == want, x


def test_bilinear_gradient_is_finite_at_invalid_points():
    image = jnp.arange(48, dtype=jnp.float32).reshape(6, 8) / 48
    for x in ([np.nan, 1.0], [np.inf, 1.0], [-3.0, 1.0], [2.5, 1.5]):
        g = jax.grad(lambda p: bilinear(image, p)[0])(jnp.asarray(x, jnp.float32))
        assert np.all(np.isfinite(np.asarray(g))), x
    g = jax.grad(lambda p: bilinear(image, p)[0])(jnp.asarray([2.5, 1.5], jnp.float32))
    np.testing.assert_allclose(np.asarray(g), [1 / 48, 8 / 48], rtol=1e-5)
