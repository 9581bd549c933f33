"""The monocular back-end: the window (mono.window) and the windowed photometric bundle adjustment with
the Schur complement and marginalisation (mono.ba).

Small windows of smooth random images check the algebra in float64 (structured Jacobians against
``jax.jacfwd``, normal equations against JᵀWJ, Schur against dense, marginalisation against the whole
problem); a window rendered from the default scene checks that bundle adjustment returns to the truth.
"""

from __future__ import annotations

import dataclasses

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.config import MonoConfig
from mbavo_jax.errors import ArgumentError
from mbavo_jax.geometry import quaternion as quat
from mbavo_jax.geometry.camera import PinholeCamera
from mbavo_jax.geometry.pose import Pose
from mbavo_jax.geometry.trajectory import ExposureTrajectory
from mbavo_jax.image import downsample
from mbavo_jax.mono import ba, depthmap
from mbavo_jax.mono.depthmap import project_points
from mbavo_jax.mono.window import Prior, Window, add_keyframe, add_points, insert_points, points_of, world_points
from mbavo_jax.synthetic.generator import camera_path
from mbavo_jax.synthetic.scene import default_scene, render_exposure, scene_arrays
from mbavo_jax.tracking.points import downsample_depth, select_points

CFG = MonoConfig()
HUBER, OUTLIER = CFG.ba_huber, CFG.ba_outlier


# ------------------------------------------------------------------------------- small windows


def _camera(width, height, dtype=jnp.float32) -> PinholeCamera:
    f = 525.0 * width / 640.0  # the generator's camera
    return PinholeCamera.create(f, f, (width - 1) / 2, (height - 1) / 2, width, height, dtype=dtype)


def _smooth_image(rng, height, width) -> np.ndarray:
    img = cv2.GaussianBlur(rng.random((height, width)).astype(np.float32), (0, 0), 2.0)
    return 0.1 + 0.8 * (img - img.min()) / (img.max() - img.min())


SMALL_POSES = [(np.zeros(3), np.zeros(3)), (np.array([0.01, -0.02, 0.005]), np.array([0.05, 0.0, 0.01])),
               (np.array([-0.01, 0.01, 0.0]), np.array([-0.03, 0.02, -0.02]))]


def _small_window(dtype, k=3, p=50, seed=0, width=64, height=48) -> Window:
    """3 keyframes (smooth random images, small motions, non-zero affine) and 48 points at 2-5 m."""
    rng = np.random.default_rng(seed)
    win = Window.empty(k, p, height, width, dtype=dtype)
    for i, (r, t) in enumerate(SMALL_POSES):
        T = Pose(quat.exp(jnp.asarray(r, dtype)), jnp.asarray(t, dtype))
        win, slot = add_keyframe(win, _smooth_image(rng, height, width), T, affine=(0.05 * i, 0.01 * i))
        n = 16
        px = np.stack([rng.uniform(4, width - 5, n), rng.uniform(4, height - 5, n)], 1)
        win, _ = add_points(win, slot, px, rng.uniform(0.2, 0.5, n))
    return win


def _full_jacobian(lin: ba.Linearization, win: Window) -> np.ndarray:
    """The dense Jacobian (P·K·8, 8K + P) assembled from the structured blocks."""
    J = np.asarray(lin.J)
    p, k = J.shape[:2]
    m = 8 * k
    full = np.zeros((p, k, 8, m + p))
    host = np.asarray(win.host)
    for i in range(p):
        for t in range(k):
            h = host[i]
            full[i, t, :, 8 * h:8 * h + 8] += J[i, t, :, :8]
            full[i, t, :, 8 * t:8 * t + 8] += J[i, t, :, 8:16]
            full[i, t, :, m + i] = J[i, t, :, 16]
    return full.reshape(p * k * 8, m + p)


_LINEARIZE = jax.jit(ba.linearize)  # module-level, so that tests of one shape share one compilation
_NORMAL_EQUATIONS = jax.jit(ba.normal_equations)


def _linearize(win, camera):
    return _LINEARIZE(win, camera, HUBER, OUTLIER)


