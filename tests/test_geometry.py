"""Poses, exposure trajectory (Eqs. 42-44), camera (Eq. 85 model) and plane transfer (Eqs. 61-68)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.geometry import ExposureTrajectory, PinholeCamera, Pose, interpolate, plane_transfer, virtual_poses
from mbavo_jax.geometry import quaternion as quat


def random_pose(rng, rot=0.3, trans=0.3, dtype=jnp.float64):
    q = quat.exp(jnp.asarray(rng.normal(scale=rot, size=3), dtype))
    return Pose(q, jnp.asarray(rng.normal(scale=trans, size=3), dtype))


def test_pose_compose_inverse_apply(x64, rng):
    a, b = random_pose(rng), random_pose(rng)
    p = jnp.asarray(rng.normal(size=3))
    np.testing.assert_allclose(a.compose(b).apply(p), a.apply(b.apply(p)), atol=1e-12)
    np.testing.assert_allclose(a.inverse().apply(a.apply(p)), p, atol=1e-12)
    np.testing.assert_allclose(a.compose(b).as_matrix(), a.as_matrix() @ b.as_matrix(), atol=1e-12)
    back = Pose.from_matrix(a.as_matrix())
    np.testing.assert_allclose(back.as_matrix(), a.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(Pose.from_vector(a.to_vector()).q, a.q)


def test_rotate_is_the_rotation_matrix_times_the_vector(x64, rng):
    for _ in range(5):
        q = random_pose(rng, rot=1.0).q
        v = jnp.asarray(rng.normal(size=3))
        np.testing.assert_allclose(quat.rotate(q, v), quat.to_matrix(q) @ v, rtol=1e-13, atol=1e-13)


def test_interpolation_endpoints_and_midpoint(x64, rng):
    a, b = random_pose(rng), random_pose(rng)
    for s, ref in ((0.0, a), (1.0, b)):
        got = interpolate(a, b, s)
        np.testing.assert_allclose(quat.to_matrix(got.q), quat.to_matrix(ref.q), atol=1e-12)
        np.testing.assert_allclose(got.t, ref.t, atol=1e-12)
    mid = interpolate(a, b, 0.5)
    # rotation halfway: the relative rotation start->mid equals mid->end
    r1 = quat.log(quat.product(quat.inverse(a.q), mid.q))
    r2 = quat.log(quat.product(quat.inverse(mid.q), b.q))
    np.testing.assert_allclose(r1, r2, atol=1e-12)
    np.testing.assert_allclose(mid.t, 0.5 * (a.t + b.t), atol=1e-12)


@pytest.mark.parametrize("n", [1, 2, 64])
def test_virtual_poses(n, rng):
    a, b = random_pose(rng, dtype=jnp.float32), random_pose(rng, dtype=jnp.float32)
    poses = virtual_poses(ExposureTrajectory(a, b), n)
    assert poses.q.shape == (n, 4) and poses.t.shape == (n, 3)
    if n == 1:
        np.testing.assert_allclose(poses.t[0], interpolate(a, b, 0.5).t, atol=1e-6)
    else:
        np.testing.assert_allclose(poses.t[0], a.t, atol=1e-6)
        np.testing.assert_allclose(poses.t[-1], b.t, atol=1e-6)


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
@pytest.mark.parametrize("same", [True, False])
@pytest.mark.parametrize("s", [0.0, 0.5, 1.0])
def test_interpolation_gradients_finite(dtype, same, s):
    """No NaN at s = 0, s = 1, and start = end (log at the identity)."""
    with jax.enable_x64(dtype == jnp.float64):
        rng = np.random.default_rng(4)
        a = random_pose(rng, dtype=dtype)
        b = a if same else random_pose(rng, dtype=dtype)

        def f(delta):
            traj = ExposureTrajectory(a, b).plus(delta)
            p = interpolate(traj.start, traj.end, jnp.asarray(s, dtype))
            return jnp.sum(p.q) + jnp.sum(p.t)

        g = jax.grad(f)(jnp.zeros(12, dtype))
        assert np.all(np.isfinite(g))


def test_camera_project_backproject(x64):
    cam = PinholeCamera.create(500, 480, 320, 240, 640, 480, dtype=jnp.float64)
    x = jnp.array([100.5, 300.25])
    np.testing.assert_allclose(cam.project(cam.backproject(x, 2.5)), x, atol=1e-12)
    np.testing.assert_allclose(jnp.linalg.norm(cam.unit_ray(x)), 1.0, atol=1e-15)
    c1 = cam.scaled(1)
    assert (c1.width, c1.height) == (320, 240)
    # pixel centre convention: level-0 pixel (2i+0.5) maps to level-1 pixel i
    p = cam.backproject(jnp.array([10.5, 20.5]), 3.0)
    np.testing.assert_allclose(c1.project(p), [5.0, 10.0], atol=1e-12)


@pytest.mark.parametrize("bad", [(0, 500, 1, 1), (-1, 500, 1, 1), (500, float("nan"), 1, 1)])
def test_camera_rejects_bad_intrinsics(bad):
    with pytest.raises(ValueError):
        PinholeCamera.create(*bad, 640, 480)


def test_plane_transfer_hits_the_point_on_the_plane(x64, rng):
    """A ref point P on the plane Z = d seen at pixel x_i of virtual camera i transfers back to π(P)."""
    cam = PinholeCamera.create(500, 500, 320, 240, 640, 480, dtype=jnp.float64)
    for _ in range(10):
        T_ref_i = random_pose(rng, rot=0.1, trans=0.1)
        d = rng.uniform(1.0, 4.0)
        P = jnp.array([rng.uniform(-0.5, 0.5) * d, rng.uniform(-0.4, 0.4) * d, d])
        x_i = cam.project(T_ref_i.inverse().apply(P))
        x_ref, valid = plane_transfer(T_ref_i, cam, x_i, d)
        assert bool(valid)
        np.testing.assert_allclose(x_ref, cam.project(P), atol=1e-9)


def test_plane_transfer_invalid_is_masked_not_nan(x64):
    cam = PinholeCamera.create(500, 500, 320, 240, 640, 480, dtype=jnp.float64)
    behind = Pose(quat.exp(jnp.array([0.0, jnp.pi, 0.0])), jnp.zeros(3))  # looking backwards
    x_ref, valid = plane_transfer(behind, cam, jnp.array([320.0, 240.0]), 2.0)
    assert not bool(valid) and np.all(np.isfinite(x_ref))
    beyond = Pose(quat.identity(jnp.float64), jnp.array([0.0, 0.0, 3.0]))  # camera past the plane
    x_ref, valid = plane_transfer(beyond, cam, jnp.array([320.0, 240.0]), 2.0)
    assert not bool(valid) and np.all(np.isfinite(x_ref))
    g = jax.grad(lambda t: plane_transfer(Pose(behind.q, t), cam, jnp.array([320.0, 240.0]), 2.0)[0].sum())(jnp.zeros(3))
    assert np.all(np.isfinite(g))
