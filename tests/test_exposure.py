"""Sequences without exposure times: the exposure is estimated online from pairs of raw frames
(``odometry.exposure``), not assumed away; known exposure times are used as before."""

from __future__ import annotations

import csv
import dataclasses
import json

import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.config import OdometryConfig, load_config
from mbavo_jax.datasets import open_sequence
from mbavo_jax.errors import MbavoError
from mbavo_jax.evaluation import exposure_path_error, exposure_path_lengths
from mbavo_jax.geometry import Pose
from mbavo_jax.io import read_exposure_file
from mbavo_jax.odometry import ExposureEstimate, RawFrame, exposure_mode, pick_pair, run_odometry
import mbavo_jax.odometry.rgbd as rgbd
from mbavo_jax.odometry.rgbd import RGBDPipeline
from mbavo_jax.synthetic import PRESETS, SynthConfig, exposure_hidden_copy, generate_sequence

SMALL_SET = ["tracker.levels=3", "tracker.points=[192,128,64]", "tracker.cell=[10,7,5]", "tracker.max_steps=[10,12,20]"]
# These 16-frame paths change speed smoothly (by 1.29x at most over their first 8 frames, seed 2, strong): the probe pairs from 1.2x.
PROBE_SET = [*SMALL_SET, "odometry.exposure_pair_ratio=1.2"]


def _generated(tmp_path_factory, preset: str):
    out = tmp_path_factory.mktemp(preset) / preset
    cfg = SynthConfig(**{**PRESETS[preset], "frames": 16, "width": 160, "height": 120, "subframes": 32, "seed": 2, "real_textures": False})
    generate_sequence(cfg, out, progress=False)
    return out, cfg


@pytest.fixture(scope="module")
def strong(tmp_path_factory):
    return _generated(tmp_path_factory, "strong")


def _camera(seq) -> dict:
    return {k: seq.meta[k] for k in ("fx", "fy", "cx", "cy", "width", "height")}


def test_exposure_mode_decides_known_estimated_or_none():
    assert exposure_mode(OdometryConfig(), recorded=True) == "known"
    assert exposure_mode(OdometryConfig(), recorded=False) == "estimate"
    assert exposure_mode(OdometryConfig(exposure_s=0.02), recorded=False) == "known"
    assert exposure_mode(OdometryConfig(exposure="estimate"), recorded=True) == "estimate"
    assert exposure_mode(OdometryConfig(exposure="none"), recorded=True) == "none"
    with pytest.raises(MbavoError, match="exposure=known"):
        exposure_mode(OdometryConfig(exposure="known"), recorded=False)
    with pytest.raises(ValueError, match="exposure"):
        OdometryConfig(exposure="sometimes")


def test_estimate_is_the_weighted_median_of_recent_samples():
    est = ExposureEstimate(guess=0.5, window=3)
    assert est.seconds(0.04) == pytest.approx(0.02) and est.fraction() == 0.5 and est.count == 0
    est = est.add((0.010, 1.0), 0.033).add((0.030, 5.0), 0.033).add(None, 0.033).add((0.020, 1.0), 0.033)
    # interpolated between the weight midpoints 0.5, 1.5, 4.5 of the sorted samples: the heavy one pulls
    assert est.count == 3 and est.seconds(1.0) == pytest.approx(0.020 + 0.010 * 2 / 3)
    assert est.fraction() == pytest.approx((0.020 + 0.010 * 2 / 3) / 0.033)
    est = est.add((0.012, 1.0), 0.033).add((0.014, 1.0), 0.033).add((0.016, 1.0), 0.033)
    assert est.count == 3 and est.seconds(1.0) == pytest.approx(0.014)  # only the window counts
    assert ExposureEstimate(0.5, 30).add((0.010, 2.0), 0.033).add((0.020, 2.0), 0.033).seconds(1.0) == pytest.approx(0.015)