@pytest.mark.slow
def test_structured_jacobians_and_normal_equations_match_dense(x64):
    win = _small_window(jnp.float64)
    cam = _camera(64, 48, jnp.float64)
    lin = _linearize(win, cam)
    assert lin.J.dtype == jnp.float64 and int(lin.visible.sum()) > 40
    m = 8 * win.slots + win.capacity
    dense = jax.jit(jax.jacfwd(ba.residual_vector, argnums=2))(win, cam, jnp.zeros(m, jnp.float64))
    full = _full_jacobian(lin, win)
    assert np.abs(full).max() > 1.0
    np.testing.assert_allclose(full, np.asarray(dense), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(lin.r).ravel(), np.asarray(ba.residual_vector(win, cam)), atol=1e-12)
    # the assembled normal equations are JᵀWJ and JᵀWr of the dense Jacobian
    neq = _NORMAL_EQUATIONS(lin, win)
    w = np.asarray(lin.w).ravel()
    H = full.T @ (full * w[:, None])
    b = full.T @ (w * np.asarray(lin.r).ravel())
    mc = 8 * win.slots
    np.testing.assert_allclose(np.asarray(neq.H_cc), H[:mc, :mc], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(neq.H_cd), H[mc:, :mc], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(neq.H_dd), np.diag(H)[mc:], rtol=1e-9, atol=1e-9)
    assert np.abs(H[mc:, mc:] - np.diag(np.diag(H)[mc:])).max() == 0.0  # the depth block is diagonal
    np.testing.assert_allclose(np.asarray(neq.b_c), b[:mc], rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(np.asarray(neq.b_d), b[mc:], rtol=1e-9, atol=1e-12)


@jax.jit
def _system(win, camera):
    """The BA's normal equations at the window's state: photometric + the anchor without a prior, +
    the prior alone with one (no distance prior, so that the linear problems compare exactly)."""
    data = ba.normal_equations(ba.linearize(win, camera, HUBER, OUTLIER), win)
    return ba.system(win, camera, HUBER, OUTLIER, ba.make_anchor(win, data, scale_with_prior=False))[0]


@pytest.mark.slow
def test_schur_solve_equals_dense_solve(x64):
    win = _small_window(jnp.float64)
    win = dataclasses.replace(win, idepth=win.idepth * 1.1)  # away from any optimum
    neq = _system(win, _camera(64, 48, jnp.float64))
    for lam in (0.0, 1e-2):
        dc, dd = ba.schur_solve(neq, lam)
        dc_ref, dd_ref = ba.dense_solve(neq, lam)
        assert np.abs(np.asarray(dc)).max() > 1e-6
        np.testing.assert_allclose(np.asarray(dc), np.asarray(dc_ref), rtol=1e-7, atol=1e-10)
        np.testing.assert_allclose(np.asarray(dd), np.asarray(dd_ref), rtol=1e-7, atol=1e-10)


def _sum_equations(a: ba.NormalEquations, b: ba.NormalEquations) -> ba.NormalEquations:
    return jax.tree.map(lambda x, y: x + y, a, b)


@pytest.mark.slow
def test_marginalising_then_solving_equals_solving_the_whole(x64):
    """Linear case: one Gauss-Newton step of the whole problem (keyframe 1, the points it hosts and every
    other residual except those of other points into keyframe 1, which DSO drops) equals the step of
    the window after marginalising keyframe 1 into the prior."""
    cam = _camera(64, 48, jnp.float64)
    win = _small_window(jnp.float64)
    win = dataclasses.replace(win, idepth=win.idepth * 1.1)
    m = 8 * win.slots
    H0 = jnp.diag(jnp.linspace(50.0, 80.0, m))  # an earlier prior holding the gauge, linearised here
    win = dataclasses.replace(win, prior=Prior(H0, jnp.linspace(-1.0, 1.0, m), win.poses, win.affine))
    slot = 1
    hosted = win.point_valid & (win.host == slot)
    own = dataclasses.replace(win, point_valid=hosted)
    rest = dataclasses.replace(win, point_valid=win.point_valid & ~hosted, kf_valid=win.kf_valid.at[slot].set(False))
    data = _sum_equations(_NORMAL_EQUATIONS(_linearize(own, cam), own), _NORMAL_EQUATIONS(_linearize(rest, cam), rest))
    whole = dataclasses.replace(data, H_cc=data.H_cc + win.prior.H, b_c=data.b_c + win.prior.b)
    dc, dd = ba.dense_solve(whole, 0.0)

    after = ba.marginalize(win, slot, cam, CFG)
    assert not bool(after.kf_valid[slot]) and not bool((after.point_valid & (after.host == slot)).any())
    prior_rows = np.asarray(after.prior.H)[8 * slot:8 * slot + 8]
    assert np.abs(prior_rows).max() == 0.0
    dc2, dd2 = ba.schur_solve(_system(after, cam), 0.0)
    keep = np.repeat(np.arange(win.slots) != slot, 8)
    assert np.abs(np.asarray(dc)[keep]).max() > 1e-5
    np.testing.assert_allclose(np.asarray(dc2)[keep], np.asarray(dc)[keep], rtol=1e-6, atol=1e-10)
    np.testing.assert_allclose(np.asarray(dc2)[~keep], 0.0)
    others = np.asarray(after.point_valid)
    np.testing.assert_allclose(np.asarray(dd2)[others], np.asarray(dd)[others], rtol=1e-6, atol=1e-10)


def test_window_helpers():
    cam = _camera(64, 48)
    win = Window.empty(2, 5, 48, 64)
    with pytest.raises(ArgumentError, match="empty"):
        add_points(win, 0, np.zeros((1, 2)), np.ones(1))
    T = Pose(quat.exp(jnp.array([0.0, 0.1, 0.0])), jnp.array([1.0, 2.0, 3.0]))
    win, s0 = add_keyframe(win, np.full((48, 64), 0.5, np.float32), Pose.identity())
    win, s1 = add_keyframe(win, np.full((48, 64), 0.25, np.float32), T)
    assert (s0, s1) == (0, 1) and np.asarray(win.stamp).tolist() == [0, 1]
    with pytest.raises(ArgumentError, match="full"):
        add_keyframe(win, np.zeros((48, 64), np.float32), T)
    win, n = add_points(win, s1, [[10.0, 20.0], [30.0, 5.0], [3.0, 4.0]], [0.5, 0.25, 1.0])
    assert n == 3
    win, n = add_points(win, s0, np.zeros((4, 2)), np.ones(4))
    assert n == 2 and int(win.point_valid.sum()) == 5
    pixels, depths = points_of(win, s1)
    np.testing.assert_allclose(depths, [2.0, 4.0, 1.0])
    xyz, value = world_points(win, cam)
    assert xyz.shape == (5, 3) and np.allclose(value[:3], 0.25) and np.allclose(value[3:], 0.5)
    X = cam.backproject(jnp.array([10.0, 20.0]), 2.0)
    np.testing.assert_allclose(xyz[0], np.asarray(T.apply(X)), rtol=1e-5)



def test_insert_points_fills_free_slots_in_order_and_stops_when_full():
    win = Window.empty(2, 6, 48, 64)
    win, s0 = add_keyframe(win, np.full((48, 64), 0.5, np.float32), Pose.identity())
    win, s1 = add_keyframe(win, np.full((48, 64), 0.25, np.float32), Pose.identity())
    win, _ = add_points(win, s0, np.zeros((3, 2)), np.ones(3))
    win = dataclasses.replace(win, point_valid=win.point_valid.at[1].set(False))  # slots 1, 3, 4, 5 free
    pixels = np.arange(12, dtype=np.float32).reshape(6, 2)
    mask = np.array([True, False, True, True, True, True])
    out, added = insert_points(win, jnp.asarray(s1, jnp.int32), pixels, 1.0 + np.arange(6, dtype=np.float32), mask)
    assert np.asarray(added).tolist() == [True, False, True, True, True, False]  # 4 free slots for 5 points
    assert np.asarray(out.point_valid).all()
    np.testing.assert_array_equal(np.asarray(out.host), [s0, s1, s0, s1, s1, s1])
    np.testing.assert_array_equal(np.asarray(out.idepth)[[1, 3, 4, 5]], [1.0, 3.0, 4.0, 5.0])
    np.testing.assert_array_equal(np.asarray(out.pixels)[[1, 3, 4, 5]], pixels[[0, 2, 3, 4]])
    np.testing.assert_array_equal(np.asarray(out.idepth)[[0, 2]], [1.0, 1.0])  # the others untouched


def test_adding_points_of_many_counts_compiles_few_programs():
    win = Window.empty(2, 2000, 48, 64)
    win, slot = add_keyframe(win, np.full((48, 64), 0.5, np.float32), Pose.identity())
    add_points(win, slot, np.zeros((1, 2)), np.ones(1))
    before = insert_points._cache_size()
    for n in (3, 17, 100, 255):
        win2, added = add_points(win, slot, np.zeros((n, 2)), np.ones(n))
        assert added == n and int(win2.point_valid.sum()) == n
    assert insert_points._cache_size() == before  # one padded length for all of these



def test_project_points_pads_without_changing_the_result():
    cam = _camera(64, 48)
    T = Pose(quat.exp(jnp.array([0.02, -0.1, 0.05])), jnp.array([0.1, -0.2, 0.3]))
    rng = np.random.default_rng(1)
    xyz = np.concatenate([rng.uniform(-1, 1, (40, 2)), rng.uniform(-1, 4, (40, 1))], 1).astype(np.float32)
    direct = [np.asarray(v) for v in jax.vmap(lambda X: T.apply(X))(jnp.asarray(xyz)).T]
    project_points(cam, T, xyz[:1])
    before = depthmap._project._cache_size()
    for n in (5, 40):
        x, z, ok = project_points(cam, T, xyz[:n])
        assert x.shape == (n, 2) and z.shape == ok.shape == (n,)
        np.testing.assert_allclose(z, direct[2][:n], rtol=1e-5)
        front = direct[2][:n] > 1e-6
        np.testing.assert_allclose(x[front, 0], cam.fx * direct[0][:n][front] / direct[2][:n][front] + cam.cx, rtol=1e-4)
        assert not ok[~front].any()
    assert depthmap._project._cache_size() == before


# ------------------------------------------------------------------- a window of the default scene

W, H, KEYFRAMES, PER_KF = 160, 120, 5, 60
BA_CFG = MonoConfig(ba_iterations=15)


def _render_keyframes(n: int):
    """n sharp keyframes of the default scene along ``camera_path`` (0.1 s apart) at 160x120, rendered
    at 640x480 and box-downsampled twice, then blurred by σ = 1 px (camera optics): the scene's
    textures hold several texels per 160x120 pixel, and without low-pass filtering the images do not
    agree between views even at the true poses. Returns (camera, images, depths, poses)."""
    cam = _camera(W, H)
    big = _camera(4 * W, 4 * H)
    arrays = scene_arrays(default_scene(0, use_real_textures=False))  # the same images with or without ../shared/data
    images, depths, poses = [], [], []
    for i in range(n):
        T = camera_path(1.0 + 0.1 * i, 0.6, 60.0, 0)
        _, sharp, depth = render_exposure(arrays, big, jax.tree.map(lambda a: a[None], T), T, 2.2)
        sharp, depth = np.asarray(downsample(downsample(sharp))), downsample_depth(downsample_depth(np.asarray(depth)))
        images.append(cv2.GaussianBlur(sharp, (0, 0), 1.0))
        depths.append(depth)
        poses.append(T)
    return cam, images, depths, poses


def _without_depth_edges(depth: np.ndarray) -> np.ndarray:
    """``depth`` with NaN where a 3x3 neighbourhood spans more than 3 % (occlusion edges, whose
    downsampled depth mixes two surfaces and is not a true depth of the pixel)."""
    k = np.ones((3, 3), np.uint8)
    return np.where(cv2.dilate(depth, k) > 1.03 * cv2.erode(depth, k), np.nan, depth).astype(np.float32)


@pytest.fixture(scope="module")
def scene_window():
    """(camera, true window): 5 keyframes, each hosting its 60 strongest-gradient pixels (off depth
    edges) at their true depth."""
    cam, images, depths, poses = _render_keyframes(KEYFRAMES)
    win = Window.empty(KEYFRAMES, KEYFRAMES * PER_KF, H, W)
    for img, dep, T in zip(images, depths, poses):
        win, slot = add_keyframe(win, img, T)
        pts = select_points(img, _without_depth_edges(dep), PER_KF, cell=10, grad_threshold=0.02)
        win, _ = add_points(win, slot, pts.pixels[pts.valid], 1.0 / pts.depths[pts.valid])
    return cam, win


def _perturbed(win: Window, rng, rot_deg=0.5, trans=0.015, depth=0.1) -> Window:
    """Every keyframe rotated by rot_deg and moved by trans (random axes), inverse depths scaled by
    1 + depth·N(0, 1) (clipped at 2σ)."""
    k = win.slots
    axes = rng.normal(size=(2, k, 3))
    axes /= np.linalg.norm(axes, axis=2, keepdims=True)
    dtype = win.idepth.dtype
    delta = jnp.asarray(np.concatenate([np.deg2rad(rot_deg) * axes[0], trans * axes[1]], 1), dtype)
    poses = jax.vmap(lambda T, d: T.plus(d))(win.poses, delta)
    scale = 1.0 + depth * np.clip(rng.normal(size=win.capacity), -2.0, 2.0)
    return dataclasses.replace(win, poses=poses, idepth=win.idepth * jnp.asarray(scale, dtype))


def _rotations(win: Window) -> np.ndarray:
    """The keyframes' rotation matrices (K, 3, 3) in float64, from their normalised quaternions."""
    q = np.asarray(win.poses.q, np.float64)
    x, y, z, w = (q / np.linalg.norm(q, axis=1, keepdims=True)).T
    return np.stack([
        np.stack([1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)], -1),
        np.stack([2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)], -1),
        np.stack([2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)], -1),
    ], 1)


