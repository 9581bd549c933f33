"""Monocular initialisation (mono.init): relative pose and depths up to scale from generated frames,
sharp and motion-blurred; pure rotation and textureless frames are refused with their reason.

Frames are rendered at 320x240 and area-averaged to 160x120 (the renderer does not anti-alias, so
rendering at the final size would add frame-to-frame texture aliasing that no real camera has)."""

from __future__ import annotations

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.config import MonoConfig
from mbavo_jax.geometry import PinholeCamera, Pose
from mbavo_jax.geometry import quaternion as quat
from mbavo_jax.image import delinearize
from mbavo_jax.mono.init import TwoViewTracker, best_rotation, rotation_parallax_deg, two_view
from mbavo_jax.synthetic.generator import camera_path, mean_blur_length
from mbavo_jax.synthetic.scene import default_scene, render_exposure, scene_arrays

W, H, SS = 160, 120, 2  # final size, supersampling factor of the render
GAMMA = 2.2
FINE = PinholeCamera.create(525.0 * W * SS / 640, 525.0 * W * SS / 640, (W * SS - 1) / 2, (H * SS - 1) / 2, W * SS, H * SS)
CAMERA = FINE.scaled(1)  # the 160x120 camera (pixel centres kept)
SPEED, ROTATION_RATE = 1.0, 20.0  # camera_path: m/s, deg/s
T0, DT = 1.0, 0.1  # first frame time and frame spacing (s)
FRAMES = 8


@pytest.fixture(scope="module")
def scene():
    return scene_arrays(default_scene(0, use_real_textures=False))


def render(arrays, poses: Pose, mid: Pose, rng) -> tuple[np.ndarray, np.ndarray, float]:
    """(160x120 display image with a little noise, 320x240 z-depth at ``mid``, mean blur length in 160x120 px)."""
    radiance, _, depth = render_exposure(arrays, FINE, poses, mid, GAMMA)
    image = cv2.resize(np.asarray(delinearize(radiance, GAMMA)), (W, H), interpolation=cv2.INTER_AREA)
    image = np.clip(image + rng.normal(scale=0.002, size=image.shape), 0.0, 1.0).astype(np.float32)
    depth = np.asarray(depth)
    return image, depth, mean_blur_length(depth, FINE, poses, mid) / SS


def path_frames(arrays, exposure_s: float, subframes: int) -> list[dict]:
    """Frames along ``camera_path`` every DT seconds, each averaged over ``subframes`` poses spread
    over ``exposure_s`` (blur); with the mid-exposure pose T_world_cam and depth."""
    rng = np.random.default_rng(1)
    out = []
    for k in range(FRAMES):
        t = T0 + k * DT
        times = t + np.linspace(-0.5, 0.5, subframes) * exposure_s if subframes > 1 else np.full(1, t)
        poses = jax.vmap(lambda s: camera_path(s, SPEED, ROTATION_RATE, 0))(jnp.asarray(times, jnp.float32))
        mid = camera_path(t, SPEED, ROTATION_RATE, 0)
        image, depth, blur = render(arrays, poses, mid, rng)
        out.append(dict(image=image, depth=depth, pose=mid, blur=blur))
    return out


def first_ok(frames: list[dict], config: MonoConfig = MonoConfig()):
    """Feed the frames to a tracker started on the first; (index, result) of the first ok result."""
    tracker = TwoViewTracker.start(frames[0]["image"], CAMERA, config)
    for k, frame in enumerate(frames[1:], start=1):
        tracker, result = tracker.update(frame["image"])
        if result.ok:
            return k, result
        assert "parallax" in result.reason, result.reason  # textured, well tracked: only the parallax is missing
    pytest.fail(f"not initialised after {len(frames) - 1} frames: {result.reason}")


