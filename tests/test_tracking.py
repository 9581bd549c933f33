"""The blur-aware tracker: Jacobian paths, accuracy vs the blur-unaware tracker, status, shapes.

Runs at 160x120 so the suite stays fast on 2 cores; the 640x480 accuracy and speed numbers come
from ``mbavo bench tracking`` (docs/benchmarks.md). Tests that generate a sequence or track a
frame are marked slow (``pytest -m "not slow"`` leaves them out)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import lineax as lx
import numpy as np
import pytest

from mbavo_jax.datasets import open_sequence
from mbavo_jax.geometry import ExposureTrajectory, Pose
from mbavo_jax.io import read_image_gray
from mbavo_jax.synthetic import SynthConfig, generate_sequence
from mbavo_jax.synthetic.generator import PRESETS
from mbavo_jax.config import TrackerConfig
from mbavo_jax.tracking import Keyframe, Status, choose_n, compiled_programs, constant_velocity_guess, exposure_from_velocity, track
from mbavo_jax.geometry.trajectory import RowClock
from mbavo_jax.tracking.level import LINEAR_SOLVER, LevelInputs, residual_pixels, solve_level
from mbavo_jax.tracking.tracker import _level_settings
from mbavo_jax.tracking.residuals import FrozenJacobian, LevelProblem, make_frozen_residual_fn, make_residual_fn, residuals_and_jacobian

SMALL = TrackerConfig(levels=3, points=(192, 128, 64), cell=(10, 7, 5), response_gamma=2.2, max_steps=(10, 12, 20))


def _sequence(tmp_path_factory, preset, frames=7):
    out = tmp_path_factory.mktemp(preset)
    cfg = SynthConfig(**{**PRESETS[preset], "frames": frames, "width": 160, "height": 120, "subframes": min(32, PRESETS[preset].get("subframes", 32)), "seed": 3, "real_textures": False})
    generate_sequence(cfg, out, progress=False)
    return open_sequence(out)


@pytest.fixture(scope="module")
def strong(tmp_path_factory):
    return _sequence(tmp_path_factory, "strong")


@pytest.fixture(scope="module")
def sharp_seq(tmp_path_factory):
    return _sequence(tmp_path_factory, "none")


def P(v):
    return Pose.from_vector(jnp.asarray(v, jnp.float32))


def case(seq, k, config):
    """Keyframe = sharp frame k with true depth; frame k+1 blurry; constant-velocity init; ground truth."""
    _, mids = seq.groundtruth
    _, S, E = seq.exposure_paths
    sharp = read_image_gray(seq[k].path.replace("/rgb/", "/sharp/"))
    kf = Keyframe.create(sharp, seq[k].depth, seq.camera, config)
    T_w_ref = P(mids[k])
    tau = seq.exposures[0]
    init = constant_velocity_guess(T_w_ref, P(mids[k - 1]), P(mids[k]), 1 / 30, tau)
    gt = ExposureTrajectory(T_w_ref.inverse().compose(P(S[k + 1])), T_w_ref.inverse().compose(P(E[k + 1])))
    return kf, seq[k + 1].image, init, gt


def endpoint_error(kf, est, gt):
    pts, cam = kf.points[0], kf.cameras[0]
    X = jax.vmap(cam.backproject)(jnp.asarray(pts.pixels[pts.valid]), jnp.asarray(pts.depths[pts.valid]))
    errs = []
    for a, b in ((est.start, gt.start), (est.end, gt.end)):
        pa = jax.vmap(lambda p: cam.project(a.inverse().apply(p)))(X)
        pb = jax.vmap(lambda p: cam.project(b.inverse().apply(p)))(X)
        errs.append(np.linalg.norm(np.asarray(pa - pb), axis=1))
    return float(np.median(np.concatenate(errs)))


def _problem(seq, jacobian, n=8, dtype=jnp.float32):
    kf, frame, init, _ = case(seq, 2, SMALL)
    pts = kf.points[0]
    cam = kf.cameras[0]
    rays, d, obs, mask, _ = residual_pixels(
        cam, jnp.asarray(frame ** 2.2), jnp.asarray(pts.pixels), jnp.asarray(pts.depths), jnp.asarray(pts.valid), init
    )
    cast = lambda t: jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype) if jnp.issubdtype(jnp.asarray(a).dtype, jnp.floating) else a, t)
    return LevelProblem(cast(kf.images[0]), cast(cam), cast(init).normalized(), cast(rays), cast(d), cast(obs), mask, n, jacobian)


@pytest.mark.slow
def test_structured_jacobians_match_plain_autodiff(strong):
    """Every structured path (per-virtual-pose rows chained through the trajectory Jacobian) equal
    jax.jacfwd of the whole residual, in float64, away from y = 0 too."""
    with jax.enable_x64(True):
        y = jnp.asarray(np.random.default_rng(0).normal(scale=[1e-3] * 12 + [0.05, 0.01]), jnp.float64)
        ref = None
        for jac in ("autodiff", "analytic", "tangent"):
            prob = _problem(strong, jac, dtype=jnp.float64)
            plain = jax.jacfwd(lambda yy: residuals_and_jacobian(yy, prob, False)[0])(y)
            r, J, valid = residuals_and_jacobian(y, prob, True)
            assert int(valid.sum()) > 200
            np.testing.assert_allclose(J, plain, atol=1e-8, rtol=1e-6)
            # the one pass that gives J gives the same residuals as the residual-only pass
            r_only, _, valid_only = residuals_and_jacobian(y, prob, False)
            np.testing.assert_array_equal(valid, valid_only)
            np.testing.assert_allclose(r, r_only, atol=1e-12)
            # the custom JVP is what optimistix's linearize sees
            f = make_residual_fn()
            _, lin = jax.linearize(lambda yy: f(yy, prob), y)
            np.testing.assert_allclose(jax.vmap(lin)(jnp.eye(14)).T, J, atol=1e-10)
            ref = J if ref is None else ref
            np.testing.assert_allclose(J, ref, atol=1e-8, rtol=1e-6)


@pytest.mark.slow
def test_a_frozen_jacobian_is_the_levels_start_one_with_exact_affine_columns(strong):
    """The chord method's linearisation (``make_frozen_residual_fn``): at the level's start y₀ it is
    the Jacobian there; at another y its path columns are y₀'s scaled by the gain e^(a − a₀), its
    affine columns those of the Jacobian at y, and its residuals those at y (float64)."""
    with jax.enable_x64(True):
        prob = _problem(strong, "tangent", dtype=jnp.float64)
        y0 = jnp.asarray([0.0] * 12 + [0.02, 0.003], jnp.float64)
        y1 = y0 + jnp.asarray(np.random.default_rng(1).normal(scale=[2e-3] * 12 + [0.05, 0.01]), jnp.float64)
        _, J0, _ = residuals_and_jacobian(y0, prob, True)
        r1, J1, valid1 = residuals_and_jacobian(y1, prob, True)
        frozen, f = FrozenJacobian(J0[:, :12], y0[12]), make_frozen_residual_fn()
        for y, want in ((y0, J0), (y1, None)):
            (r, valid), lin = jax.linearize(lambda yy: f(yy, prob, frozen), y)
            J = jax.vmap(lambda e: lin(e)[0])(jnp.eye(14)).T
            if want is not None:
                np.testing.assert_allclose(J, want, atol=1e-10)
        np.testing.assert_allclose(r, r1, atol=1e-12)
        np.testing.assert_array_equal(valid, valid1)
        np.testing.assert_allclose(J[:, 12:], J1[:, 12:], atol=1e-10)
        both = np.asarray(valid1 & (jnp.abs(J0[:, :12]).sum(1) > 0))
        np.testing.assert_allclose(J[both, :12], np.exp(float(y1[12] - y0[12])) * J0[both, :12], rtol=1e-10, atol=1e-12)
        assert np.abs(J[both, :12] - J1[both, :12]).max() > 1e-3 * np.abs(J1[both, :12]).max()  # frozen, not recomputed


@pytest.mark.slow
def test_a_frozen_jacobian_tracks_as_the_per_step_one(strong):
    """Levels that keep their start's photometric Jacobian (all but the coarsest, ``tracker.fresh_jacobian_levels``,
    the default) land where levels that recompute it at every step do, on strong blur."""
    for k in (1, 3, 5):
        errs = {}
        for name, cfg in (("frozen", SMALL), ("per_step", dataclasses.replace(SMALL, fresh_jacobian_levels=SMALL.levels))):
            kf, frame, init, gt = case(strong, k, cfg)
            traj, status, diag = track(kf, frame, init, cfg)
            assert status.ok, (name, k, status, diag)
            errs[name] = endpoint_error(kf, traj, gt)
        assert errs["frozen"] < 0.3 and errs["frozen"] <= 1.2 * errs["per_step"] + 0.02, (k, errs)


@pytest.mark.slow
@pytest.mark.parametrize("lam", [1e-6, 1.0, 1e3])
def test_lm_linear_solver_matches_float64_least_squares(strong, lam):
    """The LM step from the level's linear solver (normal equations, Cholesky, float32) on a real
    Jacobian equals the float64 least-squares solution of [J; √λ I] δ = [r; 0]."""
    prob = _problem(strong, "analytic", n=16)
    r, J, valid = residuals_and_jacobian(jnp.zeros(14, jnp.float32), prob, True)
    assert int(valid.sum()) > 200
    A = jnp.concatenate([J, np.float32(np.sqrt(lam)) * jnp.eye(14, dtype=J.dtype)])
    b = jnp.concatenate([r, jnp.zeros(14, r.dtype)])
    step = lx.linear_solve(lx.MatrixLinearOperator(A), b, LINEAR_SOLVER).value
    ref = np.linalg.lstsq(np.asarray(A, np.float64), np.asarray(b, np.float64), rcond=None)[0]
    assert np.linalg.norm(np.asarray(step, np.float64) - ref) <= 1e-4 * np.linalg.norm(ref)


@pytest.mark.slow
def test_blur_aware_beats_blur_unaware_on_strong_blur(strong):
    errs = {"n64": [], "n1": []}
    for k in (1, 3, 5):
        for name, cfg in (("n64", SMALL), ("n1", dataclasses.replace(SMALL, blur_aware=False))):
            kf, frame, init, gt = case(strong, k, cfg)
            traj, status, diag = track(kf, frame, init, cfg)
            assert status.ok, (name, k, status, diag)
            errs[name].append(endpoint_error(kf, traj, gt))
    med64, med1 = np.median(errs["n64"]), np.median(errs["n1"])
    assert med64 < 0.3, errs  # ~5 px blur at 160x120
    assert med1 > 4 * med64, errs


@pytest.mark.slow
def test_sharp_frames_n64_no_worse_than_n1(sharp_seq):
    for k in (2, 4):
        e = {}
        for name, cfg in (("n64", SMALL), ("n1", dataclasses.replace(SMALL, blur_aware=False))):
            kf, frame, init, gt = case(sharp_seq, k, cfg)
            traj, status, _ = track(kf, frame, init, cfg)
            assert status.ok
            e[name] = endpoint_error(kf, traj, gt)
        assert e["n64"] <= e["n1"] * 1.2 + 0.05, e


def mid_distance_px(kf, a, b) -> float:
    """Median image distance (px) between the keyframe's points seen from the middles of two exposure paths."""
    pts, cam = kf.points[0], kf.cameras[0]
    X = jax.vmap(cam.backproject)(jnp.asarray(pts.pixels[pts.valid]), jnp.asarray(pts.depths[pts.valid]))
    pa = jax.vmap(lambda p: cam.project(a.middle().inverse().apply(p)))(X)
    pb = jax.vmap(lambda p: cam.project(b.middle().inverse().apply(p)))(X)
    return float(np.median(np.linalg.norm(np.asarray(pa - pb), axis=1)))


