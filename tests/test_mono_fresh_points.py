"""Why a monocular window's new points were dropped: the window's affine brightness of new keyframes
and traced frames (``mono.window.frame_affine``, ``relative_affine``; ``odometry.mono``), and the
deblurring's penalty and the tracker's Jacobian in monocular runs (``mono.deblur_regularization``,
``mono.fresh_jacobian_levels``).

A keyframe joins the window with the brightness its tracking found against the newest keyframe, not
with (0, 0), and candidates are matched under the frame's brightness relative to their own host. A
keyframe whose brightness is off by more than the bundle adjustment's outlier threshold makes every
pair into it an outlier (a flat cost with no gradient), so the adjustment cannot correct it and drops
the points it hosts; the window then runs out of points and the tracker with it."""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import pytest

import mbavo_jax.odometry.mono as om
from mbavo_jax.config import RunConfig
from mbavo_jax.geometry import ExposureTrajectory, PinholeCamera, Pose
from mbavo_jax.mono.ba import BAReport
from mbavo_jax.mono.window import Window, add_keyframe, frame_affine, relative_affine
from mbavo_jax.odometry.mono import MonoPipeline, MonoState
from mbavo_jax.odometry.state import FrameOutcome, KeyframeState, NewKeyframe, RunState
from mbavo_jax.tracking import Keyframe, Status, TrackResult

W, H, F = 160, 120, 131.0
REF = (-0.3, -0.08)  # the newest keyframe's window affine: darker, offset by 20/255
OLD = (-0.1, 0.03)
TRACKED = (0.1, 0.02)  # the tracker's e^a · I_ref + b of the frame


def _camera() -> PinholeCamera:
    return PinholeCamera.create(F, F, (W - 1) / 2, (H - 1) / 2, W, H)


def _model(image, target, host):
    """The bundle adjustment's prediction of keyframe ``target`` from keyframe ``host``'s image."""
    return np.exp(target[0] - host[0]) * (image - host[1]) + target[1]


def test_frame_affine_composes_the_tracked_brightness_with_the_reference_keyframes():
    rng = np.random.default_rng(0)
    host, image = (0.2, -0.05), rng.uniform(0.0, 1.0, 50)
    ref_image = _model(image, REF, host)
    frame = np.exp(TRACKED[0]) * ref_image + TRACKED[1]
    f = np.asarray(frame_affine(jnp.asarray(REF), jnp.asarray(TRACKED)))
    np.testing.assert_allclose(_model(image, f, host), frame, atol=1e-6)
    a, b = np.asarray(relative_affine(jnp.asarray(f), jnp.asarray(host)))
    np.testing.assert_allclose(np.exp(a) * image + b, frame, atol=1e-6)
    np.testing.assert_allclose(np.asarray(relative_affine(jnp.asarray(f), jnp.asarray(REF))), TRACKED, atol=1e-6)


def _mono(rng) -> tuple[MonoState, int, int]:
    """A window of two keyframes (the older at ``OLD``, the newest at ``REF``), no points."""
    window = Window.empty(3, 16, H, W)
    window, old = add_keyframe(window, rng.uniform(0.1, 0.9, (H, W)).astype(np.float32), Pose.identity(), OLD)
    window, new = add_keyframe(window, rng.uniform(0.1, 0.9, (H, W)).astype(np.float32), Pose.identity(), REF)
    return MonoState(window=window, slots=(old, new), stamps=(0.0, 0.1), candidates=(None,) * 3), old, new


def _pipeline() -> MonoPipeline:
    return MonoPipeline(_camera(), RunConfig().replace(odometry=dict(mode="mono")))