def angle_deg(R: np.ndarray) -> float:
    """Rotation angle of R (deg), accurate for small angles (atan2 of the sine and cosine parts)."""
    sine = 0.5 * np.linalg.norm([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    return float(np.degrees(np.arctan2(sine, 0.5 * (np.trace(R) - 1.0))))


def errors(frames: list[dict], k: int, result) -> dict:
    """Rotation and translation-direction errors (deg) against the truth; per-point depth errors
    after the one scale that best fits (median ratio); the translation's length error at that scale."""
    T_true = np.asarray(frames[0]["pose"].inverse().compose(frames[k]["pose"]).as_matrix(), np.float64)
    T_est = np.asarray(result.T_ref_cur.as_matrix(), np.float64)
    t_true, t_est = T_true[:3, 3], T_est[:3, 3]
    # depth at each reference pixel: the nearest sample of the 2x finer depth map
    uv = np.clip(np.rint(SS * result.pixels + 0.5 * (SS - 1)).astype(int), 0, [W * SS - 1, H * SS - 1])
    z_true = frames[0]["depth"][uv[:, 1], uv[:, 0]]
    ratio = (1.0 / result.idepth) / z_true
    scale = float(np.median(ratio))
    return dict(
        rotation=angle_deg(T_true[:3, :3].T @ T_est[:3, :3]),
        direction=float(np.degrees(np.arccos(np.clip(t_true @ t_est / np.linalg.norm(t_true) / np.linalg.norm(t_est), -1, 1)))),
        depth=np.abs(ratio / scale - 1.0),
        length=abs(np.linalg.norm(t_est) / scale / np.linalg.norm(t_true) - 1.0),
    )


def check_result(result, frames, k, rot_tol, dir_tol, depth_tol, length_tol):
    cfg = MonoConfig()
    e = errors(frames, k, result)
    assert result.reason == "" and result.frames == k
    assert result.parallax_deg >= cfg.init_min_parallax_deg
    assert len(result.idepth) >= cfg.init_min_tracks and result.pixels.shape == (len(result.idepth), 2)
    assert result.pixels.dtype == np.float32 and result.idepth.dtype == np.float32
    assert np.all(result.idepth > 0) and np.all(np.isfinite(result.idepth))
    assert np.median(1.0 / result.idepth) == pytest.approx(1.0, rel=1e-5)  # the monocular world's scale
    assert e["rotation"] < rot_tol, e["rotation"]
    assert e["direction"] < dir_tol, e["direction"]
    assert np.median(e["depth"]) < depth_tol, np.median(e["depth"])
    assert e["length"] < length_tol, e["length"]  # the translation has the depths' scale
    return e


@pytest.mark.slow
def test_sharp_frames_give_pose_and_depths_up_to_scale(scene):
    frames = path_frames(scene, 0.0, 1)
    k, result = first_ok(frames)
    check_result(result, frames, k, rot_tol=0.5, dir_tol=5.0, depth_tol=0.05, length_tol=0.05)


@pytest.mark.slow
def test_blurred_frames_give_pose_and_depths_up_to_scale(scene):
    frames = path_frames(scene, 0.09, 16)  # 90 % of the frame interval: 2-7 px of blur (8-29 px at 640x480)
    assert np.mean([f["blur"] for f in frames]) > 3.0
    k, result = first_ok(frames)
    check_result(result, frames, k, rot_tol=1.0, dir_tol=10.0, depth_tol=0.08, length_tol=0.1)


@pytest.mark.slow
def test_pure_rotation_is_refused_for_parallax(scene):
    rng = np.random.default_rng(2)
    centre = camera_path(T0, SPEED, ROTATION_RATE, 0)
    frames = []
    for k in range(6):  # turn 1.5 deg per frame about the camera centre (yaw and a little pitch)
        turn = Pose(quat.exp(jnp.array([0.2, 1.0, 0.0], jnp.float32) * np.float32(np.radians(1.5) * k / np.hypot(0.2, 1.0))),
                    jnp.zeros(3, jnp.float32))
        pose = centre.compose(turn)
        frames.append(render(scene, jax.tree_util.tree_map(lambda a: a[None], pose), pose, rng)[0])
    tracker = TwoViewTracker.start(frames[0], CAMERA, MonoConfig())
    for k, image in enumerate(frames[1:], start=1):
        tracker, result = tracker.update(image)
        assert not result.ok and result.T_ref_cur is None and len(result.idepth) == 0 and not result.restart
        need = f"{MonoConfig().init_min_parallax_deg:g}"
        assert result.reason == f"too little parallax: {result.parallax_deg:.2f} deg (need {need}; rotation only?)"
        assert result.tracks >= MonoConfig().init_min_tracks and result.frames == k
        assert result.parallax_deg < 0.2 * MonoConfig().init_min_parallax_deg


def test_update_leaves_the_state_it_came_from(scene):
    """``update`` returns a new state: the same state updated twice gives the same result."""
    rng = np.random.default_rng(3)
    poses = [camera_path(T0 + k * DT, SPEED, ROTATION_RATE, 0) for k in range(2)]
    images = [render(scene, jax.tree_util.tree_map(lambda a: a[None], p), p, rng)[0] for p in poses]
    tracker = TwoViewTracker.start(images[0], CAMERA, MonoConfig())
    before = tracker.tracks.cur.copy()
    one, first = tracker.update(images[1])
    two, second = tracker.update(images[1])
    assert np.array_equal(tracker.tracks.cur, before) and tracker.tracks.frames == 0 and one.tracks.frames == 1
    assert (first.reason, first.tracks, first.parallax_deg) == (second.reason, second.tracks, second.parallax_deg)
    assert np.array_equal(one.tracks.cur, two.tracks.cur) and not np.array_equal(one.tracks.cur, before)


def test_textureless_image_is_refused_for_texture():
    flat = np.full((H, W), 0.5, np.float32)
    tracker = TwoViewTracker.start(flat, CAMERA, MonoConfig())
    for _ in range(3):  # not a crash, and the same answer on later frames
        tracker, result = tracker.update(flat)
        assert not result.ok and result.reason == "too little texture: 0 corners tracked (need 80)", result.reason
        assert result.restart and result.tracks == 0 and result.T_ref_cur is None
    noisy = np.clip(flat + np.random.default_rng(0).normal(scale=1.0 / 255.0, size=flat.shape), 0, 1).astype(np.float32)
    assert TwoViewTracker.start(noisy, CAMERA, MonoConfig()).tracks.ref.shape[0] < MonoConfig().init_min_tracks  # noise is no texture


def random_scene_pixels(rng, n: int, T_cur_ref: np.ndarray):
    """Reference and current pixels (n, 2) of random points 2-6 m in front of the 160x120 camera."""
    K = np.asarray(CAMERA.K(), np.float64)
    ref = rng.uniform([5, 5], [W - 6, H - 6], size=(n, 2))
    z = rng.uniform(2.0, 6.0, size=n)
    X = np.c_[ref, np.ones(n)] @ np.linalg.inv(K).T * z[:, None]
    Xc = X @ T_cur_ref[:3, :3].T + T_cur_ref[:3, 3]
    cur = Xc @ K.T
    return ref.astype(np.float32), (cur[:, :2] / cur[:, 2:]).astype(np.float32), z


def pose_errors(result, T_cur_ref: np.ndarray) -> tuple[float, float]:
    """Rotation and translation-direction errors (deg) of ``result.T_ref_cur`` against the inverse of ``T_cur_ref``."""
    truth, est = np.linalg.inv(T_cur_ref), np.asarray(result.T_ref_cur.as_matrix(), np.float64)
    cos = truth[:3, 3] @ est[:3, 3] / np.linalg.norm(truth[:3, 3]) / np.linalg.norm(est[:3, 3])
    return angle_deg(truth[:3, :3].T @ est[:3, :3]), float(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))


def test_two_view_on_exact_matches():
    """Exact correspondences: the pose, and the depths up to the one scale shared with the translation."""
    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array([0.02, -0.05, 0.01]))[0]
    T[:3, 3] = [0.3, -0.05, 0.1]  # x_cur = R x_ref + t
    ref, cur, z = random_scene_pixels(rng, 300, T)
    result = two_view(ref, cur, CAMERA, MonoConfig(), frames=3)
    assert result.ok, result.reason
    rotation, direction = pose_errors(result, T)
    assert rotation < 0.01 and direction < 0.05
    assert result.frames == 3 and result.tracks == result.inliers == len(result.idepth) == 300
    assert np.array_equal(result.pixels, ref)
    assert np.median(1.0 / result.idepth) == pytest.approx(1.0, rel=1e-5)
    ratio = (1.0 / result.idepth) / z
    assert np.max(np.abs(ratio / np.median(ratio) - 1.0)) < 1e-3
    assert np.linalg.norm(result.T_ref_cur.t) / np.median(ratio) == pytest.approx(np.linalg.norm(T[:3, 3]), rel=1e-3)


