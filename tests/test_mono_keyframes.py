"""The monocular pipeline's keyframe and frame-statistics rules: DSO's point-shift rule
(``mono.keyframes``), frame statistics over the keyframe points in view (``odometry.inview``) and a
restart after a loss that keeps the recent speed (``mono.motions``, ``MonoState``)."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.config import RunConfig
from mbavo_jax.geometry import ExposureTrajectory, PinholeCamera, Pose, quaternion
from mbavo_jax.mono.init import TwoView
from mbavo_jax.mono.keyframes import Shift, point_shift, shift_score, wants_keyframe
from mbavo_jax.mono.motions import Motion, Motions, PoseAt
from mbavo_jax.odometry import keyframe_stats
from mbavo_jax.odometry.inview import ViewStats, in_view_stats
from mbavo_jax.odometry.mono import MonoPipeline, MonoState, rescaled
from mbavo_jax.odometry.rgbd import RGBDPipeline
from mbavo_jax.tracking import Keyframe

W, H, F = 640, 480, 500.0


def camera(w=W, h=H, f=F) -> PinholeCamera:
    return PinholeCamera.create(f, f, (w - 1) / 2, (h - 1) / 2, w, h)


def moved(t=(0.0, 0.0, 0.0), axis=(0.0, 1.0, 0.0), deg=0.0) -> Pose:
    r = np.deg2rad(deg) * np.asarray(axis, np.float32)
    return Pose(quaternion.exp(jnp.asarray(r, jnp.float32)), jnp.asarray(t, jnp.float32))


def grid_points(cam: PinholeCamera, depth: float, step: int = 40):
    u, v = np.meshgrid(np.arange(20, cam.width - 20, step), np.arange(20, cam.height - 20, step))
    pixels = np.stack([u.ravel(), v.ravel()], 1).astype(np.float32)
    X = np.concatenate([(pixels - [float(cam.cx), float(cam.cy)]) / F * depth, np.full((len(pixels), 1), depth)], 1)
    return pixels, X.astype(np.float32)


def shift_of(T_frame_kf: Pose, depth: float = 5.0) -> Shift:
    cam = camera()
    pixels, X = grid_points(cam, depth)
    t, rt = point_shift(cam, jnp.asarray(pixels), jnp.asarray(X), T_frame_kf, jnp.ones(len(pixels), bool))
    return Shift(float(t), float(rt))


def test_shift_rule_asks_for_a_keyframe_on_translation_flow_not_on_rotation():
    """Sideways translation (flow 50 px at 5 m) is a shift of the translation and of the whole motion:
    a keyframe at half DSO's weights. Turning by 3 degrees (flow ~26 px) has no translation shift:
    no keyframe. Weight 0 never asks."""
    side = shift_of(moved(t=(0.5, 0.0, 0.0)))
    assert side.translation_px == pytest.approx(50.0, rel=1e-3) and side.full_px == pytest.approx(50.0, rel=1e-3)
    assert shift_score(side, W, H, 0.5) == pytest.approx(0.5 * (0.04 + 0.02) * 50.0, rel=1e-3)
    assert wants_keyframe(side, W, H, 0.5) and not wants_keyframe(side, W, H, 0.0)
    turn = shift_of(moved(deg=3.0))
    assert turn.translation_px == pytest.approx(0.0, abs=1e-4) and 20.0 < turn.full_px < 35.0
    assert not wants_keyframe(turn, W, H, 0.5) and not wants_keyframe(turn, W, H, 1.0)


def test_shift_of_forward_motion_counts_both_directions():
    """Forward motion: the shift is pooled over the motion and its translation reversed (DSO's), so
    moving forward and backward by the same step give the same shift."""
    ahead, back = shift_of(moved(t=(0.0, 0.0, -0.5))), shift_of(moved(t=(0.0, 0.0, 0.5)))
    assert ahead.translation_px > 10.0 and ahead.translation_px == pytest.approx(back.translation_px, rel=1e-4)


def test_mono_pipeline_adds_the_shift_rule_to_the_rgbd_rules():
    """Small mean flow, all points in view: the RGB-D rules keep the keyframe; a large translation shift
    makes the monocular pipeline ask for one (not with ``mono.keyframe_shift`` 0)."""
    cfg = RunConfig().replace(odometry=dict(mode="mono"))
    stats = ViewStats(5.0, 1.0, 0.0, 0.0, shift=Shift(60.0, 60.0))
    assert not RGBDPipeline(camera(), cfg).wants_keyframe(stats)
    assert MonoPipeline(camera(), cfg).wants_keyframe(stats)
    assert not MonoPipeline(camera(), cfg.replace(mono=dict(keyframe_shift=0.0))).wants_keyframe(stats)
    assert not MonoPipeline(camera(), cfg).wants_keyframe(ViewStats(5.0, 1.0, 0.0, 0.0, shift=Shift(5.0, 5.0)))


def test_frame_statistics_are_over_the_keyframe_points_in_view():
    """The camera moves 0.9 m forward past a point 1 m ahead near the image edge: it projects far
    outside the image. The in-view statistics leave it out of the means (the distance from a
    no-motion prediction stays that of the far points); the RGB-D statistics include it."""
    cam = camera(160, 120, 131.0)
    pixels = np.stack(np.meshgrid(np.arange(20.0, 140.0, 20.0), np.arange(20.0, 100.0, 20.0)), -1).reshape(-1, 2)
    depths = np.full(len(pixels), 10.0)
    pixels, depths = np.concatenate([pixels, [[150.0, 60.0]]]).astype(np.float32), np.concatenate([depths, [1.0]]).astype(np.float32)
    image = np.random.default_rng(0).uniform(0.2, 0.8, (120, 160)).astype(np.float32)
    kf = Keyframe.from_points(image, pixels, depths, cam, RunConfig().tracker)
    assert kf.points[0].count == len(pixels)
    mid = moved(t=(0.0, 0.0, 0.9))
    traj = ExposureTrajectory(mid, mid)
    plain, seen = keyframe_stats(kf, traj, Pose.identity(), Pose.identity()), in_view_stats(kf, traj, Pose.identity(), Pose.identity())
    assert seen.jump_px < 10.0 and plain.jump_px > 2 * seen.jump_px, (plain.jump_px, seen.jump_px)
    assert seen.motion_px == pytest.approx(seen.jump_px) and seen.flow_px == pytest.approx(plain.flow_px)
    assert seen.visible == pytest.approx(plain.visible) and seen.visible < 1.0
    assert seen.shift.translation_px < 10.0 and seen.shift.full_px < 10.0


def motion(dz: float, dt: float = 0.1) -> Motion:
    return Motion(moved(t=(0.0, 0.0, dz)), dt)


def test_motions_keep_the_last_ones_and_pick_the_median_speed():
    kept = Motions(keep=3)
    for k, stamp in enumerate((0.1, 0.2, 0.3, 0.4)):
        kept = kept.add(PoseAt(stamp - 0.1, moved(t=(0.0, 0.0, float(k)))), PoseAt(stamp, moved(t=(0.0, 0.0, k + 0.5 * (k + 1)))))
    assert [round(m.speed, 4) for m in kept.items] == [10.0, 15.0, 20.0]
    assert kept.typical().speed == pytest.approx(15.0)
    assert Motions().typical() is None and kept.add(PoseAt(1.0, Pose.identity()), PoseAt(1.0, Pose.identity())) is kept


def test_a_restart_keeps_the_speed_of_the_lost_window():
    """After a loss at 1.0 s (1 m/s forward, one odd fast motion among the kept ones) the new start's
    reference at 1.5 s is the last good pose carried 0.5 m on, and a two-view start over 0.3 s whose
    translation has length 0.2 (median depth 1) is scaled to move 0.3 m: the camera keeps its speed."""
    motions = Motions(items=(motion(0.1), motion(0.1), motion(2.0), motion(0.1), motion(0.1)))
    last = moved(t=(1.0, 0.0, 3.0))
    mono = MonoState(motions=motions).restart(last, 4.0, PoseAt(1.0, last)).start_at(1.5)
    assert np.allclose(np.asarray(mono.origin.t), [1.0, 0.0, 3.5], atol=1e-5)
    two_view = TwoView(True, "", moved(t=(0.0, 0.12, -0.16)), np.zeros((3, 2), np.float32), np.ones(3, np.float32), 2.0, 3, 3)
    start = rescaled(two_view, mono.start_scale(two_view, 0.3))
    assert float(np.linalg.norm(np.asarray(start.T_ref_cur.t))) == pytest.approx(0.3, rel=1e-5)
    assert MonoState(depth=4.0).start_scale(two_view, 0.3) == 4.0  # no speed known: the lost window's depth


def _two_keyframes_with_points():
    """(camera, window, slot of the new keyframe): a 160x120 window with a host keyframe at the
    origin, a new one 0.2 ahead, and 24 points of the host at inverse depth 0.2."""
    from mbavo_jax.mono.window import Window, add_keyframe, add_points

    cam = camera(160, 120, 131.0)
    window = Window.empty(3, 64, 120, 160)
    window, host = add_keyframe(window, np.zeros((120, 160), np.float32), Pose.identity())
    window, new = add_keyframe(window, np.zeros((120, 160), np.float32), moved(t=(0.0, 0.0, 0.2)))
    pixels = np.stack(np.meshgrid(np.arange(20.0, 140.0, 20.0), np.arange(20.0, 100.0, 20.0)), -1).reshape(-1, 2).astype(np.float32)
    window, _ = add_points(window, host, pixels, np.full(len(pixels), 0.2, np.float32))
    return cam, window, new


def test_a_bundle_adjustment_that_turns_the_new_keyframe_away_is_measured_in_pixels():
    """``view_moved_px``: the new keyframe turned by 9 degrees (as a bundle adjustment on the KITTI clip
    did) moves its view of the window's points by ~21 px (f = 131 px), beyond ``mono.ba_max_move``
    of the 160 px width; a 0.1 degree adjustment stays far below it."""
    import dataclasses

    from mbavo_jax.odometry.mono import view_moved_px

    cam, window, new = _two_keyframes_with_points()

    def turned(deg):
        T = moved(t=(0.0, 0.0, 0.2)).compose(moved(deg=deg))
        return dataclasses.replace(window, poses=Pose(window.poses.q.at[new].set(T.q), window.poses.t.at[new].set(T.t)))

    limit = RunConfig().mono.ba_max_move * 160
    assert view_moved_px(cam, window, turned(9.0), new) > 2 * limit
    assert view_moved_px(cam, window, turned(0.1), new) < 0.1 * limit
    assert view_moved_px(cam, window, window, new) == 0.0


def test_a_bundle_adjustment_that_jumps_runs_again_without_the_points_it_dropped(monkeypatch):
    """A first adjustment turns the new keyframe by 9 degrees and drops half the points: the window is
    adjusted again from its state before, without those points; if that one jumps too, the window
    stays unadjusted (without them)."""
    import dataclasses

    import mbavo_jax.odometry.mono as om
    from mbavo_jax.mono.ba import BAReport

    cam, window, new = _two_keyframes_with_points()
    n = int(np.asarray(window.point_valid).sum())
    calls = []
    report = BAReport(*[jnp.zeros((), jnp.float32)] * 4, *[jnp.zeros((), jnp.int32)] * 4)

    def fake(w, camera_, config, turn=(9.0, 0.1)):
        deg = turn[min(len(calls), 1)]
        calls.append(int(np.asarray(w.point_valid).sum()))
        T = moved(t=(0.0, 0.0, 0.2)).compose(moved(deg=deg))
        drop = w.point_valid & (jnp.arange(w.point_valid.shape[0]) % 2 == 0)
        return dataclasses.replace(w, poses=Pose(w.poses.q.at[new].set(T.q), w.poses.t.at[new].set(T.t)), point_valid=drop), report

    monkeypatch.setattr(om, "bundle_adjust", fake)
    pipeline = MonoPipeline(cam, RunConfig().replace(odometry=dict(mode="mono")))
    out, got, note = pipeline._adjusted(window, new, "")
    assert calls == [n, n // 2] and got is report and "again" in note
    assert int(np.asarray(out.point_valid).sum()) == n // 2  # the fake drops the same points again
    calls.clear()
    monkeypatch.setattr(om, "bundle_adjust", lambda w, c, cfg: fake(w, c, cfg, (9.0, 9.0)))
    out, _, note = pipeline._adjusted(window, new, "")
    assert "undone" in note and np.allclose(np.asarray(out.poses.q), np.asarray(window.poses.q))
    assert int(np.asarray(out.point_valid).sum()) == n // 2
    calls.clear()
    monkeypatch.setattr(om, "bundle_adjust", lambda w, c, cfg: fake(w, c, cfg, (0.1, 0.1)))
    out, _, note = pipeline._adjusted(window, new, "")
    assert calls == [n] and note == ""