def _sim3_errors(est: Window, truth: Window):
    """Errors after the Sim(3) that maps the oldest estimated keyframe onto the true one (the gauge BA
    holds) with the scale of the camera-centre distances: positions (m), rotations (deg), and the
    median relative error of the inverse depths of the points still valid."""
    Re, Rt = _rotations(est), _rotations(truth)
    te, tt = np.asarray(est.poses.t, np.float64), np.asarray(truth.poses.t, np.float64)
    i0 = int(np.argmin(np.asarray(truth.stamp)))
    Ra = Rt[i0] @ Re[i0].T
    s = np.linalg.norm(tt - tt[i0], axis=1).sum() / np.linalg.norm(te - te[i0], axis=1).sum()
    pos = np.linalg.norm(s * (te - te[i0]) @ Ra.T + tt[i0] - tt, axis=1)
    dR = np.einsum("kji,jl,klm->kim", Rt, Ra, Re)
    axis = np.stack([dR[:, 2, 1] - dR[:, 1, 2], dR[:, 0, 2] - dR[:, 2, 0], dR[:, 1, 0] - dR[:, 0, 1]], 1)
    rot = np.degrees(np.arctan2(0.5 * np.linalg.norm(axis, axis=1), 0.5 * (np.trace(dR, axis1=1, axis2=2) - 1)))
    ok = np.asarray(est.point_valid & truth.point_valid)
    rel = np.abs(np.asarray(est.idepth, np.float64)[ok] / s / np.asarray(truth.idepth, np.float64)[ok] - 1)
    return pos, rot, float(np.median(rel))


