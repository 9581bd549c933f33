"""--resume of a monocular run: wherever the run was stopped (initialising, inside a bundle
adjustment, between a frame's records, between a row and its checkpoint, with a checkpoint every
few frames), the resumed run equals the uninterrupted one, points.ply included; without a
checkpoint, one clear line; stopped inside the exposure probe, nothing written. The kills are
in-process, as in tests/test_resume.py."""

from __future__ import annotations

import numpy as np
import pytest

from mbavo_jax.config import RunConfig
from mbavo_jax.datasets import open_sequence
from mbavo_jax.errors import DataError
from mbavo_jax.io import TrajectoryWriter, read_ply
from mbavo_jax.odometry import mono as mono_module
from mbavo_jax.odometry import run as run_module
from mbavo_jax.odometry import run_odometry
from mbavo_jax.odometry.folder import committed_rows
from mbavo_jax.odometry.mono import MonoPipeline
from mbavo_jax.odometry.outputs import RunOutputs
from mbavo_jax.synthetic import PRESETS, SynthConfig, generate_sequence
from tests.test_resume import KillPoint, Killed, arm, assert_same_run

FRAMES = 28
# The kill points count calls of the main loop, which the exposure probe before it (the same steps,
# nothing written) would shift; the probe's own stop is test_a_stop_inside_the_exposure_probe_writes_nothing.
MONO = RunConfig().replace(odometry=dict(mode="mono"), mono=dict(exposure_probe=0))

KILL_POINTS = [
    KillPoint("while_initialising", MonoPipeline, "step", 5, after=False),
    KillPoint("inside_a_bundle_adjustment", mono_module, "bundle_adjust", 3, after=False),
    KillPoint("after_points_left_the_window", RunOutputs, "write_points", 1, after=True),
    KillPoint("after_a_keyframe_line", TrajectoryWriter, "write", 4, after=True, file="keyframes.txt"),
    KillPoint("between_a_row_and_its_checkpoint", run_module, "write_checkpoint", 20, after=False),
]


@pytest.fixture(scope="module")
def seq_dir(tmp_path_factory):
    """A blurred 320x240 sequence (strong preset) without exposure metadata; its depth is not read."""
    out = tmp_path_factory.mktemp("mono_resume") / "strong"
    cfg = SynthConfig(**{**PRESETS["strong"], "frames": FRAMES, "width": 320, "height": 240, "subframes": 32, "seed": 1,
                         "real_textures": False, "exposure_info": False})
    generate_sequence(cfg, out, progress=False)
    return out


@pytest.fixture(scope="module")
def uninterrupted(seq_dir, tmp_path_factory):
    out = tmp_path_factory.mktemp("mono_uninterrupted") / "run"
    summary = run_odometry(open_sequence(seq_dir), out, MONO, progress=False)
    assert summary["mode"] == "mono" and summary["tracked"] >= FRAMES // 2, summary
    assert len(read_ply(out / "points.ply")[0]) > 0
    return out


def assert_same_points(a, b) -> None:
    (xa, ia), (xb, ib) = read_ply(a / "points.ply"), read_ply(b / "points.ply")
    assert xa.shape == xb.shape and np.array_equal(xa, xb) and np.array_equal(ia, ib)


@pytest.mark.slow
@pytest.mark.parametrize("point", [pytest.param(p, id=p.id) for p in KILL_POINTS])
def test_resumed_mono_run_equals_the_uninterrupted_one(point, seq_dir, uninterrupted, tmp_path, monkeypatch):
    seq, out = open_sequence(seq_dir), tmp_path / "run"
    with monkeypatch.context() as m:
        arm(m, point)
        with pytest.raises(Killed):
            run_odometry(seq, out, MONO, progress=False)
    assert 0 < len(committed_rows(out)) < FRAMES, f"the kill point {point.id} was not reached"
    run_odometry(seq, out, MONO, resume=True, progress=False)
    assert_same_run(uninterrupted, out)
    assert_same_points(uninterrupted, out)


@pytest.mark.slow
def test_sparse_checkpoints_track_the_frames_after_the_last_one_again(seq_dir, uninterrupted, tmp_path, monkeypatch):
    """A checkpoint every 4th frame, the run stopped before frame 18: the resume cuts the run back
    to frame 15 (its last checkpoint) and tracks 16 and 17 again, with the same result."""
    seq, out = open_sequence(seq_dir), tmp_path / "run"
    sparse = MONO.replace(runtime=dict(checkpoint_every=4))
    with monkeypatch.context() as m:
        arm(m, KillPoint("before_frame_18", MonoPipeline, "step", 19, after=False))
        with pytest.raises(Killed):
            run_odometry(seq, out, sparse, progress=False)
    assert len(committed_rows(out)) == 18
    summary = run_odometry(seq, out, sparse, resume=True, progress=False)
    assert summary["frames"] == FRAMES - 16  # from frame 16 on
    assert_same_run(uninterrupted, out)
    assert_same_points(uninterrupted, out)


def test_a_stop_inside_the_exposure_probe_writes_nothing(seq_dir, tmp_path, monkeypatch):
    """The probe (the loop run once beforehand, blind to blur) records nothing: a run stopped inside
    it leaves no row, pose or checkpoint behind, so ``--resume`` starts afresh."""
    out = tmp_path / "run"
    with monkeypatch.context() as m:
        arm(m, KillPoint("inside_the_probe", MonoPipeline, "step", 3, after=False))
        with pytest.raises(Killed):
            run_odometry(open_sequence(seq_dir), out, RunConfig().replace(odometry=dict(mode="mono")), progress=False)
    assert committed_rows(out) == [] and not (out / "trajectory.txt").exists() and not (out / "checkpoint.npz").exists()


@pytest.mark.slow
def test_resume_without_a_checkpoint_is_one_clear_line(seq_dir, tmp_path, mbavo):
    """Also when the run first releases the process's compiled programs (``runtime.release_programs_at``
    tiny): its note is printed only once the input has passed the checks."""
    out = tmp_path / "run"
    settings = ("--set", "runtime.checkpoint_every=0", "--set", "runtime.release_programs_at=1e-9")
    r = mbavo("track", seq_dir, "--out", out, "--mode", "mono", "--max-frames", "3", "-q", *settings)
    assert r.returncode == 0, r.stderr
    r = mbavo("track", seq_dir, "--out", out, "--mode", "mono", "--resume", *settings)
    assert r.returncode == 1 and "checkpoint.npz" in r.stderr and "cannot --resume" in r.stderr, r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    assert len(committed_rows(out)) == 3  # the refusal changed nothing


def test_checkpoint_of_another_kind_is_refused(seq_dir, tmp_path):
    out = tmp_path / "run"
    run_odometry(open_sequence(seq_dir), out, MONO, progress=False, max_frames=3)
    (out / "checkpoint.npz").write_bytes(b"not a pickle")
    with pytest.raises(DataError, match="unreadable"):
        run_odometry(open_sequence(seq_dir), out, MONO, resume=True, progress=False)
