"""The monocular system end to end: ``mbavo track --mode mono`` and a sequence without depth, its
outputs (points.ply among them), initialisation notes, a textureless start and a black stretch
(drops, then a new initialisation), and the Python API."""

from __future__ import annotations

import csv
import dataclasses
import json
import pathlib
import shutil

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.bench.mono import trajectory_scores
from mbavo_jax.config import BenchConfig, EvalConfig, RunConfig, load_config
from mbavo_jax.datasets import open_sequence
from mbavo_jax.geometry import ExposureTrajectory, PinholeCamera, Pose
from mbavo_jax.io import read_ply, read_tum_trajectory
from mbavo_jax.mono import candidates as mc
from mbavo_jax.mono.init import TwoView
from mbavo_jax.mono.window import Window, add_keyframe, add_points
from mbavo_jax.odometry import run_odometry
from mbavo_jax.odometry.mono import MonoPipeline, rescaled, typical_idepth
from mbavo_jax.synthetic import PRESETS, SynthConfig, generate_sequence
from mbavo_jax.synthetic.generator import camera_path
from mbavo_jax.synthetic.scene import default_scene, render_exposure, scene_arrays

FRAMES = 36


def rows_of(out) -> list[dict]:
    with open(out / "frames.csv", newline="") as fh:
        return list(csv.DictReader(fh))


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    """A blurred 320x240 sequence (strong preset) without exposure metadata, with depth maps."""
    out = tmp_path_factory.mktemp("mono") / "strong"
    cfg = SynthConfig(**{**PRESETS["strong"], "frames": FRAMES, "width": 320, "height": 240, "subframes": 32, "seed": 1,
                         "real_textures": False, "exposure_info": False})
    generate_sequence(cfg, out, progress=False)
    return out


@pytest.fixture(scope="module")
def mono_run(seq_dir, tmp_path_factory):
    """``mbavo track --mode mono`` on the RGB-D sequence, with depth reading made to fail."""
    from tests.conftest import run_cli

    out = tmp_path_factory.mktemp("mono_run") / "run"
    mp = pytest.MonkeyPatch()
    mp.setattr("mbavo_jax.datasets.loaders.read_depth_png", lambda *a, **k: (_ for _ in ()).throw(AssertionError("depth read")))
    try:
        assert run_cli("track", str(seq_dir), "--out", str(out), "--mode", "mono", "-q", "--format", "json") == 0
    finally:
        mp.undo()
    return out


@pytest.mark.slow
def test_mono_run_tracks_every_frame_after_initialisation(seq_dir, mono_run):
    rows = rows_of(mono_run)
    assert len(rows) == FRAMES
    waiting = [r for r in rows if r["status"] == "initialising"]
    assert rows[0]["status"] == "initialising" and rows[0]["note"].startswith("initialising: reference frame")
    assert all(r["note"].startswith("initialising") for r in waiting)
    started = next(i for i, r in enumerate(rows) if r["status"] != "initialising")
    assert rows[started]["note"].startswith("initialised: parallax") and started <= FRAMES // 2
    assert all(r["status"] in ("converged", "max_steps") for r in rows[started:]), [r["status"] for r in rows]
    t, _ = read_tum_trajectory(mono_run / "trajectory.txt")
    assert len(t) == FRAMES - started
    kf, _ = read_tum_trajectory(mono_run / "keyframes.txt")
    assert len(kf) >= 2 and abs(kf[0] - float(rows[0]["timestamp"])) < 1e-6  # the reference is the first keyframe
    assert sum(1 for r in rows if r["backend_ms"]) >= 1  # bundle adjustments ran


@pytest.mark.slow
def test_mono_run_is_accurate_up_to_scale(seq_dir, mono_run):
    seq = open_sequence(seq_dir)
    scores = trajectory_scores(seq, mono_run, EvalConfig())
    assert scores["ate_pct"] < 5.0, scores
    assert scores["drift_scale_pct"] < 20.0, scores


@pytest.mark.slow
def test_points_ply_holds_the_window_points(mono_run):
    xyz, intensity = read_ply(mono_run / "points.ply")
    assert len(xyz) >= 100 and np.isfinite(xyz).all()
    assert (intensity >= 0).all() and (intensity <= 1).all() and intensity.std() > 0.01
    header = (mono_run / "points.ply").read_text().split("end_header")[0]
    assert f"element vertex {len(xyz):012d}" in header
    _, poses = read_tum_trajectory(mono_run / "trajectory.txt")
    centre = poses[:, :3].mean(0)
    assert np.median(np.linalg.norm(xyz - centre, axis=1)) < 50.0  # the points sit in the scene, not at infinity