@pytest.mark.slow
def test_a_mildly_blurred_pair_gives_n64_and_n1_the_same_pose(tmp_path_factory):
    """Issue 57: on mild blur (the preset's 2-5 px at 320x240) the blur model must cost nothing: n = 64
    and n = 1 place the frame's middle pose within a pixel of each other and of the truth."""
    out = tmp_path_factory.mktemp("mild_pair")
    cfg = SynthConfig(**{**PRESETS["mild"], "frames": 5, "width": 320, "height": 240, "subframes": 32, "seed": 4, "real_textures": False})
    generate_sequence(cfg, out, progress=False)
    seq, config = open_sequence(out), TrackerConfig(response_gamma=2.2)
    for k in (2, 3):
        kf, frame, init, gt = case(seq, k, config)
        n64, s64, _ = track(kf, frame, init, config)
        n1, s1, _ = track(kf, frame, init, dataclasses.replace(config, blur_aware=False))
        assert s64.ok and s1.ok
        apart, off64, off1 = mid_distance_px(kf, n64, n1), mid_distance_px(kf, n64, gt), mid_distance_px(kf, n1, gt)
        assert apart < 1.0 and off64 < 1.0 and off1 < 1.0, (k, apart, off64, off1)


@pytest.mark.slow
def test_every_jacobian_path_gives_the_same_track(strong):
    out = []
    for jac in ("tangent", "analytic", "autodiff"):
        cfg = dataclasses.replace(SMALL, jacobian=jac)
        kf, frame, init, gt = case(strong, 2, cfg)
        traj, status, _ = track(kf, frame, init, cfg)
        out.append(np.concatenate([np.asarray(traj.start.to_vector()), np.asarray(traj.end.to_vector())]))
    np.testing.assert_allclose(out[0], out[1], atol=2e-4)
    np.testing.assert_allclose(out[0], out[2], atol=2e-4)


