"""`mbavo track`: the sequence loop end to end, interruption and --resume, config errors, lost frames,
keyframe deblurring quality."""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import signal
import subprocess
import sys
import time

import cv2
import numpy as np
import pytest
import yaml

from mbavo_jax.datasets import open_sequence
from mbavo_jax.deblur import deblur, psnr, ssim
from mbavo_jax.geometry import ExposureTrajectory, Pose
from mbavo_jax.io import read_image_gray, read_tum_trajectory
from mbavo_jax.odometry import OdometryConfig, load_config, run_odometry
from mbavo_jax.tracking import TrackerConfig
from mbavo_jax.errors import ConfigError
from mbavo_jax.synthetic import PRESETS, SynthConfig, generate_sequence

SMALL_SET = ["tracker.levels=3", "tracker.points=[192,128,64]", "tracker.cell=[10,7,5]", "tracker.max_steps=[10,12,20]"]
SMALL = [arg for item in SMALL_SET for arg in ("--set", item)]


def mbavo(*args, **kw):
    return subprocess.run([sys.executable, "-m", "mbavo_jax.cli", *map(str, args)], capture_output=True, text=True, **kw)


def psnr_to_sharp(seq, k, image):
    """PSNR of ``image`` against frame k's generated sharp mid-exposure image, 8-px border left out."""
    ref = read_image_gray(seq[k].path.replace("/rgb/", "/sharp/"))
    m = np.zeros(ref.shape, bool)
    m[8:-8, 8:-8] = True
    return psnr(image, ref, m)


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    out = tmp_path_factory.mktemp("odo") / "strong"
    cfg = SynthConfig(**{**PRESETS["strong"], "frames": 16, "width": 160, "height": 120, "subframes": 32, "seed": 2, "real_textures": False})
    generate_sequence(cfg, out, progress=None)
    return out


def test_track_end_to_end(seq_dir, tmp_path):
    out = tmp_path / "run"
    r = mbavo("track", seq_dir, "--out", out, "--format", "json", "-q", *SMALL)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["frames"] == 16 and summary["dropped"] == 0 and summary["frame_drop_rate"] == 0.0
    assert summary["ate_rmse_m"] < 0.02, summary  # camera moves ~0.5 m; a few mm of drift
    t, p = read_tum_trajectory(out / "trajectory.txt")
    assert len(t) == 16
    for name in ("exposure.txt", "keyframes.txt", "frames.csv", "config.yaml", "trajectory.png", "ape_over_time.png"):
        assert (out / name).is_file(), name
    cfg = (out / "config.yaml").read_text()
    assert "response_gamma: 2.2" in cfg and "levels: 3" in cfg


def test_track_with_depth_term_reads_the_noise_model(seq_dir, tmp_path):
    """`--set tracker.depth_weight=0.01` adds the frame's depth; σ comes from the sequence's camera.yaml."""
    out = tmp_path / "run"
    r = mbavo("track", seq_dir, "--out", out, "--format", "json", "-q", *SMALL, "--set", "tracker.depth_weight=0.01")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["dropped"] == 0 and summary["ate_rmse_m"] < 0.02, summary
    cfg = yaml.safe_load((out / "config.yaml").read_text())["tracker"]
    assert cfg["depth_weight"] == 0.01 and cfg["depth_sigma"] == [0.0005, 0.0]


