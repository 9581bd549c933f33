"""Blur image formation: the sharp limit, convergence in n, dense vs sparse, masking, gradients."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.blur import blur_lengths, blur_segments, plane_depths_from_keyframe, reblur, render_blurry
from mbavo_jax.geometry import ExposureTrajectory, PinholeCamera, Pose


def texture(h=96, w=128, seed=0):
    rng = np.random.default_rng(seed)
    img = rng.uniform(size=(h // 8 + 2, w // 8 + 2)).astype(np.float32)
    import cv2

    big = cv2.resize(img, (w + 16, h + 16), interpolation=cv2.INTER_CUBIC)[8 : 8 + h, 8 : 8 + w]
    return jnp.asarray(np.clip(big, 0, 1))


@pytest.fixture
def scene():
    img = texture()
    h, w = img.shape
    cam = PinholeCamera.create(100.0, 100.0, w / 2, h / 2, w, h)
    depth = jnp.full((h, w), 2.0, jnp.float32)
    start = Pose.identity().plus(jnp.array([0.0, -0.02, 0.0, -0.03, 0.0, 0.0], jnp.float32))
    end = Pose.identity().plus(jnp.array([0.0, 0.02, 0.01, 0.03, 0.01, 0.0], jnp.float32))
    return img, cam, depth, ExposureTrajectory(start, end)


def _pixels(cam, margin=20):
    u, v = np.meshgrid(np.arange(margin, cam.width - margin, 3), np.arange(margin, cam.height - margin, 3))
    return jnp.asarray(np.stack([u.ravel(), v.ravel()], -1), jnp.float32)


@pytest.mark.slow
def test_start_equal_end_reproduces_sharp_warp(scene):
    img, cam, depth, traj = scene
    still = ExposureTrajectory(traj.start, traj.start)
    px = _pixels(cam)
    d = jnp.full(px.shape[0], 2.0)
    sharp, ok1 = reblur(img, cam, still, px, d, n=1)
    blurry64, ok64 = reblur(img, cam, still, px, d, n=64)
    np.testing.assert_allclose(blurry64, sharp, atol=4e-6)  # float32: the mean of 64 equal values rounds
    assert bool(jnp.all(ok1 == ok64))
    with jax.enable_x64(True):
        to64 = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), t)
        s64, _ = reblur(to64(img), to64(cam), to64(still), to64(px), to64(d), n=1)
        b64, _ = reblur(to64(img), to64(cam), to64(still), to64(px), to64(d), n=64)
        np.testing.assert_allclose(b64, s64, atol=1e-12)
    # identity trajectory: the "warp" is the image itself
    ident = ExposureTrajectory(Pose.identity(), Pose.identity())
    same, ok = reblur(img, cam, ident, px, d, n=8)
    np.testing.assert_allclose(same, img[px[:, 1].astype(int), px[:, 0].astype(int)], atol=1e-5)


@pytest.mark.slow
def test_converges_with_n(scene):
    img, cam, _, traj = scene
    px = _pixels(cam)
    d = jnp.full(px.shape[0], 2.0)
    vals = {n: reblur(img, cam, traj, px, d, n=n)[0] for n in (4, 16, 64, 256, 1024)}
    errs = [float(jnp.max(jnp.abs(vals[n] - vals[1024]))) for n in (4, 16, 64, 256)]
    assert all(a > b for a, b in zip(errs, errs[1:])), errs
    assert errs[-1] < 2e-3
    # and it is really blurred: far from the single mid-exposure sample
    sharp = reblur(img, cam, traj, px, d, n=1)[0]
    assert float(jnp.mean(jnp.abs(sharp - vals[1024]))) > 10 * errs[-1]


def test_dense_render_matches_sparse(scene):
    img, cam, depth, traj = scene
    planes = plane_depths_from_keyframe(depth, cam, traj.middle())
    dense, valid = render_blurry(img, planes, cam, traj, n=32)
    px = _pixels(cam)
    sparse, ok = reblur(img, cam, traj, px, jnp.full(px.shape[0], 2.0), n=32)
    iu, iv = np.asarray(px[:, 0], int), np.asarray(px[:, 1], int)
    np.testing.assert_allclose(dense[iv, iu], sparse, atol=1e-5)
    np.testing.assert_array_equal(valid[iv, iu], ok)
    assert np.all(np.isfinite(dense))


def test_invalid_samples_are_masked(scene):
    img, cam, depth, traj = scene
    px = jnp.array([[-5.0, 10.0], [10.0, 10.0], [cam.width + 30.0, 40.0], [50.0, 50.0]])
    d = jnp.array([2.0, 2.0, 2.0, -1.0])
    vals, ok = reblur(img, cam, traj, px, d, n=16)
    assert np.all(np.isfinite(vals))
    assert list(np.asarray(ok)) == [False, True, False, False]
    assert float(vals[0]) == 0.0 and float(vals[3]) == 0.0
    nan_depth = depth.at[10:20, 10:20].set(jnp.nan)
    planes = plane_depths_from_keyframe(nan_depth, cam, traj.middle())
    dense, valid = render_blurry(img, planes, cam, traj, n=8)
    assert np.all(np.isfinite(dense)) and not bool(valid[15, 15])


@pytest.mark.slow
def test_gradient_wrt_trajectory_is_finite_and_nonzero(scene):
    img, cam, _, traj = scene
    px = _pixels(cam)
    d = jnp.full(px.shape[0], 2.0)

    def loss(delta):
        v, ok = reblur(img, cam, traj.plus(delta), px, d, n=16)
        return jnp.sum(jnp.where(ok, v, 0.0) ** 2)

    g = jax.grad(loss)(jnp.zeros(12, jnp.float32))
    assert np.all(np.isfinite(g)) and float(jnp.linalg.norm(g)) > 0


@pytest.mark.slow
def test_tracker_residuals_use_the_one_blur_model(scene):
    """The tracker's synthesised intensities (its residuals plus the observed pixels, without the
    affine brightness) equal ``reblur`` at the same trajectory: one image-formation model, float64."""
    from mbavo_jax.tracking.residuals import LevelProblem, residuals_and_jacobian

    with jax.enable_x64(True):
        to64 = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(a, jnp.float64), t)
        img, cam, _, anchor = to64(scene)
        px = to64(_pixels(cam, margin=6))
        d = jnp.linspace(1.5, 3.0, px.shape[0])
        observed = jnp.asarray(np.random.default_rng(1).uniform(size=px.shape[0]))
        rays = jax.vmap(cam.unit_ray)(px)
        n = 16
        problem = LevelProblem(img, cam, anchor, rays, d, observed, jnp.ones(px.shape[0], bool), n, "analytic")
        y = jnp.concatenate([jnp.asarray(np.random.default_rng(2).normal(scale=0.01, size=12)), jnp.array([0.1, 0.02])])
        r, _, valid = residuals_and_jacobian(y, problem, with_jacobian=False)
        tracker_synth = (r - y[13] + observed) / jnp.exp(y[12])
        model, model_ok = reblur(img, cam, anchor.plus(y[:12]), px, d, n=n)
        assert bool(jnp.all(valid == model_ok)) and int(valid.sum()) > 0.9 * px.shape[0]
        np.testing.assert_allclose(np.asarray(tracker_synth)[np.asarray(valid)], np.asarray(model)[np.asarray(valid)], rtol=0, atol=1e-10)


@pytest.mark.slow
def test_blur_segments_point_along_the_motion_and_give_the_blur_lengths():
    """A sideways move of 0.04 m at 2 m depth (f = 100 px): every kernel is the 2 px segment from the
    start to the end projection, against the motion; a point without depth has a zero segment."""
    cam = PinholeCamera.create(100.0, 100.0, 64.0, 48.0, 128, 96)
    traj = ExposureTrajectory(Pose.identity().plus(jnp.array([0.0, 0.0, 0.0, -0.02, 0.0, 0.0], jnp.float32)),
                              Pose.identity().plus(jnp.array([0.0, 0.0, 0.0, 0.02, 0.0, 0.0], jnp.float32)))
    pixels = _pixels(cam)
    depths = jnp.full(pixels.shape[0], 2.0, jnp.float32).at[0].set(jnp.nan)
    segments, valid = blur_segments(cam, pixels, depths, traj)
    lengths, valid_l = blur_lengths(cam, pixels, depths, traj)
    assert not bool(valid[0]) and bool(valid[1:].all()) and np.array_equal(np.asarray(valid), np.asarray(valid_l))
    np.testing.assert_allclose(np.asarray(segments[1:]), np.tile([-2.0, 0.0], (pixels.shape[0] - 1, 1)), atol=1e-4)
    np.testing.assert_array_equal(np.asarray(segments[0]), [0.0, 0.0])
    np.testing.assert_allclose(np.asarray(lengths), np.linalg.norm(np.asarray(segments), axis=1), rtol=1e-6)


@pytest.mark.slow
def test_blur_lengths_have_a_finite_gradient_where_the_camera_does_not_move():
    """At a still exposure every segment is zero; the gradient of the lengths' sum with respect to
    the end pose is then finite (not NaN from the norm at 0), and away from it matches finite differences."""
    cam = PinholeCamera.create(100.0, 100.0, 64.0, 48.0, 128, 96)
    pixels = _pixels(cam)
    depths = jnp.full(pixels.shape[0], 2.0, jnp.float32)

    def total(delta):
        traj = ExposureTrajectory(Pose.identity(), Pose.identity().plus(delta))
        return jnp.sum(blur_lengths(cam, pixels, depths, traj)[0])

    assert np.isfinite(np.asarray(jax.grad(total)(jnp.zeros(6, jnp.float32)))).all()
    delta = jnp.array([0.0, 0.0, 0.0, 0.02, 0.0, 0.0], jnp.float32)
    step = jnp.array([0.0, 0.0, 0.0, 1e-3, 0.0, 0.0], jnp.float32)
    numeric = (total(delta + step) - total(delta - step)) / 2e-3
    np.testing.assert_allclose(float(jax.grad(total)(delta)[3]), float(numeric), rtol=1e-2)