@pytest.mark.slow
def test_adaptive_n(strong, sharp_seq):
    assert choose_n(0.2, TrackerConfig()) == 2 and choose_n(5.0, TrackerConfig()) == 16 and choose_n(500, TrackerConfig()) == 64
    cfg = dataclasses.replace(SMALL, n_mode="adaptive")
    kf, frame, init, gt = case(sharp_seq, 3, cfg)
    _, status, diag = track(kf, frame, init, cfg)
    assert status.ok and max(level["n"] for level in diag["levels"]) <= 2
    e = {}
    for name, c in (("adaptive", cfg), ("fixed", SMALL)):
        kf, frame, init, gt = case(strong, 3, c)
        traj, status, diag = track(kf, frame, init, c)
        e[name] = endpoint_error(kf, traj, gt)
    assert e["adaptive"] <= e["fixed"] + 0.1, e


@pytest.mark.slow
def test_status_never_raises(strong):
    kf, frame, init, gt = case(strong, 2, SMALL)
    black = track(kf, np.zeros_like(frame), init, SMALL)
    assert black.status == Status.TOO_FEW_POINTS
    noise = track(kf, np.random.default_rng(0).uniform(size=frame.shape).astype(np.float32), init, SMALL)
    assert not noise.status.ok
    nan = frame.copy()
    nan[10:40, 10:40] = np.nan  # a few percent of the frame without data: those pixels are left out
    r = track(kf, nan, init, SMALL)
    assert np.all(np.isfinite(np.asarray(r.trajectory.start.t))) and np.all(np.isfinite(np.asarray(r.trajectory.end.q)))
    assert r.status.ok and endpoint_error(kf, r.trajectory, gt) < 0.3, (r.status, endpoint_error(kf, r.trajectory, gt))
    void = track(kf, np.full_like(frame, np.nan), init, SMALL)  # no data at all: the frame is dropped
    assert void.status == Status.TOO_FEW_POINTS and not void.status.ok
    assert np.all(np.isfinite(np.asarray(void.trajectory.start.t)))
    empty = Keyframe.create(np.zeros_like(frame), np.full(frame.shape, np.nan, np.float32), strong.camera, SMALL)
    assert track(empty, frame, init, SMALL).status == Status.TOO_FEW_POINTS


