"""The cubic exposure path (``tracker.trajectory: cubic``): the cumulative B-spline and its straight
limit, its Jacobians against jacfwd, the tracker on curved and straight paths, the run file
exposure_spline.txt and the per-row error read from it. Small images (160x120 at most)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.config import ConfigError, TrackerConfig, load_config
from mbavo_jax.evaluation import row_fractions, row_path_error
from mbavo_jax.geometry import ExposureTrajectory, Pose, RowClock, SplineTrajectory, as_trajectory, interpolate
from mbavo_jax.io import ExposureRows, read_exposure_spline_file
from mbavo_jax.odometry.outputs import RunOutputs
from mbavo_jax.odometry.state import FrameOutcome
from mbavo_jax.tracking import Keyframe, Status, TrackResult, track
from mbavo_jax.tracking.level import CurvaturePrior, curvature_residuals, residual_pixels
from mbavo_jax.tracking.motion import motion_hypotheses
from mbavo_jax.tracking.residuals import LevelProblem, make_residual_fn, residuals_and_jacobian
from tests.test_rolling_shutter import SMALL, path, render, scene

RHO = 0.6


def curved(mid6, motion6, bend6) -> SplineTrajectory:
    """The straight path ``path(mid6, motion6)`` as a spline, bent: the outer control poses moved by
    ``bend6``, the inner ones by −``bend6`` (a path that turns one way and back)."""
    b = jnp.asarray(bend6, jnp.float32)
    return SplineTrajectory.from_linear(path(mid6, motion6)).plus(jnp.concatenate([b, -b, -b, b]))


def row_error(kf: Keyframe, est, gt, rho: float, rows: int = 9) -> float:
    """Mean over ``rows`` evenly spaced image rows of the median reprojection distance (keyframe
    points, px) between the estimated and true poses at each row's exposure start and end."""
    pts, cam = kf.points[0], kf.cameras[0]
    X = jax.vmap(cam.backproject)(jnp.asarray(pts.pixels[pts.valid]), jnp.asarray(pts.depths[pts.valid]))
    u = np.linspace(0.0, 1.0, rows)
    errs = []
    for s in np.concatenate([rho * u, rho * u + 1.0 - rho]):
        a, b = est.at(float(s)), gt.at(float(s))
        pa = jax.vmap(lambda p: cam.project(a.inverse().apply(p)))(X)
        pb = jax.vmap(lambda p: cam.project(b.inverse().apply(p)))(X)
        errs.append(np.median(np.linalg.norm(np.asarray(pa - pb), axis=1)))
    return float(np.mean(errs))


def _close(a: Pose, b: Pose, atol: float) -> None:
    np.testing.assert_allclose(a.t, b.t, atol=atol)
    np.testing.assert_allclose(abs(float(jnp.dot(a.q, b.q))), 1.0, atol=atol)


# ------------------------------------------------------------------------------------ the spline


@pytest.mark.slow
def test_evenly_spaced_controls_give_the_straight_path(x64):
    line = ExposureTrajectory(Pose.identity(jnp.float64).plus(jnp.array([0.1, -0.2, 0.05, 0.1, 0.2, 0.3])),
                              Pose.identity(jnp.float64).plus(jnp.array([0.15, -0.1, 0.1, 0.2, 0.1, 0.35])))
    spline = SplineTrajectory.from_linear(line)
    for s in np.linspace(-0.2, 1.2, 15):  # beyond the frame time too: the spline continues the line
        _close(spline.at(s), interpolate(line.start, line.end, s), 1e-12)
    # the control poses are the line's, one step apart: V^(j-1) from the start
    for j in range(4):
        _close(spline.control(j), line.at(j - 1.0), 1e-12)
    _close(spline.about_middle().at(0.3), line.about_middle().at(0.3), 1e-12)
    _close(spline.row_path(30.0, 61, 0.5).end, line.row_path(30.0, 61, 0.5).end, 1e-12)
    np.testing.assert_array_equal(spline.plus(jnp.zeros(24)).controls.q, spline.controls.q)