@pytest.mark.slow
def test_sequence_without_depth_runs_monocular(seq_dir, tmp_path, mbavo):
    """Auto mode: no depth.txt -> the monocular system; a textureless start is waited out with a note;
    a black stretch is dropped and the system initialises again. Every frame has a row."""
    data = tmp_path / "nodepth"
    shutil.copytree(seq_dir, data, ignore=shutil.ignore_patterns("depth", "depth.txt", "sharp"))
    names = [line.split()[1] for line in (data / "rgb.txt").read_text().splitlines() if not line.startswith("#")]
    for name in names[:3] + names[20:24]:  # black frames: at the start and a stretch in the middle
        cv2.imwrite(str(data / name), np.zeros((240, 320), np.uint8))
    # a lower parallax threshold makes both starts quick enough for this short sequence
    r = mbavo("track", data, "--out", tmp_path / "run", "-q", "--format", "json", "--set", "mono.init_min_parallax_deg=0.3")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["mode"] == "mono" and summary["frames"] == FRAMES
    rows = rows_of(tmp_path / "run")
    assert len(rows) == FRAMES
    assert "too little texture" in rows[1]["note"] or "too little texture" in rows[2]["note"]
    assert any("initialising again" in r["note"] for r in rows[20:25]), [r["note"] for r in rows[20:25]]
    assert all(r["status"] not in ("converged", "max_steps") for r in rows[20:24])
    assert any(r["note"].startswith("initialised") for r in rows[24:]), [r["note"] for r in rows[24:]]
    assert sum(r["note"].startswith("initialised") for r in rows) == 2