@pytest.mark.slow
def test_hypotheses_recover_from_a_bad_initial_guess(strong):
    kf, frame, _, gt = case(strong, 4, SMALL)
    bad_rot = Pose(jnp.asarray([0.0, np.sin(np.deg2rad(6)), 0.0, np.cos(np.deg2rad(6))], jnp.float32), jnp.zeros(3))
    bad = ExposureTrajectory(gt.start.compose(bad_rot), gt.end.compose(bad_rot))
    r = track(kf, frame, bad, SMALL)
    assert r.status.ok and r.diagnostics["hypotheses_tried"] > 1
    err = endpoint_error(kf, r.trajectory, gt)
    assert err < 1.0, (err, r.diagnostics)


@pytest.mark.slow
def test_no_recompilation_after_the_first_frame(strong):
    """Fixed n: every frame of a sequence (new keyframes: new points, same shapes) runs the level
    programs compiled for the first one; a different n compiles new ones (the counter counts)."""
    kf, frame, init, _ = case(strong, 1, SMALL)
    track(kf, frame, init, SMALL)
    before = compiled_programs()
    assert before >= 1
    for k in (2, 3, 4):
        kf, frame, init, _ = case(strong, k, SMALL)  # a new keyframe: new points, same shapes
        track(kf, frame, init, SMALL)
    assert compiled_programs() == before
    other_n = dataclasses.replace(SMALL, n=40)  # an n no other test uses: its programs are new here
    kf, frame, init, _ = case(strong, 2, other_n)
    track(kf, frame, init, other_n)
    assert compiled_programs() > before