@pytest.mark.slow
def test_spline_ends_middle_and_moves():
    spline = curved([0.01, 0.0, 0.02, 0.05, 0.0, -0.01], [0.02, -0.01, 0.0, 0.1, 0.02, 0.0], [0.0, 0.03, 0.0, 0.0, 0.04, 0.0])
    _close(spline.start, spline.at(0.0), 1e-6)
    _close(spline.end, spline.at(1.0), 1e-6)
    _close(spline.middle(), spline.at(0.5), 1e-6)
    assert spline.dof == 24 and ExposureTrajectory.dof == 12
    # a B-spline does not pass through its control poses: the bend shows between the ends
    chord = spline.chord()
    assert float(jnp.linalg.norm(chord.at(0.5).t - spline.middle().t)) > 1e-3
    # translation: the plain cubic B-spline of the control translations ((1, 4, 1)/6 at u = 0)
    t = spline.controls.t
    np.testing.assert_allclose(spline.start.t, (t[0] + 4 * t[1] + t[2]) / 6, atol=1e-6)
    np.testing.assert_allclose(spline.end.t, (t[1] + 4 * t[2] + t[3]) / 6, atol=1e-6)
    # seen from another frame: every pose composed on the left
    T = Pose.identity().plus(jnp.array([0.1, 0.2, -0.1, 0.5, 0.0, 0.2]))
    _close(spline.seen_from(T).at(0.3), T.compose(spline.at(0.3)), 1e-5)
    _close(spline.about_middle().middle(), Pose.identity(), 1e-6)


def test_as_trajectory_and_hypotheses_keep_the_path():
    line = path([0.01, 0.0, 0.0, 0.02, 0.0, 0.0], [0.0, 0.02, 0.0, 0.1, 0.0, 0.0])
    assert as_trajectory(line, "linear") is line
    spline = as_trajectory(line, "cubic")
    assert isinstance(spline, SplineTrajectory) and as_trajectory(spline, "cubic") is spline
    for (name_l, hyp_l), (name_s, hyp_s) in zip(motion_hypotheses(line), motion_hypotheses(spline)):
        assert name_l == name_s and isinstance(hyp_s, SplineTrajectory)
        for s in (0.0, 0.5, 1.0):
            _close(hyp_s.at(s), hyp_l.at(s), 1e-5)


def test_trajectory_setting():
    assert TrackerConfig().trajectory == "linear"
    assert load_config(None, ["tracker.trajectory=cubic"]).tracker.trajectory == "cubic"
    with pytest.raises(ConfigError, match="trajectory"):
        TrackerConfig(trajectory="quintic")


# ------------------------------------------------------------------------------------ Jacobians


def _spline_problem(jacobian: str, rho: float, dtype):
    img, cam, depth = scene(48, 64)
    gt = curved([0.003, -0.004, 0.0, 0.02, -0.01, 0.01], [0.0, 0.02, 0.0, 0.1, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0, 0.06, 0.0])
    cur, _ = render(img, cam, depth, gt, 16, rho)
    v, u = np.mgrid[4:44:5, 4:60:5]
    px = np.stack([u.ravel(), v.ravel()], 1).astype(np.float32)
    init = SplineTrajectory.from_linear(path([0.0] * 6, [0.0, 0.01, 0.0, 0.08, 0.0, 0.0]))
    rays, d, obs, mask, rows = residual_pixels(cam, jnp.asarray(cur), jnp.asarray(px), jnp.asarray(depth[v.ravel(), u.ravel()]),
                                               jnp.ones(px.shape[0], bool), init)
    times = RowClock.create(rho, 48, 0).times(jnp.arange(48, dtype=jnp.float32), 8) if rho > 0 else None
    cast = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype) if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else a, t)
    return LevelProblem(cast(jnp.asarray(img)), cast(cam), cast(init).normalized(), cast(rays), cast(d), cast(obs), mask, 8, jacobian,
                        None if times is None else cast(times), rows if rho > 0 else None)


