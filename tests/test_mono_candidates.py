"""Candidate (immature) points: selection on a keyframe and inverse-depth intervals traced along
epipolar lines in rendered views of the default scene with known poses and depth."""

from __future__ import annotations

import dataclasses

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.config import MonoConfig
from mbavo_jax.geometry import PinholeCamera, Pose
from mbavo_jax.mono import candidates as mc
from mbavo_jax.mono.window import Window, add_keyframe, add_points
from mbavo_jax.synthetic.generator import camera_path
from mbavo_jax.synthetic.scene import default_scene, render_exposure, scene_arrays
from mbavo_jax.tracking.points import gradient_magnitude

W, H, COUNT = 320, 240, 600
SPEED, ROTATION = 1.0, 60.0  # m/s, deg/s: 9-29 cm between the keyframe and the frames below
TIMES = (1.1, 1.2, 1.3)
EXPOSURE = 0.02  # s: blurred frames (about 5 px of blur at 320x240)
CONFIG = MonoConfig()
NO_AFFINE = jnp.zeros(2, jnp.float32)


@dataclasses.dataclass(frozen=True)
class View:
    T_world_cam: Pose
    sharp: jax.Array
    blurred: jax.Array
    depth: np.ndarray


@pytest.fixture(scope="module")
def scene():
    f = 525.0 * W / 640.0
    camera = PinholeCamera.create(f, f, (W - 1) / 2, (H - 1) / 2, W, H)
    arrays = scene_arrays(default_scene(0))

    def view(t: float, exposure: float = 0.0) -> View:
        mid = camera_path(t, SPEED, ROTATION, 0)
        times = t + jnp.linspace(-0.5, 0.5, 16) * exposure
        poses = jax.vmap(lambda s: camera_path(s, SPEED, ROTATION, 0))(times)
        blurred, sharp, depth = render_exposure(arrays, camera, poses, mid, 2.2)
        return View(mid, sharp, blurred, np.asarray(depth))

    host = view(1.0)
    frames = [view(t, EXPOSURE) for t in TIMES]
    return camera, host, frames, view


@pytest.fixture(scope="module")
def selected(scene):
    _, host, _, _ = scene
    return mc.select_candidates(np.asarray(host.sharp), COUNT, CONFIG)


def relative(frame: View, host: View) -> Pose:
    return frame.T_world_cam.inverse().compose(host.T_world_cam)


def true_idepth(c: mc.Candidates, host: View) -> np.ndarray:
    px = np.asarray(c.pixels).astype(int)
    return 1.0 / host.depth[px[:, 1], px[:, 0]]


def idepth_error(c: mc.Candidates, host: View) -> np.ndarray:
    _, idepth = mc.estimates(c)
    truth = true_idepth(c, host)
    return np.abs(np.asarray(idepth) - truth) / truth


def trace_all(c, camera, host, frames, images, affine=NO_AFFINE):
    """Trace ``c`` in each of ``images`` with the true relative pose of the matching frame."""
    states = []
    for frame, image in zip(frames, images):
        c = mc.trace(c, host.sharp, jnp.asarray(image), camera, relative(frame, host), affine, CONFIG)
        states.append(c)
    return states


def bounded_width(c: mc.Candidates) -> np.ndarray:
    lo, hi = np.asarray(c.idepth_min), np.asarray(c.idepth_max)
    ok = np.asarray(c.valid) & np.isfinite(hi) & (hi > 0)
    return (hi - lo)[ok] / (0.5 * (hi + lo))[ok]


# ------------------------------------------------------------------------------------------ selection