def test_a_new_keyframe_joins_the_window_with_its_tracked_brightness(monkeypatch):
    """The keyframe made at a frame tracked as e^0.1 · I_ref + 0.02 against the newest keyframe gets
    the window affine of that frame (with the bundle adjustment left out)."""
    rng = np.random.default_rng(1)
    mono, _, _ = _mono(rng)
    pipeline = _pipeline()
    report = BAReport(*[jnp.zeros((), jnp.float32)] * 4, *[jnp.zeros((), jnp.int32)] * 4)
    monkeypatch.setattr(om, "bundle_adjust", lambda w, c, cfg: (w, report))
    monkeypatch.setattr(MonoPipeline, "_activate", lambda self, m, T: m)
    image = rng.uniform(0.1, 0.9, (H, W)).astype(np.float32)
    kf = KeyframeState(Keyframe.from_points(image, np.zeros((0, 2)), np.zeros(0), _camera()), Pose.identity(), 0.1)
    state = RunState(keyframe=kf, mids=((0.2, Pose.identity()),), backend=mono)
    result = TrackResult(ExposureTrajectory(Pose.identity(), Pose.identity()), Status.CONVERGED, {"affine": list(TRACKED)})
    outcome = FrameOutcome(2, 0.2, "converged", T_world_mid=Pose.identity(), new_keyframe=NewKeyframe(0.2, Pose.identity(), image),
                           result=result)
    state, _ = pipeline._backend(state, None, outcome)
    slot = state.backend.slots[-1]
    want = (REF[0] + TRACKED[0], TRACKED[1] + np.exp(TRACKED[0]) * REF[1])
    np.testing.assert_allclose(np.asarray(state.backend.window.affine[slot]), want, atol=1e-6)


def test_candidates_are_traced_under_the_frames_brightness_relative_to_their_host(monkeypatch):
    """The newest keyframe's candidates see the tracked (a, b) itself; an older keyframe's see the
    frame's brightness relative to that keyframe."""
    rng = np.random.default_rng(2)
    mono, old, new = _mono(rng)
    seen = {}

    def fake_trace(c, host_image, frame_image, camera, T_frame_host, affine_ab, config, blur):
        seen[c] = np.asarray(affine_ab)
        return c

    monkeypatch.setattr(om, "trace", fake_trace)
    cands = [None] * 3
    cands[old], cands[new] = "old", "new"
    mono = mono.replace(candidates=tuple(cands))
    _pipeline().traced(mono, rng.uniform(0.1, 0.9, (H, W)).astype(np.float32), Pose.identity(), TRACKED)
    np.testing.assert_allclose(seen["new"], TRACKED, atol=1e-6)
    a = REF[0] + TRACKED[0] - OLD[0]
    b = TRACKED[1] + np.exp(TRACKED[0]) * REF[1] - np.exp(a) * OLD[1]
    np.testing.assert_allclose(seen["old"], (a, b), atol=1e-6)
    assert abs(seen["old"][1] - TRACKED[1]) > 0.1  # far from the tracked offset: the test can tell them apart


def test_monocular_keyframes_are_deblurred_with_the_monocular_penalty():
    """The monocular pipeline deblurs with ``mono.deblur_regularization`` (its depth is the window's
    points filled in), the RGB-D pipeline with ``deblur.regularization``."""
    from mbavo_jax.odometry.rgbd import RGBDPipeline

    cfg = RunConfig().replace(mono=dict(deblur_regularization=0.07), deblur=dict(regularization=0.01))
    assert MonoPipeline(_camera(), cfg).config.deblur.regularization == 0.07
    assert RGBDPipeline(_camera(), cfg).config.deblur.regularization == 0.01
    assert RunConfig().mono.deblur_regularization > RunConfig().deblur.regularization


def test_monocular_tracking_recomputes_the_jacobian_as_the_monocular_setting_says():
    """The monocular pipeline's tracker takes ``mono.fresh_jacobian_levels`` (per-step on every level by
    default), the RGB-D pipeline's ``tracker.fresh_jacobian_levels`` (the chord method on the finer levels)."""
    from mbavo_jax.odometry.rgbd import RGBDPipeline

    cfg = RunConfig().replace(mono=dict(fresh_jacobian_levels=2), tracker=dict(fresh_jacobian_levels=1))
    assert MonoPipeline(_camera(), cfg).config.tracker.fresh_jacobian_levels == 2
    assert RGBDPipeline(_camera(), cfg).config.tracker.fresh_jacobian_levels == 1
    assert RunConfig().mono.fresh_jacobian_levels >= RunConfig().tracker.levels > RunConfig().tracker.fresh_jacobian_levels