@pytest.mark.slow
def test_bundle_adjustment_returns_to_the_truth(scene_window):
    cam, truth = scene_window
    start = _perturbed(truth, np.random.default_rng(1))
    pos0, rot0, dep0 = _sim3_errors(start, truth)
    out, report = ba.bundle_adjust(start, cam, BA_CFG)
    pos, rot, dep = _sim3_errors(out, truth)
    assert pos0.max() > 0.01 and rot0.max() > 0.4 and dep0 > 0.05
    assert pos.max() < 0.005 and pos.max() < 0.2 * pos0.max(), (pos, pos0)
    assert rot.max() < 0.08 and rot.max() < 0.1 * rot0.max(), (rot, rot0)
    assert dep < 0.03 and dep < 0.4 * dep0, (dep, dep0)
    assert float(report.rms_after) < 0.8 * float(report.rms_before)
    assert float(report.energy_after) < float(report.energy_before)
    assert 0 < int(report.accepted) <= BA_CFG.ba_iterations
    assert int(report.dropped) < 0.3 * truth.capacity
    assert int(out.point_valid.sum()) == int(truth.point_valid.sum()) - int(report.dropped)


@pytest.mark.slow
def test_points_that_are_outliers_in_their_targets_are_dropped(scene_window):
    """A bright square painted over ten points in their host image only (as a moving object would):
    their patterns match no other keyframe, so they are outliers everywhere and are dropped."""
    cam, truth = scene_window
    host = np.asarray(truth.host)
    bad = np.flatnonzero(np.asarray(truth.point_valid) & (host == 2))[::6][:10]
    image = np.asarray(truth.images[2]).copy()
    for u, v in np.asarray(truth.pixels)[bad].astype(int):
        image[v - 3:v + 4, u - 3:u + 4] = 1.0
    win = dataclasses.replace(truth, images=truth.images.at[2].set(jnp.asarray(image)))
    out, report = ba.bundle_adjust(win, cam, BA_CFG)
    assert len(bad) == 10 and not np.asarray(out.point_valid)[bad].any()
    assert int(report.dropped) < 10 + 0.1 * truth.capacity


