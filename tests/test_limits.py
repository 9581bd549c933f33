"""Limits of the settings: the image-size rule (``TrackerConfig.for_image``) and the memory check
(``tracking.memory.check_memory``). Pure functions, except one small keyframe and one tiny track."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from mbavo_jax.config import MIN_CELL, RunConfig, TrackerConfig, _grid_cells
from mbavo_jax.errors import ConfigError
from mbavo_jax.geometry.camera import PinholeCamera
from mbavo_jax.tracking import Keyframe, track
from mbavo_jax.tracking.memory import GIB, available_memory, check_memory, estimate_memory

DEFAULT = TrackerConfig()
PER_LEVEL = ("levels", "points", "cell", "max_steps", "min_valid", "min_keyframe_points")
ROOMY = (64.0 * GIB, "this machine has")


@pytest.mark.parametrize("height, width", [(240, 320), (480, 640)])
def test_benchmark_sizes_keep_every_default(height, width):
    eff = DEFAULT.for_image(height, width)
    assert eff is DEFAULT and eff == TrackerConfig()
    assert {k: getattr(eff, k) for k in PER_LEVEL} == {k: getattr(TrackerConfig(), k) for k in PER_LEVEL}
    assert DEFAULT.size_note(height, width) == ""


def test_small_images_get_fewer_levels_and_smaller_cells():
    eff = DEFAULT.for_image(120, 160)
    assert (eff.levels, eff.cell, eff.points, eff.max_steps) == (3, (30, 20, 10), (384, 256, 192), (8, 10, 12))
    note = DEFAULT.size_note(120, 160)
    assert note.startswith("160x120: using 3 pyramid levels instead of 4") and "\n" not in note
    assert DEFAULT.for_image(48, 64).levels == 2


@settings(max_examples=200, deadline=None)
@given(st.integers(32, 2000), st.integers(32, 2000))
def test_every_level_used_holds_enough_cells(height, width):
    eff = DEFAULT.for_image(height, width)
    assert 1 <= eff.levels <= DEFAULT.levels and all(MIN_CELL <= c <= d for c, d in zip(eff.cell, DEFAULT.cell))
    for level in range(eff.levels):
        assert _grid_cells(height >> level, width >> level, eff.cell[level]) >= DEFAULT.min_cells
    assert eff.for_image(height, width) == eff  # the rule is idempotent: keyframes and frames agree


def test_settings_that_already_fit_are_kept():
    small = TrackerConfig(levels=3, points=(192, 128, 64), cell=(10, 7, 5), max_steps=(10, 12, 20))  # the tests' 160x120 set
    assert small.for_image(120, 160) is small


def test_too_small_images_are_refused_in_one_line():
    with pytest.raises(ConfigError, match=r"24x24 .*too small.*tracker\.min_valid to 48") as err:
        DEFAULT.for_image(24, 24)
    assert "\n" not in str(err.value)
    assert dataclasses.replace(DEFAULT, min_valid=48).for_image(24, 24).levels == 1  # the fix it names works


def _textured(height, width, seed=0):
    rng = np.random.default_rng(seed)
    image = np.kron(rng.uniform(0.1, 0.9, (height // 4, width // 4)), np.ones((4, 4))).astype(np.float32)
    return image, np.full((height, width), 2.0, np.float32)


def test_keyframe_is_built_with_the_effective_levels():
    image, depth = _textured(48, 64)
    kf = Keyframe.create(image, depth, PinholeCamera.create(50.0, 50.0, 31.5, 23.5, 64, 48), DEFAULT)
    assert len(kf.images) == len(kf.points) == 2 and kf.points[1].pixels.shape == (256, 2)


@pytest.mark.slow
def test_tiny_image_tracks_with_default_levels():
    image, depth = _textured(48, 64)
    config = dataclasses.replace(DEFAULT, n=2, n_coarse_min=2, hypotheses=False)
    kf = Keyframe.create(image, depth, PinholeCamera.create(50.0, 50.0, 31.5, 23.5, 64, 48), config)
    result = track(kf, image, config=config)
    assert [p["level"] for p in result.diagnostics["levels"]] == [1, 0] and result.status.ok


# ------------------------------------------------------------------------------------------ memory

# Peak resident memory (bytes) of `mbavo track` on a 320x240 sequence, --max-frames 3, deblurring off,
# and of `mbavo deblur` (2 CPU cores, jax CPU): the estimate must bound them within 3x.
MEASURED_TRACK = {64: 1062720e3 * 1.024, 512: 1491628e3 * 1.024, 2048: 2435240e3 * 1.024}
MEASURED_DEBLUR = {(240, 320, 64): 661496e3 * 1.024, (240, 320, 256): 1319416e3 * 1.024, (480, 640, 64): 1284124e3 * 1.024}


@pytest.mark.parametrize("n", sorted(MEASURED_TRACK))
def test_estimate_bounds_measured_tracking_peaks(n):
    config = RunConfig().replace(tracker=dict(n=n), odometry=dict(deblur_min_blur_px=float("inf")))
    assert MEASURED_TRACK[n] <= estimate_memory(config, 240, 320).total <= 3 * MEASURED_TRACK[n]


@pytest.mark.parametrize("height, width, n", sorted(MEASURED_DEBLUR))
def test_estimate_bounds_measured_deblurring_peaks(height, width, n):
    est = estimate_memory(RunConfig().replace(deblur=dict(n=n)), height, width)
    assert MEASURED_DEBLUR[height, width, n] <= est.total <= 3 * MEASURED_DEBLUR[height, width, n]


def test_default_settings_fit_a_small_machine():
    check_memory(RunConfig(), 480, 640, (4.0 * GIB, "this machine has"))
    check_memory(RunConfig(), 240, 320)  # and this one


def test_huge_n_is_refused_naming_the_setting():
    config = RunConfig().replace(tracker=dict(n=100000))
    with pytest.raises(ConfigError, match=r"^tracker\.n=100000.* need about \d+ GiB at 640x480 \(this machine has 64 GiB\): "
                                          r"lower tracker\.n or tracker\.points$"):
        check_memory(config, 480, 640, ROOMY)


def test_large_images_are_limited_by_deblurring():
    with pytest.raises(ConfigError, match=r"^deblur\.n=0, deblur\.n_max=64 need .* lower deblur\.n_max"):
        check_memory(RunConfig(), 2160 * 2, 3840 * 2, ROOMY)
    check_memory(RunConfig().replace(odometry=dict(deblur_min_blur_px=float("inf"))), 2160 * 2, 3840 * 2, ROOMY)


def test_estimate_grows_with_the_settings():
    base = estimate_memory(RunConfig(), 480, 640)
    more_n = estimate_memory(RunConfig().replace(tracker=dict(n=1024)), 480, 640)
    autodiff = estimate_memory(RunConfig().replace(tracker=dict(n=1024, jacobian="autodiff")), 480, 640)
    bigger = estimate_memory(RunConfig(), 960, 1280)
    assert base.tracking < more_n.tracking < autodiff.tracking and base.deblurring < bigger.deblurring
    assert base.total < estimate_memory(RunConfig().replace(tracker=dict(n=4096)), 480, 640).total


def test_available_memory_is_known():
    have, what = available_memory()
    assert have > 0.5 * GIB and what