# ------------------------------------------------------------------ optional depth term (RGB-D)


def test_depth_points_fixed_shape_skip_edges_and_holes():
    from mbavo_jax.tracking.geometric import select_depth_points

    depth = np.full((60, 80), 2.0, np.float32)
    depth[:, 40:] = 3.0  # a depth edge at column 40
    depth[:10, :] = np.nan  # a hole
    pts = select_depth_points(depth, stride=4)
    again = select_depth_points(np.full((60, 80), 2.0, np.float32), stride=4)
    assert pts.pixels.shape == again.pixels.shape  # one slot per cell, whatever the content
    u, v = pts.pixels[:, 0], pts.pixels[:, 1]
    near_edge = np.abs(u - 39.5) < 1.6
    assert not pts.valid[near_edge].any()
    assert not pts.valid[v < 11].any()
    assert pts.valid[~near_edge & (v > 11)].all()
    assert np.allclose(pts.depths[pts.valid], np.where(u[pts.valid] < 40, 2.0, 3.0))


@pytest.mark.slow
def test_depth_residuals_vanish_at_truth_and_have_finite_gradients(strong):
    from mbavo_jax.tracking.geometric import depth_residuals, select_depth_points

    kf, _, _, gt = case(strong, 2, SMALL)
    cam = kf.cameras[0]
    dp = select_depth_points(kf.depth, 8)
    cur = np.nan_to_num(strong[3].depth, nan=0.0)
    cur[:40, :40] = 0.0  # a hole in the current depth map
    args = (cam, jnp.asarray(cur), jnp.asarray(dp.pixels), jnp.asarray(dp.depths), jnp.asarray(dp.valid), 0.02)
    r, ok = depth_residuals(gt.middle(), *args)
    assert int(ok.sum()) > 0.5 * dp.valid.sum() - 40
    assert float(np.median(np.abs(np.asarray(r)[np.asarray(ok)]))) < 0.3  # in σ of the Kinect noise model
    moved = Pose(gt.middle().q, gt.middle().t + jnp.array([0.0, 0.0, 0.05]))
    r2, ok2 = depth_residuals(moved, *args)
    assert float(np.median(np.abs(np.asarray(r2)[np.asarray(ok2)]))) > 5 * float(np.median(np.abs(np.asarray(r)[np.asarray(ok)])))
    grad = jax.grad(lambda v: jnp.sum(depth_residuals(Pose.from_vector(v), *args)[0] ** 2))(gt.middle().to_vector())
    assert np.all(np.isfinite(np.asarray(grad))) and np.any(np.asarray(grad) != 0)