def _padded(win: Window, k: int, p: int, slot_of: list[int], rng) -> tuple[Window, np.ndarray]:
    """``win`` moved into a (k, p) window: keyframe i to slot slot_of[i], its points spread over random
    point slots; the free slots hold garbage (NaN images, random poses, NaN inverse depths).
    Returns the window and the point slots of win's points."""
    dtype = win.idepth.dtype
    h, w = win.images.shape[1:]
    points = np.sort(rng.choice(p, win.capacity, replace=False))
    slot_of = np.asarray(slot_of)
    rand = lambda *shape: jnp.asarray(rng.normal(size=shape), dtype)
    q = rand(k, 4)
    poses = Pose(q / jnp.linalg.norm(q, axis=1, keepdims=True), rand(k, 3))
    poses = Pose(poses.q.at[slot_of].set(win.poses.q), poses.t.at[slot_of].set(win.poses.t))
    nan = jnp.asarray(np.nan, dtype)
    padded = Window(
        images=jnp.full((k, h, w), nan).at[slot_of].set(win.images),
        raw=jnp.full((k, *win.raw.shape[1:]), nan).at[slot_of].set(win.raw),
        exposure=jax.tree.map(lambda a: jnp.repeat(a[:1], k, axis=0).at[slot_of].set(a), win.exposure),
        poses=poses,
        affine=rand(k, 2).at[slot_of].set(win.affine),
        kf_valid=jnp.zeros(k, bool).at[slot_of].set(win.kf_valid),
        stamp=jnp.asarray(rng.integers(0, 100, k), jnp.int32).at[slot_of].set(win.stamp),
        host=jnp.asarray(rng.integers(0, k, p), jnp.int32).at[points].set(jnp.asarray(slot_of, jnp.int32)[win.host]),
        pixels=jnp.asarray(rng.uniform(0, w, (p, 2)), dtype).at[points].set(win.pixels),
        idepth=jnp.full(p, nan).at[points].set(win.idepth),
        point_valid=jnp.zeros(p, bool).at[points].set(win.point_valid),
        prior=Prior.zeros(k, dtype),
    )
    return padded, points