def test_killed_run_keeps_every_finished_pose_and_resumes(seq_dir, tmp_path):
    out = tmp_path / "killed"
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    proc = subprocess.Popen([sys.executable, "-m", "mbavo_jax.cli", "track", str(seq_dir), "--out", str(out), "-q", *SMALL],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, env=env)
    csv_path = out / "frames.csv"
    deadline = time.time() + 300
    while time.time() < deadline:  # wait until a few frames are done, then kill it hard
        if csv_path.is_file() and len(csv_path.read_text().splitlines()) >= 6:
            break
        time.sleep(0.2)
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    rows = [l.split(",") for l in csv_path.read_text().splitlines()[1:]]
    finished = [r for r in rows if r[2] not in ("lost", "diverged", "too_few_points")]
    t, _ = read_tum_trajectory(out / "trajectory.txt")
    assert len(t) >= len(finished) >= 5  # every finished frame's pose is on disk
    assert len(t) < 16
    r = mbavo("track", seq_dir, "--out", out, "--resume", "--format", "json", "-q", *SMALL)
    assert r.returncode == 0, r.stderr
    t2, _ = read_tum_trajectory(out / "trajectory.txt")
    assert len(t2) == 16 and np.all(np.diff(t2) > 0)
    assert json.loads(r.stdout)["ate_rmse_m"] < 0.03


def test_config_errors():
    with pytest.raises(ConfigError, match="unknown tracker key"):
        load_config(None, ["tracker.nope=3"])
    with pytest.raises(ConfigError, match="section"):
        load_config(None, ["tracker=3"])
    with pytest.raises(ConfigError, match="n_mode"):
        load_config(None, ["tracker.n_mode=sometimes"])
    with pytest.raises(ConfigError, match="tracker.n: expected an integer"):
        load_config(None, ["tracker.n=3.5"])
    with pytest.raises(ConfigError, match="expected a list"):
        load_config(None, ["tracker.points=5"])
    assert load_config(None, ["odometry.keyframe_max_blur_px=1e9"])[1].keyframe_max_blur_px == 1e9  # YAML reads 1e9 as a string
    tc, oc = load_config(pathlib.Path(__file__).parents[1] / "configs" / "default.yaml", ["tracker.n=16"])
    assert tc.n == 16 and oc.keyframe_flow == 0.1


def test_default_config_file_lists_every_key_with_its_default():
    """configs/default.yaml says it holds every key: it must, with the dataclasses' own defaults."""
    import dataclasses

    path = pathlib.Path(__file__).parents[1] / "configs" / "default.yaml"
    data = yaml.safe_load(path.read_text())
    tc, oc = load_config(path)
    for section, cls, loaded in (("tracker", TrackerConfig, tc), ("odometry", OdometryConfig, oc)):
        assert set(data[section]) == {f.name for f in dataclasses.fields(cls)}, section
        assert loaded == cls(), section


def test_bad_config_key_is_one_line_error(seq_dir, tmp_path):
    r = mbavo("track", seq_dir, "--out", tmp_path / "x", "--set", "tracker.bogus=1")
    assert r.returncode == 1 and r.stderr.strip().startswith("mbavo: error:") and "bogus" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1