def test_two_view_with_outliers():
    """20 % of the matches moved by up to 15 px: RANSAC drops them (bar the few that happen to lie
    near their epipolar line) and the pose holds."""
    rng = np.random.default_rng(0)
    T = np.eye(4)
    T[:3, :3] = cv2.Rodrigues(np.array([0.02, -0.05, 0.01]))[0]
    T[:3, 3] = [0.3, -0.05, 0.1]
    ref, cur, _ = random_scene_pixels(rng, 300, T)
    bad = rng.random(300) < 0.2
    cur[bad] += rng.uniform(-15, 15, size=(bad.sum(), 2)).astype(np.float32)
    # exact matches: a 1 px inlier band (the default 2 px is for tracked corners on blurred frames)
    result = two_view(ref, cur, CAMERA, MonoConfig(init_ransac_px=1.0))
    assert result.ok, result.reason
    rotation, direction = pose_errors(result, T)
    assert rotation < 0.3 and direction < 2.0
    assert (~bad).sum() <= result.inliers <= (~bad).sum() + 0.1 * bad.sum()
    outliers = {tuple(p) for p in ref[bad]}
    assert sum(tuple(p) in outliers for p in result.pixels) <= 0.1 * bad.sum()


def test_two_view_reasons():
    """Each refusal says why: too few tracks, rotation only, too few inliers."""
    rng = np.random.default_rng(1)
    cfg = MonoConfig()
    T = np.eye(4)
    T[:3, 3] = [0.3, 0.0, 0.0]
    ref, cur, _ = random_scene_pixels(rng, 300, T)
    few = two_view(ref[:50], cur[:50], CAMERA, cfg)
    assert not few.ok and few.reason == "too little texture: 50 corners tracked (need 80)"
    R = np.eye(4)
    R[:3, :3] = cv2.Rodrigues(np.array([0.0, 0.1, 0.03]))[0]
    rref, rcur, _ = random_scene_pixels(rng, 300, R)
    turn = two_view(rref, rcur, CAMERA, cfg)
    assert not turn.ok and turn.reason.startswith(f"too little parallax: 0.00 deg (need {MonoConfig().init_min_parallax_deg:g}; rotation only?)"), turn.reason
    junk = cur.copy()
    junk[:150] = rng.uniform([0, 0], [W, H], size=(150, 2)).astype(np.float32)
    bad = two_view(ref, junk, CAMERA, cfg)
    assert not bad.ok and bad.reason.startswith("two-view geometry failed:") and "% inliers" in bad.reason, bad.reason


def test_rotation_parallax_ignores_rotation():
    rng = np.random.default_rng(2)
    a = rng.normal(size=(100, 3))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    R = cv2.Rodrigues(np.array([0.3, -0.2, 0.5]))[0]
    b = a @ R  # b_i = R^T a_i: a_i = R b_i
    b[:10] = rng.normal(size=(10, 3))  # bad tracks
    b /= np.linalg.norm(b, axis=1, keepdims=True)
    assert np.allclose(best_rotation(a, b), R, atol=1e-9)
    assert rotation_parallax_deg(a, b) < 1e-6