def _first_keyframes(win: Window, n: int) -> Window:
    """The first n keyframes of ``win`` and their points, in a window of exactly that size."""
    keep = np.flatnonzero(np.asarray(win.host) < n)
    take = lambda a: a[:n]
    return Window(take(win.images), take(win.raw), jax.tree.map(take, win.exposure), jax.tree.map(take, win.poses), take(win.affine),
                  take(win.kf_valid), take(win.stamp), win.host[keep], win.pixels[keep], win.idepth[keep], win.point_valid[keep], Prior.zeros(n, win.idepth.dtype))


def _to64(tree):
    return jax.tree.map(lambda a: a.astype(jnp.float64) if a.dtype == jnp.float32 else a, tree)


@pytest.mark.slow
def test_padding_and_slot_order_do_not_change_the_result(scene_window, x64):
    """Three keyframes alone, or at slots 4, 0, 2 of a 5-slot window whose free slots and points hold
    garbage (NaN): the same bundle adjustment. In float64, because LM's path through a truncated cost
    is sensitive to float32 rounding (summation order) at this condition number."""
    cam, truth = scene_window
    cam, truth = _to64(cam), _to64(truth)
    small = _perturbed(_first_keyframes(truth, 3), np.random.default_rng(2))
    padded, points = _padded(small, KEYFRAMES, truth.capacity, [4, 0, 2], np.random.default_rng(3))
    cfg = MonoConfig(ba_iterations=8)
    out_a, rep_a = ba.bundle_adjust(small, cam, cfg)
    out_b, rep_b = ba.bundle_adjust(padded, cam, cfg)
    assert out_b.idepth.dtype == jnp.float64
    assert int(rep_a.accepted) > 2 and int(rep_a.dropped) > 0
    for name in ("accepted", "dropped", "residuals", "outliers"):
        assert int(getattr(rep_a, name)) == int(getattr(rep_b, name)), name
    np.testing.assert_allclose(float(rep_b.energy_after), float(rep_a.energy_after), rtol=1e-9)
    slots = np.array([4, 0, 2])
    for a, b in ((out_a.poses.t, out_b.poses.t), (out_a.poses.q, out_b.poses.q), (out_a.affine, out_b.affine)):
        np.testing.assert_allclose(np.asarray(b)[slots], np.asarray(a), atol=1e-9)
    np.testing.assert_array_equal(np.asarray(out_b.point_valid)[points], np.asarray(out_a.point_valid))
    assert int(out_b.point_valid.sum()) == int(out_a.point_valid.sum())
    np.testing.assert_allclose(np.asarray(out_b.idepth)[points], np.asarray(out_a.idepth), rtol=1e-8)