def test_black_frame_nan_depth_and_jump_are_lost_frames_not_crashes(seq_dir, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(seq_dir, bad)
    rgb = sorted((bad / "rgb").glob("*.png"))
    dep = sorted((bad / "depth").glob("*.png"))
    cv2.imwrite(str(rgb[5]), np.zeros((120, 160), np.uint8))  # black frame
    cv2.imwrite(str(dep[7]), np.zeros((120, 160), np.uint16))  # no depth at all (NaN after loading)
    img = cv2.imread(str(rgb[9]), cv2.IMREAD_GRAYSCALE)
    cv2.imwrite(str(rgb[9]), np.roll(img, 60, axis=1)[::-1])  # a sudden jump to an unrelated view
    seq = open_sequence(bad)
    from mbavo_jax.odometry import load_config

    tc, oc = load_config(None, [*SMALL_SET, "tracker.response_gamma=2.2"])
    summary = run_odometry(seq, tmp_path / "run", tc, oc, progress=None)
    assert summary["frames"] == 16 and 1 <= summary["dropped"] <= 4
    rows = (tmp_path / "run" / "frames.csv").read_text().splitlines()
    assert "too_few_points" in rows[6]  # the black frame (index 5)
    t, _ = read_tum_trajectory(tmp_path / "run" / "trajectory.txt")
    assert len(t) == 16 - summary["dropped"]


def test_deblurring_improves_psnr_and_ssim(seq_dir):
    seq = open_sequence(seq_dir)
    import jax.numpy as jnp

    _, S, E = seq.exposure_paths
    gains = []
    for k in (4, 9):
        f = seq[k]
        traj = ExposureTrajectory(Pose.from_vector(jnp.asarray(S[k], jnp.float32)), Pose.from_vector(jnp.asarray(E[k], jnp.float32)))
        ref = read_image_gray(f.path.replace("/rgb/", "/sharp/"))
        sharp = deblur(f.image, f.depth, seq.camera, traj, n=32, iterations=30, response_gamma=2.2)  # default regularization
        m = np.zeros(ref.shape, bool)
        m[8:-8, 8:-8] = True
        gains.append((psnr(sharp, ref, m) - psnr(f.image, ref, m), ssim(sharp, ref) - ssim(f.image, ref)))
    assert all(g[0] > 1.0 and g[1] > 0.005 for g in gains), gains  # PSNR +1 dB, SSIM better


def test_exposure_blur_px_and_deblur_virtual_frames():
    """A sideways exposure of 0.1 m in front of a wall 2 m away blurs every pixel by fx·0.1/2 px."""
    import jax.numpy as jnp

    from mbavo_jax.deblur import deblur_virtual_frames, exposure_blur_px
    from mbavo_jax.geometry import PinholeCamera

    cam = PinholeCamera(200.0, 200.0, 80.0, 60.0, 160, 120)
    depth = np.full((120, 160), 2.0, np.float32)
    traj = ExposureTrajectory(Pose(jnp.array([0.0, 0, 0, 1]), jnp.array([-0.05, 0, 0])), Pose(jnp.array([0.0, 0, 0, 1]), jnp.array([0.05, 0, 0])))
    mean, p95 = exposure_blur_px(depth, cam, traj)
    assert abs(mean - 10.0) < 1e-3 and abs(p95 - 10.0) < 1e-3
    assert exposure_blur_px(np.full_like(depth, np.nan), cam, traj) == (0.0, 0.0)
    assert [deblur_virtual_frames(b) for b in (0.0, 3.0, 9.0, 16.0, 17.0, 44.0, 300.0)] == [8, 8, 16, 16, 32, 64, 64]
    assert deblur_virtual_frames(300.0, n_max=32) == 32


def test_odometry_benchmark_runs_every_method(tmp_path):
    """`mbavo bench odometry`'s engine on a tiny sequence: every method gives a row, ours are finite."""
    from mbavo_jax.bench import format_odometry_table, run_odometry_benchmark

    cfg = SynthConfig(**{**PRESETS["strong"], "frames": 6, "width": 160, "height": 120, "subframes": 16, "seed": 3, "real_textures": False})
    generate_sequence(cfg, tmp_path / "seq", progress=None)
    small = dict(levels=3, points=(192, 128, 64), cell=(10, 7, 5), max_steps=(10, 12, 20))
    res = run_odometry_benchmark({"strong": tmp_path / "seq"}, tmp_path / "bench", progress=None, tracker_overrides=small)
    row = res["strong"]["methods"]
    assert set(row) == {"ours_n64", "ours_n1", "ours_adaptive", "ours_n64_depth", "ours_n1_depth", "open3d", "open3d_color", "opencv"}
    assert res["strong"]["depth_sigma"] == [0.0005, 0.0]  # read from the generated camera.yaml
    for m in ("ours_n64", "ours_n1", "ours_adaptive", "ours_n64_depth", "ours_n1_depth", "opencv"):
        assert np.isfinite(row[m]["ate_rmse_m"]) and row[m]["frame_drop_rate"] == 0.0, (m, row[m])
    assert row["ours_n64"]["ate_rmse_m"] < 0.02
    table = format_odometry_table(res)
    assert "ours_adaptive" in table and "ours_n64_depth" in table and "opencv" in table and "deblurred keyframes" in table
    assert res["strong"]["depth_weight"] == 0.03
    again = run_odometry_benchmark({"strong": tmp_path / "seq"}, tmp_path / "bench2", progress=None, tracker_overrides=small,
                                   methods=["ours_n1_depth", "opencv"], depth_weight=0.01)
    assert set(again["strong"]["methods"]) == {"ours_n1_depth", "opencv"} and again["strong"]["depth_weight"] == 0.01
    assert "ours_n64 " not in format_odometry_table(again)


def test_odometry_benchmark_rejects_unknown_methods_before_any_work(tmp_path):
    r = mbavo("bench", "odometry", "--methods", "ours_n64,icp", "--out", tmp_path / "b", "--presets", "mild")
    assert r.returncode == 1 and r.stderr.strip() == (
        "mbavo: error: unknown benchmark method(s) icp; choose from "
        "ours_n64, ours_n1, ours_adaptive, ours_n64_depth, ours_n1_depth, open3d, open3d_color, opencv"
    )
    assert not (tmp_path / "b").exists()


def test_missing_depth_mid_run_is_one_line_error_and_keeps_finished_poses(seq_dir, tmp_path):
    bad = tmp_path / "bad"
    shutil.copytree(seq_dir, bad)
    (sorted((bad / "depth").glob("*.png"))[6]).unlink()
    out = tmp_path / "run"
    r = mbavo("track", bad, "--out", out, "-q", *SMALL)
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1
    assert r.stderr.startswith("mbavo: error:") and "depth image not found" in r.stderr
    t, _ = read_tum_trajectory(out / "trajectory.txt")
    assert len(t) == 6  # frames 0-5 were finished before frame 6 failed to load


def test_keyframe_decision_uses_flow_visibility_and_blur():
    from mbavo_jax.odometry import needs_keyframe

    odo = OdometryConfig()  # flow 10 % of the width, blur rule off
    assert not needs_keyframe(50.0, 0.9, 30.0, 640, odo)
    assert needs_keyframe(70.0, 0.9, 30.0, 640, odo)
    assert needs_keyframe(10.0, 0.5, 0.0, 640, odo)  # too few points in view
    held = OdometryConfig(keyframe_max_blur_px=8.0)
    assert needs_keyframe(70.0, 0.9, 5.0, 640, held) and not needs_keyframe(70.0, 0.9, 30.0, 640, held)
    assert needs_keyframe(100.0, 0.9, 30.0, 640, held)  # beyond keyframe_flow_max (15 %): whatever the blur
    assert needs_keyframe(10.0, 0.5, 30.0, 640, held)


def test_fresh_run_clears_keyframe_images_of_an_earlier_run(seq_dir, tmp_path):
    """Keyframe images and triptychs left in --out by an earlier run must not mix into a new one
    (they did: the benchmark's PSNR read stale keyframes); --resume keeps them."""
    out = tmp_path / "run"
    (out / "keyframes").mkdir(parents=True)
    stale = [out / "keyframes" / "99.000000.png", out / "triptych_7.png"]
    for p in stale:
        cv2.imwrite(str(p), np.zeros((4, 4), np.uint8))
    seq = open_sequence(seq_dir)
    tc, oc = load_config(None, SMALL_SET)
    run_odometry(seq, out, tc, oc, max_frames=2, progress=None)
    assert not any(p.exists() for p in stale)
    kf_stamps, _ = read_tum_trajectory(out / "keyframes.txt")
    assert sorted(p.name for p in (out / "keyframes").glob("*.png")) == sorted(f"{t:.6f}.png" for t in kf_stamps)


def test_first_keyframe_is_deblurred_once_the_velocity_is_known(seq_dir, tmp_path):
    """The first frame is blurred too: after frame 1 gives the velocity, keyframe 0 is replaced by its
    deconvolution (sharper against the generated sharp frame); switched off, it stays the input."""
    seq = open_sequence(seq_dir)
    scores = {}
    for on in (True, False):
        tc, oc = load_config(None, [*SMALL_SET, f"odometry.deblur_first_keyframe={str(on).lower()}"])
        out = tmp_path / str(on)
        summary = run_odometry(seq, out, tc, oc, max_frames=3, progress=None)
        assert summary["tracked"] == 3
        t0 = read_tum_trajectory(out / "keyframes.txt")[0][0]
        kf0 = read_image_gray(out / "keyframes" / f"{t0:.6f}.png")
        scores[on] = psnr_to_sharp(seq, 0, kf0)
    blurry = psnr_to_sharp(seq, 0, seq[0].image)
    assert abs(scores[False] - blurry) < 0.1 and scores[True] > blurry + 1.0, (scores, blurry)
    # interrupted after the first frame (its keyframe still the raw input), then --resume: the
    # resumed run deblurs it as the uninterrupted one does
    tc, oc = load_config(None, SMALL_SET)
    out = tmp_path / "resumed"
    run_odometry(seq, out, tc, oc, max_frames=1, progress=None)
    assert run_odometry(seq, out, tc, oc, max_frames=3, resume=True, progress=None)["tracked"] == 2
    kf0 = read_image_gray(out / "keyframes" / f"{seq[0].timestamp:.6f}.png")
    assert abs(psnr_to_sharp(seq, 0, kf0) - scores[True]) < 0.05, (psnr_to_sharp(seq, 0, kf0), scores)


def test_keyframe_made_after_drops_is_deblurred_like_the_first(seq_dir, tmp_path, monkeypatch):
    """Frames 10-12 are reported lost (the real tracker's result with status LOST), so frame 12
    becomes a keyframe at the last good pose without an exposure path; once frame 13 tracks against
    it, it is replaced by its deconvolution, as the first keyframe is. (Deblurred with the generator's
    own path, frame 12 gains 1.0 dB.)"""
    import dataclasses as dc

    import mbavo_jax.odometry as odometry
    from mbavo_jax.tracking import Status

    seq = open_sequence(seq_dir)
    lost = [seq[i].image for i in (10, 11, 12)]
    real_track = odometry.track

    def track(kf, image, init, config, **kw):
        result = real_track(kf, image, init, config, **kw)
        return dc.replace(result, status=Status.LOST) if any(np.array_equal(image, x) for x in lost) else result

    monkeypatch.setattr(odometry, "track", track)
    tc, oc = load_config(None, SMALL_SET)
    summary = run_odometry(seq, tmp_path / "run", tc, oc, max_frames=14, progress=None)
    assert summary["dropped"] == 3
    stamp = seq[12].timestamp
    assert any(abs(t - stamp) < 1e-6 for t in read_tum_trajectory(tmp_path / "run" / "keyframes.txt")[0])
    kf12 = read_image_gray(tmp_path / "run" / "keyframes" / f"{stamp:.6f}.png")
    assert psnr_to_sharp(seq, 12, kf12) > psnr_to_sharp(seq, 12, seq[12].image) + 0.5
    # killed right after the reset (frame 12 still the raw input), then --resume: it continues after
    # frame 12, deblurs it as above and writes the same poses
    out = tmp_path / "resumed"
    run_odometry(seq, out, tc, oc, max_frames=13, progress=None)
    assert run_odometry(seq, out, tc, oc, max_frames=14, resume=True, progress=None)["frames"] == 1
    resumed = read_image_gray(out / "keyframes" / f"{stamp:.6f}.png")
    assert abs(psnr_to_sharp(seq, 12, resumed) - psnr_to_sharp(seq, 12, kf12)) < 0.05
    t_a, p_a = read_tum_trajectory(tmp_path / "run" / "trajectory.txt")
    t_b, p_b = read_tum_trajectory(out / "trajectory.txt")
    assert np.allclose(t_a, t_b) and np.allclose(p_a, p_b, atol=1e-4)
    assert np.allclose(read_tum_trajectory(out / "keyframes.txt")[0], read_tum_trajectory(tmp_path / "run" / "keyframes.txt")[0])