@pytest.mark.slow
def test_depth_residuals_truncate_occluded_points(strong):
    """A foreground object in the current depth map hides keyframe points: their residuals are
    hundreds of σ; they are truncated at ``outlier`` σ instead of pulling the pose harder."""
    from mbavo_jax.tracking.geometric import depth_residuals, select_depth_points

    kf, _, _, gt = case(strong, 2, SMALL)
    dp = select_depth_points(kf.depth, 8)
    cur = np.nan_to_num(strong[3].depth, nan=0.0)
    cur[30:90, 40:120] = 0.3  # an object 0.3 m from the camera
    args = (kf.cameras[0], jnp.asarray(cur), jnp.asarray(dp.pixels), jnp.asarray(dp.depths), jnp.asarray(dp.valid), 0.02, (0.0005, 0.0))
    r_all, ok_all = (np.asarray(x) for x in depth_residuals(gt.middle(), *args))
    r_cut, ok_cut = (np.asarray(x) for x in depth_residuals(gt.middle(), *args, 20.0))
    hidden = ok_all & (np.abs(r_all) >= 20.0)
    assert hidden.sum() >= 10 and np.all(r_all[hidden] < -100)  # the object is nearer than the scene
    assert np.array_equal(ok_cut, ok_all) and np.all(r_cut[hidden] == -20.0)
    assert np.allclose(r_cut[ok_cut & ~hidden], r_all[ok_cut & ~hidden])


@pytest.mark.slow
def test_depth_term_gains_nothing_by_pushing_points_out(strong):
    """The depth term's cost inside the solver never falls as the mid pose moves away from the
    truth: a residual beyond ``outlier`` σ costs as much as one at the cut (a cut to zero let the
    solver lower the cost by pushing every point past it)."""
    from mbavo_jax.tracking.geometric import select_depth_points
    from mbavo_jax.tracking.level import DepthTerm, depth_residuals_block

    kf, _, _, gt = case(strong, 2, SMALL)
    dp = select_depth_points(kf.depth, 8)
    f32 = lambda v: jnp.asarray(v, jnp.float32)
    term = DepthTerm(f32(np.nan_to_num(strong[3].depth, nan=0.0)), f32(dp.pixels), f32(dp.depths), jnp.asarray(dp.valid),
                     f32(0.03), f32(3.0), f32(20.0), f32(0.02), f32([0.0005, 0.0]))
    mid = gt.middle()
    moved = [Pose(mid.q, mid.t + jnp.array([0.0, 0.0, dz])) for dz in np.linspace(0.0, 0.06, 13)]
    cost = [float(jnp.sum(depth_residuals_block(ExposureTrajectory(p, p), kf.cameras[0], term) ** 2)) for p in moved]
    assert cost[-1] > 10 * cost[0], cost
    assert all(b >= a * (1 - 1e-5) for a, b in zip(cost, cost[1:])), cost


@pytest.mark.slow
def test_stiff_depth_term_with_an_occluder_still_lands(strong):
    """Exact depth weighted 100x the maximum-likelihood balance and an object in front of the
    scene: the mid pose must stay as good as the images-only estimate. Needs both guards: occluded
    points truncated (``depth_outlier``) and no depth on the coarsest level (``depth_levels`` 2 of 3,
    as the docstring advises for stiff weights)."""
    stiff = dataclasses.replace(SMALL, depth_weight=1.0, depth_sigma=(0.0005, 0.0), depth_levels=2)
    unguarded = dataclasses.replace(stiff, depth_outlier=1e9, depth_levels=SMALL.levels)
    err = {"images": [], "stiff": [], "unguarded": []}
    for k in range(1, 5):
        cur = np.array(strong[k + 1].depth)
        cur[30:90, 40:120] = 0.3
        for name, cfg in (("images", SMALL), ("stiff", stiff), ("unguarded", unguarded)):
            kf, frame, init, gt = case(strong, k, cfg)
            r = track(kf, frame, init, cfg, depth=cur)
            err[name].append(float(np.linalg.norm(np.asarray(r.trajectory.middle().t - gt.middle().t))))
            if name == "stiff":
                assert [lv["depth_term"] for lv in r.diagnostics["levels"]] == [False, True, True]  # coarse to fine
    assert np.mean(err["stiff"]) < np.mean(err["images"]), err
    assert np.mean(err["stiff"]) < 0.5 * np.mean(err["unguarded"]), err


@pytest.mark.slow
def test_depth_term_off_changes_nothing_and_checks_shape(strong):
    kf, frame, init, _ = case(strong, 2, SMALL)
    a = track(kf, frame, init, SMALL)
    b = track(kf, frame, init, SMALL, depth=strong[3].depth)  # depth_weight = 0: depth ignored
    assert np.allclose(np.asarray(a.trajectory.start.t), np.asarray(b.trajectory.start.t))
    assert not b.diagnostics["depth_term"]
    with pytest.raises(ValueError, match="depth shape"):
        track(kf, frame, init, dataclasses.replace(SMALL, depth_weight=1.0), depth=np.ones((10, 10), np.float32))


