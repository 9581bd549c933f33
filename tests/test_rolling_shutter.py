"""Rolling shutter inside the blur model: row times, the global-shutter limit, the shear of a
readout, both Jacobian paths against jacfwd, the tracker, deblurring, the loops' exposure span and
the camera.yaml calibration. Small images (at most 160x120); tracking and deblurring are slow."""

from __future__ import annotations

import dataclasses

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.blur import plane_depths_from_keyframe, reblur, render_blurry, virtual_pq, virtual_sample
from mbavo_jax.config import RunConfig, TrackerConfig, calibration_of, load_config
from mbavo_jax.deblur import deblur, psnr
from mbavo_jax.geometry import ExposureTrajectory, PinholeCamera, Pose, RowClock, readout_fraction, row_times, virtual_times
from mbavo_jax.tracking import Keyframe, track
from mbavo_jax.tracking.level import residual_pixels
from mbavo_jax.tracking.residuals import LevelProblem, make_residual_fn, residuals_and_jacobian
from tests.test_tracking import endpoint_error

SMALL = TrackerConfig(levels=3, points=(192, 128, 64), cell=(10, 7, 5), max_steps=(10, 12, 20), n=32, hypotheses=False)


def texture(h, w, seed=0, cells=10):
    rng = np.random.default_rng(seed)
    img = rng.uniform(size=(h // cells + 2, w // cells + 2)).astype(np.float32)
    big = cv2.resize(img, (w + 2 * cells, h + 2 * cells), interpolation=cv2.INTER_CUBIC)[cells : cells + h, cells : cells + w]
    return np.clip(big, 0, 1).astype(np.float32)


def scene(h=120, w=160):
    """A smooth random texture on a slanted plane, seen by a camera of focal 0.9 w."""
    cam = PinholeCamera.create(0.9 * w, 0.9 * w, (w - 1) / 2, (h - 1) / 2, w, h)
    yy, xx = np.mgrid[0:h, 0:w]
    return texture(h, w), cam, (2.0 + 0.3 * xx / w + 0.2 * yy / h).astype(np.float32)


def path(mid6, motion6) -> ExposureTrajectory:
    """A path whose middle is exp(mid6) and whose motion start⁻¹·end is exp(motion6) (halves about the middle)."""
    mid = Pose.identity().plus(jnp.asarray(mid6, jnp.float32))
    half = jnp.asarray(motion6, jnp.float32) / 2
    return ExposureTrajectory(mid.compose(Pose.identity().plus(-half)), mid.compose(Pose.identity().plus(half)))


def render(img, cam, depth, traj, n, rho):
    """The blurry frame along ``traj`` (planes from the keyframe depth at the path's middle); pixels
    the model cannot render keep the keyframe's value."""
    planes = plane_depths_from_keyframe(jnp.asarray(depth), cam, traj.middle())
    b, ok = render_blurry(jnp.asarray(img), planes, cam, traj, n, rho)
    return np.where(np.asarray(ok), np.asarray(b), img), planes


GT = path([0.003, -0.004, 0.0, 0.02, -0.01, 0.01], [0.0, 0.02, 0.0, 0.12, 0.0, 0.0])  # readout-dominated sideways motion
RHO = 0.6


# ------------------------------------------------------------------------------------ time model


def test_row_times_and_fraction():
    n, h = 5, 11
    rows = jnp.arange(h, dtype=jnp.float32)
    np.testing.assert_array_equal(row_times(n, rows, h, 0.0), np.broadcast_to(virtual_times(n), (h, n)))
    t = np.asarray(row_times(n, rows, h, 0.25))
    np.testing.assert_allclose(t[0], np.linspace(0.0, 0.75, n), atol=1e-7)  # first row: [0, 1 - ρ]
    np.testing.assert_allclose(t[-1], np.linspace(0.25, 1.0, n), atol=1e-7)  # last row: [ρ, 1]
    np.testing.assert_allclose(np.diff(t[:, 0]), 0.025, atol=1e-7)  # rows start ρ/(H-1) apart
    np.testing.assert_allclose(row_times(1, rows, h, 0.25)[:, 0], 0.375 + 0.025 * np.arange(h), atol=1e-7)  # each row's middle
    assert readout_fraction(0.0, 0.01) == 0.0 and readout_fraction(0.03, 0.0) == 1.0
    assert readout_fraction(0.03, 0.01) == pytest.approx(0.75)


def test_row_clock_maps_pyramid_rows_to_full_rows():
    """Row v of level l is full-resolution row v·2^l + (2^l-1)/2: the same times as that row."""
    for level in (1, 2):
        clock = RowClock.create(0.4, 120, level)
        v = jnp.arange(120 >> level, dtype=jnp.float32)
        full = v * 2**level + 0.5 * (2**level - 1)
        np.testing.assert_allclose(clock.times(v, 4), row_times(4, full, 120, 0.4), atol=1e-7)


def test_row_path_is_the_rows_own_exposure():
    traj = path([0.01, 0.0, 0.02, 0.05, 0.0, -0.01], [0.02, -0.01, 0.0, 0.1, 0.02, 0.0])
    sub = traj.row_path(30.0, 61, 0.5)  # s from 0.25 to 0.75
    for s_sub, s in ((0.0, 0.25), (1.0, 0.75), (0.3, 0.25 + 0.3 * 0.5)):
        a, b = sub.at(s_sub), traj.at(s)
        np.testing.assert_allclose(a.t, b.t, atol=1e-6)
        np.testing.assert_allclose(np.abs(np.dot(a.q, b.q)), 1.0, atol=1e-6)
    assert traj.middle_row_path(0.0) is traj


# ------------------------------------------------------------------------- the global-shutter limit


@jax.jit
def _global_shutter_reference(img, cam, traj, pixels, depths):
    """Today's model, written out: the mean over the n = 8 poses of the path, shared by all pixels."""
    rays = jax.vmap(cam.unit_ray)(pixels)
    per_pose = lambda pq: jax.vmap(lambda ray, d: virtual_sample(img, cam, pq, ray, d))(rays, depths)
    values, _, _, ok = jax.vmap(per_pose)(virtual_pq(traj, 8))
    valid = jnp.all(ok, axis=0)
    return jnp.where(valid, jnp.mean(values, axis=0), 0.0), valid


@pytest.mark.slow
def test_zero_readout_is_the_global_shutter_model():
    img, cam, depth = scene(48, 64)
    img = jnp.asarray(img)
    traj = GT
    px = jnp.asarray(np.random.default_rng(1).uniform([2, 2], [61, 45], (200, 2)), jnp.float32)
    d = jnp.asarray(np.random.default_rng(2).uniform(1.8, 2.4, 200), jnp.float32)
    ref, ref_ok = _global_shutter_reference(img, cam, traj, px, d)
    got, ok = reblur(img, cam, traj, px, d, 8, 0.0)
    np.testing.assert_array_equal(got, ref)  # identical, not just close
    np.testing.assert_array_equal(ok, ref_ok)
    # the per-row program with a traced ρ = 0 is the same model (to rounding)
    traced, ok_t = jax.jit(lambda r: reblur(img, cam, traj, px, d, 8, r))(jnp.float32(0.0))
    np.testing.assert_allclose(traced, ref, atol=2e-6)
    planes = plane_depths_from_keyframe(jnp.asarray(depth), cam, traj.middle())
    dense, dense_ok = render_blurry(img, planes, cam, traj, 8)
    np.testing.assert_array_equal(dense, render_blurry(img, planes, cam, traj, 8, 0.0)[0])
    traced, traced_ok = jax.jit(lambda r: render_blurry(img, planes, cam, traj, 8, r))(jnp.float32(0.0))
    np.testing.assert_allclose(traced, dense, atol=2e-6)
    np.testing.assert_array_equal(traced_ok, dense_ok)


def test_readout_shears_vertical_edges():
    """A sideways translation tx during the readout alone (τ = 0, ρ = 1) moves a vertical edge in row
    v by -f·tx·v/((H-1)·d) pixels: later rows see the camera further right, the edge further left."""
    h, w, d, tx = 48, 64, 2.0, 0.05
    cam = PinholeCamera.create(60.0, 60.0, (w - 1) / 2, (h - 1) / 2, w, h)
    x = np.arange(w, dtype=np.float32)
    img = jnp.asarray(np.tile(1.0 / (1.0 + np.exp(-(x - 32.0) / 2.0)), (h, 1)).astype(np.float32))
    traj = ExposureTrajectory(Pose.identity(), Pose(Pose.identity().q, jnp.array([tx, 0.0, 0.0], jnp.float32)))
    blurry, ok = render_blurry(img, jnp.full((h, w), d, jnp.float32), cam, traj, 4, 1.0)
    inner = np.arange(1, h - 1)  # the border rows sample outside the keyframe
    assert np.asarray(ok)[inner][:, 8:-8].all()
    edges = []
    for row in np.asarray(blurry)[inner]:
        k = int(np.argmax(row >= 0.5))
        edges.append(k - 1 + (0.5 - row[k - 1]) / (row[k] - row[k - 1]))
    expected = 32.0 - 60.0 * tx * inner / ((h - 1) * d)
    np.testing.assert_allclose(edges, expected, atol=0.03)
    assert edges[-1] < edges[0] - 1.4  # 1.5 px of shear from the first row to the last
    # the same frame with a global shutter: one (blurred) edge shared by all rows
    gs = np.asarray(render_blurry(img, jnp.full((h, w), d, jnp.float32), cam, traj, 4, 0.0)[0])
    np.testing.assert_allclose(gs[inner, 8:-8], np.broadcast_to(gs[h // 2, 8:-8], (h - 2, w - 16)), atol=1e-6)


# ------------------------------------------------------------------------------------- Jacobians


def _rs_problem(jacobian, rho, dtype):
    img, cam, depth = scene(48, 64)
    cur, _ = render(img, cam, depth, GT, 16, rho)
    v, u = np.mgrid[4:44:5, 4:60:5]
    px = np.stack([u.ravel(), v.ravel()], 1).astype(np.float32)
    init = path([0.0] * 6, [0.0, 0.01, 0.0, 0.08, 0.0, 0.0])
    rays, d, obs, mask, rows = residual_pixels(cam, jnp.asarray(cur), jnp.asarray(px), jnp.asarray(depth[v.ravel(), u.ravel()]),
                                               jnp.ones(px.shape[0], bool), init)
    times = RowClock.create(rho, 48, 0).times(jnp.arange(48, dtype=jnp.float32), 8)
    cast = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype) if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else a, t)
    return LevelProblem(cast(jnp.asarray(img)), cast(cam), cast(init).normalized(), cast(rays), cast(d), cast(obs), mask, 8, jacobian,
                        cast(times), rows)


@pytest.mark.slow
def test_rolling_shutter_jacobians_match_jacfwd(x64):
    """Per-row-bucket M_{b,i}, every path, equal jax.jacfwd of the whole residual in float64, away
    from y = 0; the custom JVP is what optimistix linearises."""
    y = jnp.asarray(np.random.default_rng(0).normal(scale=[1e-3] * 12 + [0.05, 0.01]), jnp.float64)
    ref = None
    for jac in ("autodiff", "analytic", "tangent"):
        prob = _rs_problem(jac, RHO, jnp.float64)
        plain = jax.jacfwd(lambda yy: residuals_and_jacobian(yy, prob, False)[0])(y)
        r, J, valid = residuals_and_jacobian(y, prob, True)
        assert int(valid.sum()) > 300
        assert len(np.unique(np.asarray(prob.rows)[np.asarray(valid)])) > 20  # many row buckets in play
        np.testing.assert_allclose(J, plain, atol=1e-8, rtol=1e-6)
        _, lin = jax.linearize(lambda yy: make_residual_fn()(yy, prob), y)
        np.testing.assert_allclose(jax.vmap(lin)(jnp.eye(14)).T, J, atol=1e-10)
        ref = J if ref is None else ref
        np.testing.assert_allclose(J, ref, atol=1e-8, rtol=1e-6)
    # the row buckets matter: the global-shutter Jacobian differs
    gs = dataclasses.replace(prob, times=None, rows=None)
    assert float(jnp.max(jnp.abs(residuals_and_jacobian(y, gs, True)[1] - ref))) > 1e-3


# ---------------------------------------------------------------------------- tracker, deblurring


@pytest.mark.slow
def test_tracker_recovers_a_rolling_shutter_path():
    """A frame rendered with ρ = 0.6: the per-row model's start/end endpoint error is at most half the
    global-shutter model's."""
    img, cam, depth = scene()
    kf = Keyframe.create(img, depth, cam, SMALL)
    blurry, _ = render(img, cam, depth, GT, 64, RHO)
    init = path([0.0] * 6, [0.0, 0.015, 0.0, 0.1, 0.0, 0.0])
    err = {}
    for rho in (0.0, RHO):
        res = track(kf, blurry, init, SMALL, readout=rho)
        assert res.status.ok and res.diagnostics["readout"] == rho
        err[rho] = endpoint_error(kf, res.trajectory, GT)
    assert err[RHO] <= 0.5 * err[0.0], err
    assert err[RHO] < 0.5, err


@pytest.mark.slow
def test_deblurring_with_the_readout_is_sharper():
    img, cam, depth = scene()
    blurry, planes = render(img, cam, depth, GT, 64, RHO)
    mid = GT.middle()
    sharp = np.asarray(render_blurry(jnp.asarray(img), planes, cam, ExposureTrajectory(mid, mid), 1)[0])
    frame_depth = np.asarray(planes)
    cfg = RunConfig().deblur
    inner = np.zeros(img.shape, bool)
    inner[12:-12, 16:-16] = True
    scores = {rho: psnr(deblur(blurry, frame_depth, cam, GT, cfg, 1.0, rho), sharp, inner) for rho in (0.0, RHO)}
    assert scores[RHO] > scores[0.0] + 1.0, scores
    assert scores[RHO] > psnr(blurry, sharp, inner) + 2.0, scores


# --------------------------------------------------------------------------- settings and loops


def test_calibration_maps_readout_ms_and_set_overrides_it():
    assert calibration_of({"readout_ms": 30}) == {"readout_s": pytest.approx(0.03)}
    assert load_config(None, [], calibration_of({"readout_ms": 15})).tracker.readout_s == pytest.approx(0.015)
    assert load_config(None, ["tracker.readout_s=0"], calibration_of({"readout_ms": 15})).tracker.readout_s == 0.0
    assert TrackerConfig().readout_s == 0.0


def test_loop_paths_span_exposure_plus_readout():
    """The constant-velocity path of the loops spans τ + R and comes with ρ = R/(R+τ)."""
    from mbavo_jax.odometry.rgbd import RGBDPipeline

    cam = PinholeCamera.create(100.0, 100.0, 79.5, 59.5, 160, 120)
    pipe = RGBDPipeline(cam, RunConfig().replace(tracker=dict(readout_s=0.03)))
    V = Pose(Pose.identity().q, jnp.array([0.1, 0.0, 0.0], jnp.float32))  # 0.1 m per 1/30 s
    p, rho = pipe.velocity_path(V, 1 / 30, 0.01)
    assert rho == pytest.approx(0.75)
    np.testing.assert_allclose(p.start.inverse().compose(p.end).t, [0.1 * 0.04 * 30, 0.0, 0.0], rtol=1e-5)
    assert pipe.readout_of(0.0) == 1.0 and RGBDPipeline(cam).readout_of(0.01) == 0.0