@pytest.mark.slow
@pytest.mark.parametrize("rho", [0.0, RHO])
def test_spline_jacobians_match_jacfwd(x64, rho):
    """Every path (analytic or tangent g with the spline's autodiff M; autodiff) equal jax.jacfwd of the whole
    residual in float64, away from y = 0; the custom JVP is what optimistix linearises."""
    y = jnp.asarray(np.random.default_rng(0).normal(scale=[1e-3] * 24 + [0.05, 0.01]), jnp.float64)
    for jac in ("autodiff", "analytic", "tangent"):
        prob = _spline_problem(jac, rho, jnp.float64)
        plain = jax.jacfwd(lambda yy: residuals_and_jacobian(yy, prob, False)[0])(y)
        r, J, valid = residuals_and_jacobian(y, prob, True)
        assert J.shape == (r.shape[0], 26) and int(valid.sum()) > 300
        assert float(jnp.max(jnp.abs(J[:, :24]))) > 1e-3  # the control poses do move the residuals
        np.testing.assert_allclose(J, plain, atol=1e-8, rtol=1e-6)
        _, lin = jax.linearize(lambda yy: make_residual_fn()(yy, prob), y)
        np.testing.assert_allclose(jax.vmap(lin)(jnp.eye(26)).T, J, atol=1e-10)


# ------------------------------------------------------------------------------------- tracking

MID, MOTION = [0.003, -0.004, 0.0, 0.02, -0.01, 0.01], [0.0, 0.02, 0.0, 0.1, 0.0, 0.0]
INIT = path([0.0] * 6, [0.0, 0.015, 0.0, 0.08, 0.0, 0.0])


def _track_both(gt, rho: float) -> dict:
    img, cam, depth = scene()
    kf = Keyframe.create(img, depth, cam, SMALL)
    blurry, _ = render(img, cam, depth, gt, 64, rho)
    err = {}
    for kind in ("linear", "cubic"):
        res = track(kf, blurry, INIT, dataclasses.replace(SMALL, trajectory=kind), readout=rho)
        assert res.status.ok and isinstance(res.trajectory, SplineTrajectory) == (kind == "cubic"), (kind, res.status)
        err[kind] = row_error(kf, res.trajectory, gt, rho)
    return err


@pytest.mark.slow
def test_cubic_recovers_a_curved_rolling_shutter_path():
    """A frame rendered along a bent spline with ρ = 0.6: the cubic path's per-row endpoint error
    (:func:`row_error`) is at most half the straight path's."""
    gt = curved(MID, MOTION, [0.0, 0.0, 0.0, 0.0, 0.12, 0.0])
    err = _track_both(gt, RHO)
    assert err["cubic"] <= 0.5 * err["linear"], err


@pytest.mark.slow
def test_cubic_on_a_straight_path_is_no_worse():
    err = _track_both(SplineTrajectory.from_linear(path(MID, MOTION)), RHO)
    assert err["cubic"] <= 1.2 * err["linear"] + 0.05, err


@pytest.mark.slow
def test_curvature_prior_is_zero_on_straight_paths_and_straightens_the_fit():
    """The prior's residuals vanish on a constant-velocity spline; a stiff prior (tiny σ) keeps a
    fit to a bent frame nearly straight."""
    unit = CurvaturePrior(jnp.ones(6, jnp.float32), jnp.float32(1.0))
    straight, gt = SplineTrajectory.from_linear(path(MID, MOTION)), curved(MID, MOTION, [0.0, 0.0, 0.0, 0.0, 0.12, 0.0])
    assert float(jnp.max(jnp.abs(curvature_residuals(straight, unit)))) < 1e-6
    assert float(jnp.max(jnp.abs(curvature_residuals(gt, unit)))) > 0.1
    img, cam, depth = scene()
    kf = Keyframe.create(img, depth, cam, SMALL)
    blurry, _ = render(img, cam, depth, gt, 64, RHO)
    res = track(kf, blurry, INIT, dataclasses.replace(SMALL, trajectory="cubic", curvature_prior_rad=1e-6), readout=RHO)
    assert res.status.ok, res.status
    bend, true_bend = (float(jnp.linalg.norm(curvature_residuals(p, unit))) for p in (res.trajectory, gt))
    assert bend < 0.05 * true_bend, (bend, true_bend)  # test_cubic_recovers_a_curved_rolling_shutter_path: free, it follows the bend