def test_select_exact_count_on_strong_gradients_spread_over_the_image(scene, selected):
    _, host, _, _ = scene
    image = np.asarray(host.sharp)
    c = selected
    assert c.pixels.shape == (COUNT, 2) and c.valid.shape == (COUNT,)
    valid = np.asarray(c.valid)
    assert valid.sum() >= 0.95 * COUNT  # a textured keyframe fills every slot (or nearly)
    px = np.asarray(c.pixels)[valid].astype(int)
    assert len(np.unique(px, axis=0)) == len(px)
    grad = gradient_magnitude(image)
    g = grad[px[:, 1], px[:, 0]]
    assert np.all(g > mc.GRAD_ADD * 0.75 ** (mc.SELECT_LEVELS - 1))
    assert np.median(g) > 2.0 * np.median(grad)
    assert px.min() >= mc.BORDER and px[:, 0].max() < W - mc.BORDER and px[:, 1].max() < H - mc.BORDER
    cells = np.unique(px // 40, axis=0)  # 8 x 6 cells of 40 px: the points cover (nearly) all of them
    assert len(cells) >= 44


def test_select_pads_to_count_and_finds_nothing_on_a_flat_image(scene):
    _, host, _, _ = scene
    image = np.asarray(host.sharp)
    few = mc.select_candidates(image, 37, CONFIG)
    assert few.pixels.shape == (37, 2) and int(few.valid.sum()) == 37
    flat = mc.select_candidates(np.full((H, W), 0.4, np.float32), COUNT, CONFIG)
    assert flat.pixels.shape == (COUNT, 2) and not bool(flat.valid.any())
    half = image.copy()
    half[:, : W // 2] = 0.4  # the left half is flat: no candidate there
    c = mc.select_candidates(half, COUNT, CONFIG)
    px = np.asarray(c.pixels)[np.asarray(c.valid)]
    assert len(px) > 0.5 * COUNT and px[:, 0].min() >= W // 2 - 2


# -------------------------------------------------------------------------------------------- tracing


@pytest.mark.slow
def test_sharp_frames_converge_to_the_true_inverse_depth(scene, selected):
    camera, host, frames, _ = scene
    states = trace_all(selected, camera, host, frames, [f.sharp for f in frames])
    widths = [np.median(bounded_width(c)) for c in states]
    assert widths[0] > widths[1] > widths[2]  # the intervals shrink as the baseline grows
    last = states[-1]
    valid = np.asarray(last.valid)
    lo, hi, truth = np.asarray(last.idepth_min), np.asarray(last.idepth_max), true_idepth(last, host)
    bounded = valid & np.isfinite(hi)
    assert bounded.sum() > 0.7 * valid.sum()
    assert np.mean((truth >= lo) & (truth <= hi), where=bounded) > 0.8  # misses: depth edges, slanted surfaces
    ok = np.asarray(mc.ready(last, CONFIG))
    err = idepth_error(last, host)
    assert ok.sum() > 0.25 * valid.sum()
    assert np.mean(err[ok] < 0.05) > 0.85 and np.mean(err[ok] < 0.1) > 0.92 and np.median(err[ok]) < 0.02
    assert np.all(np.asarray(last.traced)[ok] >= 1) and np.all(np.asarray(last.quality)[ok] > mc.MIN_QUALITY)


def test_blurred_frames_still_converge(scene, selected):
    camera, host, frames, _ = scene
    last = trace_all(selected, camera, host, frames, [f.blurred for f in frames])[-1]
    valid = np.asarray(last.valid)
    ok = np.asarray(mc.ready(last, CONFIG))
    err = idepth_error(last, host)
    assert ok.sum() > 0.15 * valid.sum()
    assert np.mean(err[ok] < 0.1) > 0.85 and np.median(err[ok]) < 0.03
    assert np.asarray(last.outlier)[valid].mean() < 0.25  # blur alone drops few candidates


def test_brightness_change_is_followed_through_the_affine_guess(scene, selected):
    camera, host, frames, _ = scene
    a, b = 0.4, 0.03
    images = [np.exp(a) * np.asarray(f.sharp) + b for f in frames]
    right = trace_all(selected, camera, host, frames, images, jnp.array([a, b], jnp.float32))[-1]
    plain = trace_all(selected, camera, host, frames, [f.sharp for f in frames])[-1]
    ok = np.asarray(mc.ready(right, CONFIG))
    assert ok.sum() >= 0.85 * int(mc.ready(plain, CONFIG).sum())
    assert np.mean(idepth_error(right, host)[ok] < 0.05) > 0.85  # ready: DSO-like (8 px along the line, interval at most its midpoint); BA refines


@pytest.mark.parametrize("wrong", ["unrelated", "shuffled"])
def test_wrong_frames_give_outliers_not_confident_depths(scene, selected, wrong):
    camera, host, frames, view = scene
    rng = np.random.default_rng(1)
    if wrong == "unrelated":  # the scene from elsewhere on the path, passed off as the frames
        images = [view(t + 7.0).sharp for t in TIMES]
    else:
        images = [rng.permutation(np.asarray(f.sharp).ravel()).reshape(H, W) for f in frames]
    last = trace_all(selected, camera, host, frames, images)[-1]
    valid = np.asarray(last.valid)
    rejected = np.asarray(last.outlier) | (np.asarray(last.status) == mc.OUTLIER)
    assert rejected[valid].mean() > 0.6
    ok = np.asarray(mc.ready(last, CONFIG))
    confidently_wrong = ok & (idepth_error(last, host) > 0.1)
    assert confidently_wrong.sum() <= 0.01 * valid.sum()


def test_uninformative_traces_keep_the_interval(scene, selected):
    camera, host, frames, _ = scene
    c = trace_all(selected, camera, host, frames[:2], [f.sharp for f in frames[:2]])[-1]
    # the host itself, and a pure rotation: no baseline, nothing to learn
    turned = Pose(jnp.array([0.0, 0.02, 0.0, 1.0]) / jnp.sqrt(1.0004), jnp.zeros(3))
    for T in (Pose.identity(), turned):
        out = mc.trace(c, host.sharp, host.sharp, camera, T, NO_AFFINE, CONFIG)
        for name in ("idepth_min", "idepth_max", "quality", "traced", "outlier"):
            np.testing.assert_array_equal(np.asarray(getattr(out, name)), np.asarray(getattr(c, name)), err_msg=name)
        status = np.asarray(out.status)[np.asarray(c.valid) & ~np.asarray(c.outlier)]
        assert np.all(np.isin(status, (mc.SKIPPED, mc.BAD_CONDITION, mc.OUT_OF_IMAGE)))
    # a frame that sees none of the host's points (turned 90 degrees): out of the image, kept
    away = Pose(jnp.array([0.0, np.sin(np.pi / 4), 0.0, np.cos(np.pi / 4)], jnp.float32), jnp.array([0.1, 0.0, 0.0]))
    out = mc.trace(c, host.sharp, frames[2].sharp, camera, away, NO_AFFINE, CONFIG)
    active = np.asarray(c.valid) & ~np.asarray(c.outlier)
    assert np.all(np.asarray(out.status)[active] == mc.OUT_OF_IMAGE)
    np.testing.assert_array_equal(np.asarray(out.idepth_max), np.asarray(c.idepth_max))


def test_padding_slots_are_never_traced_or_ready(scene):
    camera, host, frames, _ = scene
    c = mc.select_candidates(np.asarray(host.sharp), COUNT, CONFIG)
    c = eqx.tree_at(lambda x: x.valid, c, c.valid.at[::2].set(False))  # every other slot is padding
    out = trace_all(c, camera, host, frames, [f.sharp for f in frames])[-1]
    pad = ~np.asarray(c.valid)
    assert np.all(np.asarray(out.status)[pad] == mc.UNTRACED) and np.all(np.isinf(np.asarray(out.idepth_max)[pad]))
    assert not np.asarray(mc.ready(out, CONFIG))[pad].any()
    _, idepth = mc.estimates(c)
    assert np.all(np.asarray(idepth) == 0.0)  # unbounded intervals have no estimate yet


def test_activate_moves_ready_candidates_into_the_window_as_far_as_it_holds_them(scene, selected):
    camera, host, frames, _ = scene
    c = trace_all(selected, camera, host, frames, [f.sharp for f in frames])[-1]
    mask = np.asarray(mc.ready(c, CONFIG))
    assert mask.sum() > 20
    pixels, idepth = (np.asarray(v) for v in mc.estimates(c))
    win, slot = add_keyframe(Window.empty(2, int(mask.sum()) - 5, H, W), np.asarray(host.sharp), host.T_world_cam)
    out, rest = mc.activate(win, jnp.asarray(slot, jnp.int32), c, CONFIG)
    joined = np.flatnonzero(mask)[: win.capacity]  # in candidate order, until the window is full
    np.testing.assert_array_equal(np.asarray(out.pixels), pixels[joined])
    np.testing.assert_array_equal(np.asarray(out.idepth), idepth[joined])
    assert np.asarray(out.point_valid).all() and (np.asarray(out.host) == slot).all()
    valid = np.asarray(c.valid).copy()
    valid[joined] = False
    np.testing.assert_array_equal(np.asarray(rest.valid), valid)  # those that joined are no longer candidates
    assert int(np.asarray(mc.ready(rest, CONFIG)).sum()) == 5  # those that did not fit wait


def test_parallax_is_the_disparity_of_a_point_at_that_depth(scene, selected):
    camera = scene[0]
    b, idepth = 0.05, 0.4  # a 5 cm sideways step, points at 2.5 m: f · b · ρ px for every pixel
    step = Pose(jnp.array([0.0, 0.0, 0.0, 1.0], jnp.float32), jnp.array([b, 0.0, 0.0], jnp.float32))
    disparity = np.asarray(mc.parallax(selected, camera, step, jnp.asarray(idepth, jnp.float32)))
    np.testing.assert_allclose(disparity, float(camera.fx) * b * idepth, rtol=1e-4)
    assert np.all(np.asarray(mc.parallax(selected, camera, step, jnp.asarray(0.0))) == 0.0)


def test_activate_waits_for_a_baseline_to_the_latest_frame(scene, selected):
    """Ready candidates join only when a point at the window's median depth would move at least
    MIN_PARALLAX px between their host and the latest frame traced: not after a 1 mm step."""
    camera, host, frames, _ = scene
    c = trace_all(selected, camera, host, frames, [f.sharp for f in frames])[-1]
    mask = np.asarray(mc.ready(c, CONFIG))
    win, slot = add_keyframe(Window.empty(2, 2 * COUNT, H, W), np.asarray(host.sharp), host.T_world_cam)
    win, _ = add_points(win, slot, np.array([[10.0, 10.0]]), np.array([1.0 / np.median(host.depth)]))  # the median depth
    near = host.T_world_cam.compose(Pose(jnp.array([0.0, 0.0, 0.0, 1.0], jnp.float32), jnp.array([1e-3, 0.0, 0.0], jnp.float32)))
    out, rest = mc.activate(win, jnp.asarray(slot, jnp.int32), c, CONFIG, camera, near)
    assert int(np.asarray(out.point_valid).sum()) == 1  # none joined
    np.testing.assert_array_equal(np.asarray(rest.valid), np.asarray(c.valid))
    out, rest = mc.activate(win, jnp.asarray(slot, jnp.int32), c, CONFIG, camera, frames[-1].T_world_cam)
    assert int(np.asarray(out.point_valid).sum()) == 1 + mask.sum() and mask.sum() > 20