def test_rgbd_mode_needs_depth(seq_dir, tmp_path, mbavo):
    data = tmp_path / "nodepth"
    shutil.copytree(seq_dir, data, ignore=shutil.ignore_patterns("depth", "depth.txt", "sharp"))
    r = mbavo("track", data, "--out", tmp_path / "run", "--mode", "rgbd")
    assert r.returncode == 1 and "needs depth" in r.stderr and len(r.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_python_api_runs_the_monocular_pipeline(seq_dir, tmp_path):
    """``run_odometry`` with a ``MonoPipeline`` on a Sequence (depth present but unused)."""
    seq = open_sequence(seq_dir)
    pipeline = MonoPipeline(seq.camera, RunConfig().replace(tracker=dict(n=8)))
    summary = run_odometry(seq, tmp_path / "run", pipeline=pipeline, progress=False, max_frames=14)
    assert summary["mode"] == "mono" and summary["frames"] == 14 and summary["tracked"] >= 3
    assert pipeline.config.tracker.depth_weight == 0.0


@pytest.mark.slow
def test_the_exposure_probe_starts_a_monocular_run_from_an_estimate_not_the_guess(seq_dir, monkeypatch):
    """Without exposure times the monocular loop first runs blind over the first frames (nothing
    deblurred, nothing written) until its estimate settles: the run starts from those samples (true
    fraction 0.75, the guess 0.5), not from the guess, and the probe stops at the first frame whose
    estimate meets the settling rule. The rule itself is tested on constructed samples in
    test_exposure.py; here it is met with a wide margin (three samples within 0.3 of the frame interval
    where they spread by under 0.1), so the stop does not hang on a sample's last digits. Off with
    ``mono.exposure_probe=0`` and for a loop blind to blur."""
    import mbavo_jax.odometry.rgbd as odo_rgbd

    seq = open_sequence(seq_dir)
    settings = ["odometry.mode=mono", "odometry.exposure_pair_ratio=1.2",  # this short path changes speed by less than 1.3x in 6 frames
                "odometry.exposure_settled=0.3"]
    monkeypatch.setattr(odo_rgbd, "SETTLED_SAMPLES", 3)  # the probe's rule (RGBDPipeline.probe_done) reads it
    monkeypatch.setattr(MonoPipeline, "deblurred", lambda *a, **k: (_ for _ in ()).throw(AssertionError("the probe deblurred")))
    asked = []  # (samples so far, the rule's answer) each time the loop asks
    rule = MonoPipeline.probe_done
    monkeypatch.setattr(MonoPipeline, "probe_done", lambda self, state: asked.append((self.estimate(state).count, rule(self, state))) or asked[-1][1])
    pipeline = MonoPipeline(seq.camera, load_config(None, settings))
    start = pipeline.start_state(seq)
    true_fraction = PRESETS["strong"]["exposure_ms"] / 1000 * SynthConfig().fps
    assert start.exposure is not None and start.exposure.count >= 3 and start.tracked == 0 and start.backend is None
    assert abs(start.exposure.fraction() - true_fraction) < abs(pipeline.config.odometry.exposure_guess - true_fraction), start.exposure
    answers = [done for _, done in asked]
    assert answers[-1] and not any(answers[:-1]), asked  # it ran until the rule first held, and stopped there
    assert asked[-1][0] == start.exposure.count == 3 and len(asked) < FRAMES and start.probed_until == seq[len(asked) - 1].timestamp
    fractions = [dataclasses.replace(start.exposure, samples=start.exposure.samples[:k]).fraction() for k in (1, 2, 3)]
    assert max(fractions) - min(fractions) < 0.3 / 2, fractions  # the margin the test relies on
    assert MonoPipeline(seq.camera, load_config(None, [*settings, "mono.exposure_probe=0"])).start_state(seq).exposure is None
    assert MonoPipeline(seq.camera, load_config(None, [*settings, "tracker.blur_aware=false"])).start_state(seq).exposure is None


# ------------------------------------------------- candidates of a sharp keyframe in blurry frames


@pytest.mark.slow
def test_sharp_keyframe_candidates_are_found_in_blurry_frames_through_the_blur_model():
    """A deblurred (sharp) keyframe's candidates traced in frames blurred over ~15 px: compared as
    they are, most searches end as outliers; with the frames' exposure paths (``FrameBlur``) the
    patterns are blurred by the blur model first, and most candidates converge to the true depth."""
    w, h, exposure, speed, rotation = 320, 240, 0.04, 1.0, 90.0
    camera = PinholeCamera.create(262.5, 262.5, (w - 1) / 2, (h - 1) / 2, w, h)
    arrays = scene_arrays(default_scene(0))
    at = lambda t: camera_path(t, speed, rotation, 0)  # noqa: E731
    _, host, depth = render_exposure(arrays, camera, jax.vmap(at)(jnp.array([1.0])), at(1.0))
    host_pose, config = at(1.0), RunConfig().mono
    window, slot = add_keyframe(Window.empty(2, 64, h, w), host, host_pose)
    window, _ = add_points(window, slot, np.array([[160.0, 120.0]], np.float32), np.array([1.0 / np.median(depth)], np.float32))
    plain = blurred = mc.select_candidates(np.asarray(host), 400, config)
    for t in (1.03, 1.07):
        poses = jax.vmap(at)(t + jnp.linspace(-0.5, 0.5, 24) * exposure)
        frame, _, _ = render_exposure(arrays, camera, poses, at(t))
        T_frame_host = at(t).inverse().compose(host_pose)
        path = ExposureTrajectory(at(t - exposure / 2), at(t + exposure / 2)).seen_from(host_pose.inverse())
        blur = mc.FrameBlur.create(path, 0.0, typical_idepth(window, slot))
        plain = mc.trace(plain, host, frame, camera, T_frame_host, jnp.zeros(2, jnp.float32), config)
        blurred = mc.trace(blurred, host, frame, camera, T_frame_host, jnp.zeros(2, jnp.float32), config, blur)
    px = np.asarray(blurred.pixels).astype(int)
    truth = 1.0 / np.asarray(depth)[px[:, 1], px[:, 0]]
    valid = np.asarray(blurred.valid)
    outliers = lambda c: float((np.asarray(c.status) == mc.OUTLIER)[valid].mean())  # noqa: E731
    ready = np.asarray(mc.ready(blurred, config))
    err = np.abs(np.asarray(mc.estimates(blurred)[1]) - truth) / truth
    assert outliers(plain) > 0.3 and outliers(blurred) < 0.1, (outliers(plain), outliers(blurred))
    assert ready.sum() > 2 * np.asarray(mc.ready(plain, config)).sum() and ready.sum() > 0.3 * valid.sum()
    assert np.median(err[ready]) < 0.05


def test_a_new_start_after_a_loss_keeps_the_scale_of_the_lost_window():
    """A two-view start (median point depth 1) rescaled to the lost window's median depth: points and
    translation together, so the geometry (bearings, rotation) is unchanged."""
    T = Pose.from_matrix(jnp.asarray(np.array([[1, 0, 0, 0.1], [0, 1, 0, -0.02], [0, 0, 1, 0.01], [0, 0, 0, 1]], np.float32)))
    idepth = np.array([0.5, 1.0, 2.0], np.float32)
    start = TwoView(True, "", T, np.zeros((3, 2), np.float32), idepth, 2.0, 3, 3)
    again = rescaled(start, 2.5)
    assert np.median(1.0 / again.idepth) == pytest.approx(2.5)
    assert np.allclose(np.asarray(again.T_ref_cur.t), 2.5 * np.asarray(T.t)) and np.allclose(again.T_ref_cur.q, T.q)
    assert rescaled(start, 1.0) is start


def test_exposure_pairs_use_the_window_points_depth_at_the_tracked_pose():
    """A frame kept for the exposure estimate's pairs carries the depth of the window's points seen
    from its tracked pose (NaN elsewhere), not the filled map the frame was tracked with: only the
    points give the blur of the pair's tracking a reliable depth."""
    from mbavo_jax.datasets.base import Frame
    from mbavo_jax.odometry.mono import MonoState
    from mbavo_jax.odometry.state import RunState

    w, h = 160, 120
    camera = PinholeCamera.create(131.0, 131.0, (w - 1) / 2, (h - 1) / 2, w, h)
    window = Window.empty(4, 64, h, w)
    for k in range(3):
        window, _ = add_keyframe(window, np.zeros((h, w), np.float32), Pose(Pose.identity().q, jnp.array([0.05 * k, 0.0, 0.0])))
    pixels = np.array([[40.0, 30.0], [80.0, 60.0], [120.0, 90.0]], np.float32)
    window, _ = add_points(window, 0, pixels, np.array([0.5, 0.25, 1.0], np.float32))
    pipeline = MonoPipeline(camera, RunConfig().replace(odometry=dict(mode="mono")))
    mono = MonoState(window=window, slots=(0, 1, 2), stamps=(0.0, 0.1, 0.2), candidates=(None,) * 4)
    state = RunState(mids=((0.2, Pose.identity()),), backend=mono)
    frame = Frame(3, 0.3, np.full((h, w), 0.5, np.float32), camera, depth=np.ones((h, w), np.float32))
    recent = pipeline.exposure_pairing(state, frame, Pose.identity(), 100.0, 0.1).recent
    depth = recent[-1].depth
    assert np.isfinite(depth).sum() == 3
    assert np.allclose(depth[[30, 60, 90], [40, 80, 120]], [2.0, 4.0, 1.0])


def test_the_bench_defaults_find_the_real_clips_from_any_folder(tmp_path, monkeypatch):
    """``--tum`` / ``--kitti`` default to ``../shared/data/...``: from a folder without that path the
    clip is looked up by name in the shared data folder; a path that exists is kept; an unknown one
    comes back unchanged (the loader then says it is missing)."""
    from mbavo_jax.bench.sequences import real_clip

    from .conftest import shared_dataset

    kitti = shared_dataset("kitti07_head160")
    shared_dataset("tum_fr1_xyz_head37")
    monkeypatch.setenv("MBAVO_SHARED_DATA", str(kitti.parent))
    monkeypatch.chdir(tmp_path)
    for value in (BenchConfig().kitti, BenchConfig().tum):
        found = real_clip(value)
        assert found.is_dir() and found.name == pathlib.Path(value).name and found.parent == kitti.parent
    (tmp_path / "mine").mkdir()
    assert real_clip("mine") == pathlib.Path("mine")
    assert real_clip("../nowhere/clip") == pathlib.Path("../nowhere/clip")


def test_the_bench_draws_run_each_method_at_each_huber_draw_and_the_seed_means_use_their_mean(tmp_path, monkeypatch):
    """``bench mono --draws K``: draw 0 is the run as configured, in the method's folder; draw d the
    tracker's Huber threshold times HUBER_DRAWS[d] / HUBER_DRAWS[0], in its own folder. The row is
    draw 0's with every draw's ATE and the mean of those that scored, which the seed means use."""
    from mbavo_jax.bench import mono as bm
    from mbavo_jax.config import HUBER_DRAWS

    calls = []
    ates = iter([2.0, None, 4.0])

    def fake_run(seq, run, config, progress):
        calls.append((run.name, config.tracker.huber))
        ate = next(ates)
        return {"dropped": int(ate is None), **({} if ate is None else {"ate_pct": ate, "ate_rmse_m": ate / 100})}

    monkeypatch.setattr(bm, "run_method", fake_run)
    row = bm.run_draws(None, tmp_path / "mono_n64", RunConfig(), draws=3, progress=False)
    assert calls == [("mono_n64", HUBER_DRAWS[0]), (f"mono_n64_huber{HUBER_DRAWS[1]:.7f}", HUBER_DRAWS[1]),
                     (f"mono_n64_huber{HUBER_DRAWS[2]:.7f}", HUBER_DRAWS[2])]
    assert row["ate_pct"] == 2.0 and row["ate_pct_mean"] == pytest.approx(3.0)
    assert [d["ate_pct"] for d in row["draws"]] == [2.0, None, 4.0] and [d["dropped"] for d in row["draws"]] == [0, 1, 0]
    assert bm.draw_huber(0.05, 2) == pytest.approx(0.05 * HUBER_DRAWS[2] / HUBER_DRAWS[0]) and bm.draw_huber(HUBER_DRAWS[0], 3) == HUBER_DRAWS[3]
    calls.clear()
    ates = iter([5.0])
    assert bm.run_draws(None, tmp_path / "mono_n1", RunConfig(), draws=1, progress=False) == {"dropped": 0, "ate_pct": 5.0, "ate_rmse_m": 0.05}
    results = {"a": {"mono_n64": row, "mono_n1": {"ate_pct": 6.0, "draws": [], "ate_pct_mean": 1.5}}}
    assert bm.seed_means(results, ["a"])["mono_n64"]["ratio"] == pytest.approx(2.0)  # 3.0 against 1.5: the means over draws
    with pytest.raises(Exception, match=f"draws: at most {len(HUBER_DRAWS)}"):
        BenchConfig(draws=len(HUBER_DRAWS) + 1)
    results["a"]["mono_n64"].update(drift_trans_pct=1.0, drift_scale_pct=1.0, initialising=0, keyframes=4, seconds_per_frame=1.0,
                                    track_s_per_frame=0.5, backend_s_per_frame=0.3, other_s_per_frame=0.2, backend_s_per_keyframe=1.0,
                                    compile_s=0.0)
    table = bm.format_mono_table(results)
    assert "over the draws: mean ATE (range)" in table and "| 3.00 % (2.00-4.00), 2 of 3 scored, 1 dropped |" in table


def test_the_bench_means_over_seeds_compare_only_sequences_both_methods_scored():
    """``bench mono --seeds``: the presets' sequences at each seed (the base seed keeps the plain
    name), and per method the mean ATE over the seeds it scored, its ratio to mono_n1 over the
    sequences both scored, and each seed's ratio; a run without a score counts as run, not scored."""
    from mbavo_jax.bench.mono import format_seed_table, seed_groups, seed_means

    cfg = BenchConfig(presets="none,strong", seed=3, seeds="1,3, 2")
    assert seed_groups(cfg) == {"none": {"none": 3, "none_s1": 1, "none_s2": 2}, "strong": {"strong": 3, "strong_s1": 1, "strong_s2": 2}}
    with pytest.raises(Exception, match="seeds: not a non-negative integer: x"):
        BenchConfig(seeds="1,x")
    results = {"a": {"mono_n64": {"ate_pct": 0.4}, "mono_n1": {"ate_pct": 0.2}},
               "b": {"mono_n64": {"ate_pct": 0.1}, "mono_n1": {"ate_pct": 0.3}},
               "c": {"mono_n64": {"ate_pct": 9.0}, "mono_n1": {"dropped": 3}}}
    means = seed_means(results, ["a", "b", "c"])
    assert means["mono_n64"]["scored"] == 3 and means["mono_n64"]["runs"] == 3
    assert means["mono_n64"]["mean_ate_pct"] == pytest.approx(9.5 / 3)
    assert means["mono_n64"]["ratio"] == pytest.approx(0.5 / 0.5)  # c is left out: n = 1 has no score there
    assert means["mono_n64"]["ratios"] == pytest.approx([2.0, 1 / 3])
    assert means["mono_n1"]["scored"] == 2 and means["mono_n1"]["runs"] == 3
    table = format_seed_table(results, {"none": ["a", "b", "c"]})
    assert "| none | mono_n64 | 3 of 3 | 3.167 | 1.00 | 2.00, 0.33 |" in table