# ---------------------------------------------------------------------------------- run records


@pytest.mark.slow
def test_spline_file_and_row_error_from_it(tmp_path):
    """A cubic result's control poses go to exposure_spline.txt (camera-to-world, the spline at 0
    being exposure.txt's start); the per-row error read from them equals the straight path's when
    the spline is straight, and sees a bend that the straight estimate misses."""
    cam = scene()[1]
    T_w_kf = Pose.identity().plus(jnp.array([0.0, 0.1, 0.0, 1.0, 0.0, 0.5]))
    gt = curved(MID, MOTION, [0.0, 0.0, 0.0, 0.0, 0.08, 0.0])
    with RunOutputs(tmp_path, cam, 1.0) as out:
        for k, traj in enumerate((SplineTrajectory.from_linear(path(MID, MOTION)), gt)):
            result = TrackResult(traj, Status.CONVERGED, {})
            out.write(FrameOutcome(k, 1.0 + k, "converged", T_w_kf.compose(traj.middle()), T_w_kf.compose(traj.start),
                                   T_w_kf.compose(traj.end), result=result))
    stamps, controls = read_exposure_spline_file(tmp_path / "exposure_spline.txt")
    assert controls.shape == (2, 4, 7) and np.allclose(stamps, [1.0, 2.0])
    world = SplineTrajectory(jax.vmap(Pose.from_vector)(jnp.asarray(controls[1], jnp.float32)))
    _close(world.start, T_w_kf.compose(gt.start), 1e-5)
    _close(world.at(0.4), T_w_kf.compose(gt.at(0.4)), 1e-5)
    # per-row truth of both frames: the straight one and the bent one, each row at its own times
    rows = np.array([0, 30, 60, 90, 119])
    s = row_fractions(rows, 120, RHO)
    vec = lambda p: np.asarray(p.to_vector(), np.float64)
    truth_at = lambda traj, j: np.stack([vec(T_w_kf.compose(traj.at(float(x)))) for x in s[:, j]])
    paths = (SplineTrajectory.from_linear(path(MID, MOTION)), gt)
    truth = ExposureRows(np.array([1.0, 2.0]), np.tile(rows, (2, 1)), np.stack([truth_at(p, 0) for p in paths]),
                         np.stack([truth_at(p, 1) for p in paths]))
    c = cam.as_dict()
    by_spline = row_path_error(truth, (stamps, controls), c, readout=RHO)
    starts, ends = np.stack([vec(T_w_kf.compose(p.start)) for p in paths]), np.stack([vec(T_w_kf.compose(p.end)) for p in paths])
    by_chord = row_path_error(truth, (stamps, starts, ends), c, readout=RHO)
    assert by_spline["reprojection_px"]["max"] < 0.02  # its own path (float32 records)
    assert by_chord["reprojection_px"]["max"] > 0.5  # the bent frame's chord misses the bend
    one = lambda e: row_path_error(ExposureRows(truth.stamps[:1], truth.rows[:1], truth.starts[:1], truth.ends[:1]), e, c, readout=RHO)
    assert abs(one((stamps, controls))["reprojection_px"]["mean"] - one((stamps, starts, ends))["reprojection_px"]["mean"]) < 0.02