@pytest.mark.slow
def test_exposure_from_velocity_matches_the_generated_exposure(strong):
    """The exposure path of a frame about its own mid pose, from the motion to the next frame
    (constant velocity: how the first keyframe gets its path), against the generator's path."""
    _, mids = strong.groundtruth
    _, S, E = strong.exposure_paths
    tau = strong.exposures[0]
    kf = Keyframe.create(strong[2].image, strong[2].depth, strong.camera, SMALL)
    for k in (1, 2, 3):
        T_mid = P(mids[k])
        V = T_mid.inverse().compose(P(mids[k + 1]))
        est = exposure_from_velocity(V, 1 / 30, tau)
        gt = ExposureTrajectory(T_mid.inverse().compose(P(S[k])), T_mid.inverse().compose(P(E[k])))
        assert np.allclose(np.asarray(est.middle().to_vector()), [0, 0, 0, 0, 0, 0, 1], atol=1e-5)
        still = ExposureTrajectory(Pose.identity(), Pose.identity())
        blur = endpoint_error(kf, still, gt)  # how far the exposure endpoints are from the mid pose
        assert blur > 2.0 and endpoint_error(kf, est, gt) < 0.1 * blur, (k, blur, endpoint_error(kf, est, gt))


@pytest.mark.slow
def test_depth_term_pins_the_mid_pose(strong):
    """With the frame's exact depth (σ = 0.5 mm) the mid-exposure translation error drops well below
    the images-only estimate (both n = 64), while the blur (endpoint error) stays as good."""
    with_depth = dataclasses.replace(SMALL, depth_weight=0.01, depth_sigma=(0.0005, 0.0))
    err = {False: [], True: []}
    ep = {False: [], True: []}
    for k in range(1, 5):
        for use in (False, True):
            kf, frame, init, gt = case(strong, k, with_depth if use else SMALL)
            r = track(kf, frame, init, with_depth if use else SMALL, depth=strong[k + 1].depth)
            assert r.status.ok and r.diagnostics["depth_term"] == use
            err[use].append(float(np.linalg.norm(np.asarray(r.trajectory.middle().t - gt.middle().t))))
            ep[use].append(endpoint_error(kf, r.trajectory, gt))
    assert np.mean(err[True]) < 0.7 * np.mean(err[False]), err
    assert np.mean(ep[True]) < 1.1 * np.mean(ep[False]), ep


@pytest.mark.slow
def test_a_level_reports_the_residuals_at_the_point_it_returns(strong):
    """A level's rms and valid count come from the solver's last accepted linearisation: they equal a
    fresh residual pass at the path and brightness it returns, also when the step budget stops it
    mid-way (a lagging record would be a step behind)."""
    config = dataclasses.replace(SMALL, outlier_sigma=0.0, max_steps=(3, 3, 3))
    kf, frame, init, _ = case(strong, 2, config)
    image = jnp.asarray(frame ** 2.2)
    inputs = LevelInputs(kf.images[0], kf.cameras[0], image, *kf.points[0].on_device, init, jnp.zeros(2, jnp.float32),
                         RowClock.create(0.0, kf.cameras[0].height, 0))
    res = solve_level(inputs, _level_settings(config, 0, 8), None, None)
    assert int(res.steps) == 3 and float(res.rms) < 0.9 * float(res.rms_init)
    rays, d, obs, mask, _ = residual_pixels(kf.cameras[0], image, *kf.points[0].on_device, init)
    prob = LevelProblem(kf.images[0], kf.cameras[0], res.trajectory, rays, d, obs, mask, 8, config.jacobian)
    r, _, valid = residuals_and_jacobian(jnp.concatenate([jnp.zeros(12, jnp.float32), res.affine_ab]), prob, False)
    assert int(valid.sum()) == int(res.valid)
    np.testing.assert_allclose(float(res.rms), float(jnp.sqrt(jnp.sum(r * r) / valid.sum().astype(r.dtype))), rtol=1e-4)
