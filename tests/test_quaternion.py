"""Quaternion maps of the supplement §3: values, round trips, Taylor branches, NaN-free gradients."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbavo_jax.geometry import quaternion as quat

vec3 = st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=3, max_size=3).map(np.array)


def _rotvec_to_quat_reference(r):
    """Independent reference: q = [sin(|r|/2) r/|r|, cos(|r|/2)]."""
    a = np.linalg.norm(r)
    if a == 0:
        return np.array([0, 0, 0, 1.0])
    return np.concatenate([np.sin(a / 2) * r / a, [np.cos(a / 2)]])


@settings(max_examples=40, deadline=None)
@given(vec3)
def test_exp_matches_axis_angle(r):
    with jax.enable_x64(True):
        np.testing.assert_allclose(quat.exp(jnp.asarray(r)), _rotvec_to_quat_reference(r), atol=1e-12)


@settings(max_examples=40, deadline=None)
@given(vec3)
def test_log_inverts_exp(r):
    if np.linalg.norm(r) >= np.pi - 1e-3:  # log returns the shortest rotation
        return
    with jax.enable_x64(True):
        np.testing.assert_allclose(quat.log(quat.exp(jnp.asarray(r))), r, atol=1e-9)


def test_log_of_negated_quaternion_is_same_rotation(x64, rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    r1, r2 = quat.log(jnp.asarray(q)), quat.log(jnp.asarray(-q))
    np.testing.assert_allclose(quat.to_matrix(quat.exp(r1)), quat.to_matrix(quat.exp(r2)), atol=1e-12)


def test_product_matches_matrix_product(x64, rng):
    for _ in range(5):
        a, b = (rng.normal(size=4) for _ in range(2))
        a, b = a / np.linalg.norm(a), b / np.linalg.norm(b)
        ab = quat.product(jnp.asarray(a), jnp.asarray(b))
        np.testing.assert_allclose(quat.to_matrix(ab), quat.to_matrix(jnp.asarray(a)) @ quat.to_matrix(jnp.asarray(b)), atol=1e-12)
        np.testing.assert_allclose(quat.Q_hat(jnp.asarray(b)) @ a, ab, atol=1e-12)  # Eq. 36


def test_inverse_and_matrix_round_trip(x64, rng):
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    np.testing.assert_allclose(quat.product(jnp.asarray(q), quat.inverse(jnp.asarray(q))), [0, 0, 0, 1], atol=1e-12)
    back = quat.from_matrix(quat.to_matrix(jnp.asarray(q)))
    np.testing.assert_allclose(back * np.sign(back[3]), q * np.sign(q[3]), atol=1e-12)


@pytest.mark.parametrize("theta", [1e-3, 5e-3, 9.9e-3, 1.01e-2, 0.02])
def test_exp_continuous_across_taylor_threshold_float32(theta):
    r = jnp.array([2 * theta, 0.0, 0.0], jnp.float32)
    np.testing.assert_allclose(quat.exp(r), _rotvec_to_quat_reference(np.array([2 * theta, 0, 0])), atol=2e-7)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize(
    "r", [np.zeros(3), np.array([1e-12, 0, 0]), np.array([1e-6, -2e-6, 3e-7]), np.array([0.3, -0.2, 0.1])]
)
def test_exp_gradients_finite(dtype, r):
    with jax.enable_x64(dtype == jnp.float64):
        r = jnp.asarray(r, dtype)
        assert np.all(np.isfinite(jax.jacfwd(quat.exp)(r)))
        assert np.all(np.isfinite(jax.grad(lambda x: quat.exp(x).sum())(r)))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize(
    "q",
    [
        [0.0, 0.0, 0.0, 1.0],  # θ = 0
        [1e-9, 0.0, 0.0, 1.0],  # tiny θ
        [0.0, 0.0, 0.0, -1.0],  # θ = 0, q_w < 0
        [0.6, 0.8, 0.0, 0.0],  # q_w = 0
        [0.6, 0.8, 0.0, 1e-9],  # q_w → 0+
        [0.6, 0.8, 0.0, -1e-9],  # q_w → 0-
        [0.1, -0.2, 0.3, 0.927],
    ],
)
def test_log_values_and_gradients_finite(dtype, q):
    with jax.enable_x64(dtype == jnp.float64):
        q = jnp.asarray(q, dtype)
        assert np.all(np.isfinite(quat.log(q)))
        assert np.all(np.isfinite(jax.jacfwd(quat.log)(q)))
        assert np.all(np.isfinite(jax.jacrev(quat.log)(q)))
        assert np.all(np.isfinite(jax.grad(lambda x: quat.log(x).sum())(q)))


def test_log_half_turn_branch_matches_exact_map(x64):
    """Near q_w = 0 the first-order branch agrees with 2 arctan(θ/q_w)/θ evaluated directly."""
    for qw in (1e-8, -1e-8, 1e-7 / 2):
        v = np.array([0.6, 0.8, 0.0]) * np.sqrt(1 - qw**2)
        q = jnp.asarray(np.concatenate([v, [qw]]))
        theta = np.linalg.norm(v)
        exact = 2 * np.arctan(theta / qw) / theta * v
        np.testing.assert_allclose(quat.log(q), exact, atol=1e-12)
        np.testing.assert_allclose(jax.jacfwd(quat.log)(q)[:, 3], -2 * v / theta**2, atol=1e-6)


def test_batched_under_vmap_and_jit(rng):
    r = jnp.asarray(rng.normal(size=(7, 5, 3)), jnp.float32)
    f = jax.jit(jax.vmap(jax.vmap(quat.exp)))
    q = f(r)
    assert q.shape == (7, 5, 4) and q.dtype == jnp.float32
    np.testing.assert_allclose(jnp.linalg.norm(q, axis=-1), 1.0, atol=1e-6)