@pytest.mark.slow
def test_after_marginalising_the_prior_holds_the_gauge(scene_window):
    """The oldest keyframe leaves at the true state; the prior (and the distance prior at its
    linearisation point, no pin) then holds the gauge: bundle adjustment from perturbed poses returns
    to the truth without any alignment."""
    cam, truth = scene_window
    oldest = int(np.argmin(np.asarray(truth.stamp)))
    win = ba.marginalize(truth, oldest, cam, BA_CFG)
    assert bool(win.prior.active()) and not bool(win.kf_valid[oldest])
    assert int(win.point_valid.sum()) == int(truth.point_valid.sum()) - int((truth.host == oldest).sum())
    H = np.asarray(win.prior.H, np.float64)
    np.testing.assert_allclose(H, H.T, rtol=1e-5, atol=1e-6 * np.abs(H).max())
    start = _perturbed(win, np.random.default_rng(4), rot_deg=0.3, trans=0.01, depth=0.05)
    out, report = ba.bundle_adjust(start, cam, BA_CFG)
    keep = np.asarray(win.kf_valid)
    pos = np.linalg.norm(np.asarray(out.poses.t - truth.poses.t), axis=1)[keep]
    pos0 = np.linalg.norm(np.asarray(start.poses.t - truth.poses.t), axis=1)[keep]
    assert pos.max() < 0.004 and pos.max() < 0.3 * pos0.max(), (pos, pos0)
    assert float(report.energy_after) < 0.5 * float(report.energy_before)


# ----------------------------------------------------------------------- the blur-aware residuals


def _blurry_target(t: float, exposure: float, samples: int = 16):
    """A frame of the default scene at time t exposed ``exposure`` s along ``camera_path``: (recorded
    image, sharp image, mid pose, exposure path about the mid pose), at 160x120 as the keyframes."""
    big = _camera(4 * W, 4 * H)
    arrays = scene_arrays(default_scene(0, use_real_textures=False))
    sub = [camera_path(t + s, 0.6, 60.0, 0) for s in np.linspace(-exposure / 2, exposure / 2, samples)]
    mid = camera_path(t, 0.6, 60.0, 0)
    blurry, sharp, _ = render_exposure(arrays, big, jax.tree.map(lambda *a: jnp.stack(a), *sub), mid, 2.2)
    small = lambda a: cv2.GaussianBlur(np.asarray(downsample(downsample(a))), (0, 0), 1.0)
    to_mid = mid.inverse()
    return small(blurry), small(sharp), mid, ExposureTrajectory(to_mid.compose(sub[0]), to_mid.compose(sub[-1]))


def _pair_rms(win: Window, cam, host: ba.HostValues, target: int) -> float:
    r, ok, _ = ba._evaluate(win, cam, False, host)
    visible = np.asarray(ba._visible(win, ok))[:, target]
    return float(np.sqrt(np.mean(np.asarray(r)[:, target][visible] ** 2)))