def test_reblur_fraction_matches_box_blurs_in_the_image_domain():
    """h(ρ) against a brute-force search in the image domain: a random signal whose power falls as
    1/f, box-blurred over ρ·b and over b = 24 px (1/8 px steps); the box ℓ that best turns the first
    into the second is h·b within 2 %. Added variances (√(1 − ρ²)) would be 6-13 % short."""
    from mbavo_jax.odometry.exposure import reblur_fraction

    def centred_box(x, n):  # mean over n (odd) samples centred on each sample, same indices as x
        c = np.concatenate([[0.0], np.cumsum(x)])
        h = n // 2
        return np.concatenate([np.zeros(h), (c[n:] - c[:-n]) / n, np.zeros(h)])

    sub, b = 8, 24
    f = np.fft.rfftfreq(2**17, d=1 / sub)  # cycles per px
    amp = np.zeros_like(f)
    band = (f > 0) & (f <= 0.5)
    amp[band] = f[band] ** -0.5
    x = np.fft.irfft(amp * np.exp(2j * np.pi * np.random.default_rng(0).random(len(f))), 2**17)
    nb = b * sub + 1
    inner = slice(2 * nb, -2 * nb)
    target = centred_box(x, nb)[inner]
    for rho in (0.3, 0.5, 0.67, 0.72):
        a = centred_box(x, 2 * int(rho * nb / 2) + 1)
        lengths = np.arange(1, nb + 1, 2)
        err = [np.mean((centred_box(a, n)[inner] - target) ** 2) for n in lengths]
        best = lengths[int(np.argmin(err))] / nb
        assert reblur_fraction(rho) == pytest.approx(best, rel=0.02), (rho, best)
        if rho >= 0.5:
            assert best > np.sqrt(1 - rho**2) + 0.05


def test_estimate_settles_when_it_stops_moving():
    est = ExposureEstimate(guess=0.5, window=30)
    for e in (0.020, 0.024, 0.021, 0.022, 0.023, 0.0215):
        est = est.add((e, 1.0), 0.04)
    # the estimate after each sample, as fractions of 0.04 s: 0.5, 0.55, 0.525, 0.5375, 0.55, 0.54375
    assert not est.settled(7, 1.0)  # too few samples
    assert est.settled(6, 0.051) and not est.settled(6, 0.049)
    assert est.settled(5, 0.026) and not est.settled(6, 0.026)
    assert est.settled(3, 0.013) and not est.settled(3, 0.012)


def test_pairs_need_speeds_that_differ_enough():
    def raw(stamp, speed):
        return RawFrame(stamp, np.zeros((2, 2)), None, Pose.identity(), Pose.identity(), 0.033, speed)

    recent = (raw(1.0, 100.0), raw(1.1, 140.0), raw(1.2, 105.0))
    slow, fast = pick_pair(recent, raw(1.3, 150.0), ratio=1.3)
    assert (slow.stamp, fast.stamp) == (1.0, 1.3)
    slow, fast = pick_pair(recent, raw(1.3, 70.0), ratio=1.3)  # the current frame is the slow one
    assert (slow.stamp, fast.stamp) == (1.3, 1.1)
    assert pick_pair(recent, raw(1.3, 120.0), ratio=1.3) is None


def test_a_frames_speed_is_the_central_difference_about_its_exposure():
    """Under acceleration the speed about a frame's exposure is the previous-to-next mid pose
    difference (the exposure is centred on the mid pose), not the previous-to-own one, which lags
    by half a frame: x(t) = v t + a t², depth 2 m, fx 100: 100 v / 2 px/s, where the backward
    difference gives 100 (v - a dt) / 2."""
    from mbavo_jax.config import TrackerConfig
    from mbavo_jax.geometry import PinholeCamera
    from mbavo_jax.odometry.exposure import point_speed, with_keyframe, with_next

    v, a, dt = 0.3, 3.0, 1 / 30
    at = lambda t: Pose(Pose.identity().q, jnp.array([v * t + a * t * t, 0.0, 0.0], jnp.float32))
    camera = PinholeCamera.create(100.0, 100.0, 39.5, 29.5, 80, 60)
    image = np.random.default_rng(0).random((60, 80)).astype(np.float32)
    frame = with_keyframe(RawFrame(1.0, image, np.full((60, 80), 2.0, np.float32), at(0.0), at(-dt), dt, 0.0), camera, TrackerConfig())
    T_ref = frame.T_world_mid.inverse()
    assert point_speed(frame.keyframe, T_ref, frame) == pytest.approx(100 * (v - a * dt) / 2, rel=0.01)  # no next frame yet
    central = with_next(frame, at(dt), dt, 0.0)
    assert central.velocity()[2] == pytest.approx(2 * dt)
    assert point_speed(central.keyframe, T_ref, central) == pytest.approx(100 * v / 2, rel=0.01)


def test_known_exposure_without_times_is_one_line_error(strong, tmp_path, mbavo):
    hidden = exposure_hidden_copy(strong[0], tmp_path / "hidden")
    r = mbavo("track", hidden, "--out", tmp_path / "run", "-q", "--set", "odometry.exposure=known")
    assert r.returncode == 1 and "Traceback" not in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1 and "exposure" in r.stderr