@pytest.mark.slow
def test_blur_aware_predictions_match_the_recorded_blurry_keyframe(scene_window):
    """A keyframe recorded with motion blur (about 10 px) is predicted from the sharp host blurred
    along its exposure path (``mono.ba_blur_samples``) far better than by the sharp host values, and
    about as well as the sharp model predicts its sharp image."""
    cam, truth = scene_window
    blurry, sharp, mid, path = _blurry_target(1.15, 0.08)
    win = dataclasses.replace(truth, point_valid=truth.point_valid & (truth.host == 0))
    win = dataclasses.replace(win, kf_valid=win.kf_valid.at[2:].set(False), raw=win.images)  # a window that keeps recorded frames
    win, slot = add_keyframe(dataclasses.replace(win, kf_valid=win.kf_valid.at[1].set(False)), sharp, mid, raw=blurry, exposure=path)
    sharp_model = ba.host_values(win, cam, 1)
    blur_model = ba.host_values(win, cam, 16)
    per_target = lambda a: jnp.broadcast_to(a[:, None], blur_model.values.shape)
    on_raw = ba.HostValues(per_target(sharp_model.values), per_target(sharp_model.ok), True)  # the sharp model on the recorded image
    rms_sharp = _pair_rms(win, cam, sharp_model, slot)
    rms_raw = _pair_rms(win, cam, on_raw, slot)
    rms_blur = _pair_rms(win, cam, blur_model, slot)
    assert rms_blur < 0.4 * rms_raw, (rms_blur, rms_raw)
    assert rms_blur < 1.5 * rms_sharp, (rms_blur, rms_sharp)
    change = np.abs(np.asarray(per_target(sharp_model.values) - blur_model.values))
    assert change.max() > 0.05  # the paths are long enough to change the predictions


@pytest.mark.slow
def test_blur_aware_structured_jacobians_match_dense(x64):
    """With exposure paths and recorded images, the blocks against the held blurred predictions are
    the Jacobian of ``residual_vector`` (whose predictions are those of the unmoved window)."""
    win = _small_window(jnp.float64)
    cam = _camera(64, 48, jnp.float64)
    rng = np.random.default_rng(5)
    dtype = jnp.float64
    half = Pose(quat.exp(jnp.asarray([0.004, -0.006, 0.002], dtype)), jnp.asarray([0.01, 0.004, 0.0], dtype))
    paths = ExposureTrajectory(jax.tree.map(lambda a: jnp.stack([a] * win.slots), half.inverse()),
                               jax.tree.map(lambda a: jnp.stack([a] * win.slots), half))
    raw = jnp.stack([jnp.asarray(_smooth_image(rng, 48, 64), dtype) for _ in range(win.slots)])
    win = dataclasses.replace(win, raw=raw, exposure=paths)
    host = ba.host_values(win, cam, 8)
    assert host.blurred and np.abs(np.asarray(host.values - ba.host_values(win, cam, 1).values[:, None])).max() > 1e-3
    lin = jax.jit(ba.linearize)(win, cam, HUBER, OUTLIER, host)
    assert int(lin.visible.sum()) > 40
    m = 8 * win.slots + win.capacity
    dense = jax.jit(jax.jacfwd(ba.residual_vector, argnums=2), static_argnames="samples")(win, cam, jnp.zeros(m, dtype), samples=8)
    np.testing.assert_allclose(_full_jacobian(lin, win), np.asarray(dense), rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(lin.r).ravel(), np.asarray(ba.residual_vector(win, cam, samples=8)), atol=1e-12)


def test_a_blur_aware_adjustment_needs_a_window_that_keeps_recorded_frames():
    win = _small_window(jnp.float32)
    cam = _camera(64, 48)
    assert not win.recorded and win.raw.shape == (3, 0, 0)  # the sharp adjustment keeps no copy of the frames
    with pytest.raises(ArgumentError, match="recorded"):
        add_keyframe(Window.empty(2, 4, 48, 64), np.zeros((48, 64)), Pose.identity(), raw=np.zeros((48, 64)))
    with pytest.raises(ArgumentError, match="recorded frames"):
        ba.bundle_adjust(win, cam, CFG, samples=4)
    kept, slot = add_keyframe(Window.empty(2, 4, 48, 64, recorded=True), np.zeros((48, 64)), Pose.identity(), raw=np.ones((48, 64)))
    assert kept.recorded and float(kept.raw[slot].min()) == 1.0 and float(kept.images[slot].max()) == 0.0