@pytest.mark.slow
def test_blurred_sequence_without_exposure_times_recovers_the_exposure(strong, tmp_path, mbavo):
    """No exposure_ms, no times.txt: the run estimates the exposure (true fraction 0.75) within
    20 %, gives blurred frames a real exposure path (start != end), and writes the estimate per
    frame and in the summary."""
    path, cfg = strong
    hidden = exposure_hidden_copy(path, tmp_path / "hidden")
    seq = open_sequence(hidden)
    assert seq.exposures is None and seq.exposure_paths is not None
    out = tmp_path / "run"
    r = mbavo("track", hidden, "--out", out, "--format", "json", "-q", *[a for s in SMALL_SET for a in ("--set", s)])
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    true_fraction = cfg.exposure_ms / 1000 * cfg.fps
    assert summary["exposure"] == "estimate" and summary["exposure_samples"] >= 3, summary
    assert abs(summary["exposure_fraction"] - true_fraction) <= 0.2 * true_fraction, summary
    with open(out / "frames.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert all(r["exposure"] == "estimate" and float(r["exposure_fraction"]) > 0 for r in rows)
    est = read_exposure_file(out / "exposure.txt")
    lengths = exposure_path_lengths(est, _camera(seq))
    assert np.all(lengths[1:] > 0.3), lengths  # start != end on every blurred frame after the first
    ratio = exposure_path_error(seq.exposure_paths, est, _camera(seq))["length_ratio"]["median"]
    assert 0.5 < ratio < 1.5, ratio


@pytest.mark.slow
def test_probe_starts_the_run_from_an_estimate_not_the_guess(strong, tmp_path):
    """With the exposure estimated, the first frames are run once beforehand (nothing written): the
    run starts from their samples (true fraction 0.75, the guess 0.5), reports the estimate on frame
    0 and does not pair those frames again."""
    path, cfg = strong
    seq = open_sequence(exposure_hidden_copy(path, tmp_path / "hidden"))
    config = load_config(None, PROBE_SET)
    pipeline = RGBDPipeline(seq.camera, config)
    start = pipeline.start_state(seq)
    true_fraction = cfg.exposure_ms / 1000 * cfg.fps
    assert start.exposure is not None and start.exposure.count >= 3 and start.tracked == 0
    assert pipeline.probe_done(start) or start.probed_until == seq[min(config.odometry.exposure_probe, len(seq)) - 1].timestamp
    assert abs(start.exposure.fraction() - true_fraction) <= 0.2 * true_fraction, start.exposure
    assert RGBDPipeline(seq.camera, load_config(None, [*SMALL_SET, "odometry.exposure_probe=0"])).start_state(seq).exposure is None
    assert RGBDPipeline(seq.camera, config).start_state(open_sequence(path)).exposure is None  # exposure known: no probe
    run_odometry(seq, tmp_path / "run", config, max_frames=2, progress=False)
    with open(tmp_path / "run" / "frames.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 2 and float(rows[0]["exposure_fraction"]) == pytest.approx(start.exposure.fraction(), abs=1e-4)
    assert not rows[1]["sample_s"]  # frame 1 was paired by the probe


@pytest.mark.slow
def test_the_probe_runs_on_until_a_slowly_changing_path_gives_its_samples(tmp_path_factory):
    """Issue 57's regression: this path (strong preset, seed 17) changes speed so slowly that its first
    exposure sample comes after the 12th frame. A probe of a fixed 12 frames ended without one, and the
    run tracked and deblurred its first 17 frames along the guess (half the frame interval where the
    truth is three quarters): 2x n = 1's ATE at 320x240. The probe now runs until its estimate has
    settled (at most ``odometry.exposure_probe`` frames), so the run starts from samples."""
    out = tmp_path_factory.mktemp("slow_speed") / "seq"
    cfg = SynthConfig(**{**PRESETS["strong"], "frames": 24, "width": 160, "height": 120, "subframes": 32, "seed": 17,
                         "real_textures": False, "exposure_info": False})
    generate_sequence(cfg, out, progress=False)
    seq = open_sequence(out)
    start = RGBDPipeline(seq.camera, load_config(None, [])).start_state(seq)
    assert start.exposure is not None and start.exposure.count >= 1, "the probe ended without a sample"
    assert start.probed_until > seq[11].timestamp, start.probed_until  # past the old fixed 12 frames


def test_a_short_exposure_picks_adaptive_n_and_a_settled_one_thins_the_samples():
    """A short exposure, estimated (settled or not) or known, has frames predicted by a velocity
    tracked with adaptive n (few virtual frames for little blur); a long one does not. Once the
    estimate has settled, only every ``exposure_thin``-th tracked frame is paired, and frames the
    exposure probe paired are not paired again."""
    from types import SimpleNamespace

    from mbavo_jax.geometry import PinholeCamera
    from mbavo_jax.odometry.state import RunState

    config = load_config(None, [])
    pipe = RGBDPipeline(PinholeCamera.create(100.0, 100.0, 50.0, 40.0, 100, 80), config)
    mids = ((1.0, Pose.identity()), (1.04, Pose.identity()))
    frame = SimpleNamespace(timestamp=1.08, exposure=None)

    def state(*fractions):
        est = ExposureEstimate(0.5, 30)
        for f in fractions:
            est = est.add((f * 0.04, 1.0), 0.04)
        return RunState(mids=mids, exposure=est, tracked=9)

    short, unsettled, long = state(*[0.02] * 6), state(0.4, 0.01, 0.02, 0.01, 0.3, 0.02), state(*[0.7] * 6)
    assert pipe.tracker_config(frame, True, short).n_mode == "adaptive"
    assert pipe.tracker_config(frame, True, unsettled).n_mode == "adaptive"
    assert pipe.tracker_config(frame, True, long).n_mode == "fixed"
    assert pipe.tracker_config(frame, True, RunState()).n_mode == "fixed"  # nothing tracked yet: no velocity
    assert pipe.tracker_config(frame, False, short).blur_prior == 0  # no velocity: the prior is off, n as configured
    assert pipe.tracker_config(frame, False, short).n_mode == "fixed"
    assert pipe.tracker_config(SimpleNamespace(timestamp=1.08, exposure=0.0), True, RunState(mids=mids)).n_mode == "adaptive"
    assert pipe.tracker_config(SimpleNamespace(timestamp=1.08, exposure=0.03), True, RunState(mids=mids)).n_mode == "fixed"
    assert not pipe.sample_due(short, 1.08) and pipe.sample_due(dataclasses.replace(short, tracked=16), 1.08)
    assert pipe.sample_due(unsettled, 1.08) and pipe.sample_due(state(*[0.02] * 5), 1.08)
    assert not pipe.sample_due(dataclasses.replace(unsettled, probed_until=1.08), 1.08)


def test_a_frame_predicted_mildly_blurred_is_tracked_with_adaptive_n_and_a_sharp_one_with_one_pose(monkeypatch):
    """The fallback rule (issue 57), per frame from the blur its constant-velocity guess predicts
    on the keyframe's points, whatever the exposure: at or above ``odometry.adaptive_below_px`` n as
    configured; below it adaptive n (few virtual frames for a little blur); below
    ``sharp_blur_px`` one pose (start = end). Never for a frame without a velocity, a rolling
    shutter, or ``adaptive_below_px=0``."""
    from types import SimpleNamespace

    from mbavo_jax.geometry import ExposureTrajectory, PinholeCamera
    from mbavo_jax.odometry.state import RunState

    mids = ((1.0, Pose.identity()), (1.04, Pose.identity()))
    state = RunState(mids=mids, exposure=ExposureEstimate(0.5, 30).add((0.03, 1.0), 0.04), tracked=9)
    object.__setattr__(state, "keyframe", SimpleNamespace(keyframe=None))  # read only by the predicted blur, patched below
    frame, init = SimpleNamespace(timestamp=1.08, exposure=None), ExposureTrajectory(Pose.identity(), Pose.identity())
    camera = PinholeCamera.create(100.0, 100.0, 50.0, 40.0, 100, 80)

    def chosen(blur_px, settings=(), informed=True, readout=0.0):
        monkeypatch.setattr(rgbd, "predicted_blur_px", lambda keyframe, traj: blur_px)
        tracker, _ = RGBDPipeline(camera, load_config(None, list(settings))).frame_tracker(state, frame, init, informed, readout)
        return "one pose" if not tracker.blur_aware else tracker.n_mode

    below, sharp = OdometryConfig().adaptive_below_px, OdometryConfig().sharp_blur_px
    assert chosen(below + 4) == chosen(below) == "fixed"
    assert chosen(below - 0.1) == chosen(2.0) == chosen(sharp) == "adaptive"
    assert chosen(sharp / 2) == chosen(0.0) == "one pose"
    assert chosen(2.0, ["odometry.adaptive_below_px=0"]) == "fixed" and chosen(2.0, informed=False) == "one pose"
    assert chosen(2.0, readout=0.5) == "fixed"


@pytest.mark.slow
def test_sharp_sequence_without_exposure_times_keeps_start_and_end_together(tmp_path_factory, tmp_path):
    """A sharp sequence without exposure times: the estimate goes to a short exposure and the
    exposure paths stay short once it has samples (from the first frame when the exposure probe,
    which runs until the estimate settles, gave them all)."""
    path, _ = _generated(tmp_path_factory, "none")
    hidden = exposure_hidden_copy(path, tmp_path / "hidden")
    seq = open_sequence(hidden)
    out = tmp_path / "run"
    summary = run_odometry(seq, out, load_config(None, SMALL_SET), progress=False)
    assert summary["exposure"] == "estimate" and summary["exposure_samples"] >= 1, summary
    assert summary["exposure_fraction"] < 0.15, summary
    with open(out / "frames.csv", newline="") as fh:
        first_sample = next((int(r["index"]) for r in csv.DictReader(fh) if r["sample_s"]), -1)
    lengths = exposure_path_lengths(read_exposure_file(out / "exposure.txt"), _camera(seq))
    assert np.all(lengths[first_sample + 1:] < 0.25), (first_sample, lengths)


@pytest.mark.slow
def test_sharp_frames_and_the_exposure_probe_are_tracked_with_one_pose(tmp_path_factory, tmp_path, monkeypatch):
    """A sharp sequence without exposure times: the probe tracks blind and deblurs nothing, yet
    gives samples; in the run, frames whose predicted blur is under half a pixel (the estimate is
    short) are tracked with one pose, n = 1."""
    path, _ = _generated(tmp_path_factory, "none")
    seq, config = open_sequence(exposure_hidden_copy(path, tmp_path / "hidden")), load_config(None, PROBE_SET)

    def no_deblur(*args, **kwargs):
        raise AssertionError("the exposure probe deblurred a keyframe")

    monkeypatch.setattr(rgbd, "deblur", no_deblur)
    start = RGBDPipeline(seq.camera, config).start_state(seq)
    assert start.exposure is not None and start.exposure.count >= 1 and start.exposure.fraction() < 0.15, start.exposure
    monkeypatch.undo()
    run_odometry(seq, tmp_path / "run", config, progress=False)
    with open(tmp_path / "run" / "frames.csv", newline="") as fh:
        n = [int(r["n_finest"]) for r in csv.DictReader(fh)][1:]
    assert sum(k == 1 for k in n) >= 0.8 * len(n), n


@pytest.mark.slow
def test_resumed_estimate_continues_as_the_uninterrupted_run(strong, tmp_path):
    """--resume restores the exposure samples and the raw frames kept for pairing from frames.csv:
    the resumed run's estimate and poses follow the uninterrupted run's."""
    hidden = exposure_hidden_copy(strong[0], tmp_path / "hidden")
    seq, cfg = open_sequence(hidden), load_config(None, SMALL_SET)
    full = run_odometry(seq, tmp_path / "full", cfg, progress=False)
    run_odometry(seq, tmp_path / "resumed", cfg, max_frames=10, progress=False)
    resumed = run_odometry(seq, tmp_path / "resumed", cfg, resume=True, progress=False)
    assert resumed["exposure_samples"] == full["exposure_samples"], (resumed, full)
    assert resumed["exposure_ms"] == pytest.approx(full["exposure_ms"], rel=1e-3)
    a, b = (np.loadtxt(tmp_path / name / "trajectory.txt") for name in ("full", "resumed"))
    assert a.shape == b.shape and np.abs(a[:, 1:4] - b[:, 1:4]).max() < 1e-4


@pytest.mark.slow
def test_pairs_are_tracked_without_the_prior_on_the_finest_levels(strong, tmp_path, monkeypatch):
    """A pair's frames are tracked against each other without the exposure-motion prior, on the
    ``odometry.exposure_pair_levels`` finest pyramid levels only (both frames are tracked already)."""
    import mbavo_jax.odometry.exposure as exposure

    seen, track = [], exposure.track

    def recording(keyframe, frame, init, config, **kwargs):
        seen.append((config.levels, config.blur_prior))
        return track(keyframe, frame, init, config, **kwargs)

    monkeypatch.setattr(exposure, "track", recording)
    seq = open_sequence(exposure_hidden_copy(strong[0], tmp_path / "hidden"))
    config = load_config(None, [*PROBE_SET, "odometry.exposure_pair_levels=1"])
    start = RGBDPipeline(seq.camera, config).start_state(seq)
    assert start.exposure is not None and start.exposure.count >= 1
    assert seen and set(seen) == {(1, 0.0)}, seen
