"""Faults during a run: wherever a run is stopped, --resume goes on exactly as the uninterrupted run
did; an odd frame (part black, NaN, another sequence's) is dropped as implausible, not tracked
metres off.

The kills are in-process: the run is stopped by an exception raised at the chosen point (inside
keyframe deblurring, between two records of a frame, half-way through a row). Every record is
flushed as it is written, so the files are then what a SIGKILL at that point leaves;
tests/test_odometry.py kills a real process (SIGKILL and SIGTERM).
"""

from __future__ import annotations

import dataclasses
import pathlib
import re
import shutil

import cv2
import numpy as np
import pytest

from mbavo_jax.config import SynthConfig, calibration_of, load_config
from mbavo_jax.datasets import open_sequence
from mbavo_jax.errors import ArgumentError
from mbavo_jax.evaluation import evaluate_run
from mbavo_jax.io import TrajectoryWriter, read_exposure_file, read_tum_trajectory
from mbavo_jax.odometry import run_odometry
from mbavo_jax.odometry import rgbd as rgbd_module
from mbavo_jax.odometry.folder import committed_rows
from mbavo_jax.odometry.outputs import RunOutputs
from mbavo_jax.synthetic import PRESETS, generate_sequence

FRAMES = 12
ODD = 7  # the frame an odd-frame sequence spoils


class Killed(BaseException):
    """Stands for the signal: not an Exception, so nothing on the way catches it."""


@dataclasses.dataclass(frozen=True)
class KillPoint:
    """Stop the run at the ``nth`` call of ``owner.name`` (for TrajectoryWriter.write: the nth line of
    ``file``), before or after the call does its work."""

    id: str
    owner: object
    name: str
    nth: int
    after: bool
    file: str = ""


KILL_POINTS = [
    KillPoint("deblurring_the_first_keyframe", rgbd_module, "deblur", 1, after=False),
    KillPoint("deblurring_a_new_keyframe", rgbd_module, "deblur", 2, after=False),
    KillPoint("after_a_deblurred_image_replaced_the_first", RunOutputs, "save_keyframe_image", 2, after=True),
    KillPoint("after_a_new_keyframe_image", RunOutputs, "save_keyframe_image", 3, after=True),
    KillPoint("after_a_trajectory_line", TrajectoryWriter, "write", 5, after=True, file="trajectory.txt"),
    KillPoint("after_an_exposure_line", TrajectoryWriter, "write", 5, after=True, file="exposure.txt"),
    KillPoint("after_a_keyframe_line", TrajectoryWriter, "write", 2, after=True, file="keyframes.txt"),
    KillPoint("after_the_odd_frame", TrajectoryWriter, "write", ODD + 1, after=False, file="trajectory.txt"),
]


def arm(monkeypatch, point: KillPoint) -> None:
    """Make ``point`` raise Killed."""
    original, calls = getattr(point.owner, point.name), [0]

    def wrapper(*args, **kwargs):
        if point.file and pathlib.Path(args[0].path).name != point.file:
            return original(*args, **kwargs)
        calls[0] += 1
        if calls[0] == point.nth and not point.after:
            raise Killed(point.id)
        out = original(*args, **kwargs)
        if calls[0] == point.nth:
            raise Killed(point.id)
        return out

    monkeypatch.setattr(point.owner, point.name, wrapper)


def spoil(kind: str):
    """A frame loader change that spoils frame ODD: top quarter black, top half NaN, or the same
    frame of another sequence."""

    def change(seq, other):
        load = seq.frame_loader

        def loader(i):
            frame = load(i)
            if i != ODD:
                return frame
            image = frame.image.copy()
            if kind == "black":
                image[: image.shape[0] // 4] = 0
            elif kind == "nan":
                image[: image.shape[0] // 2] = np.nan
            else:
                image = other[i].image
            return dataclasses.replace(frame, image=image)

        return dataclasses.replace(seq, frame_loader=loader)

    return change


@pytest.fixture(scope="module")
def sequences(tmp_path_factory):
    """Two 160x120 strong-blur sequences with different scenes (seeds), the first with frame ODD's
    top quarter black on disk."""
    root = tmp_path_factory.mktemp("faults")
    out = {}
    for name, seed in (("main", 4), ("other", 9)):
        cfg = SynthConfig(**{**PRESETS["strong"], "frames": FRAMES, "width": 160, "height": 120, "subframes": 32, "seed": seed,
                             "real_textures": False})
        generate_sequence(cfg, root / name, progress=False)
        out[name] = root / name
    shutil.copytree(out["main"], root / "odd")
    path = sorted((root / "odd" / "rgb").glob("*.png"))[ODD]
    im = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    im[: im.shape[0] // 4] = 0
    cv2.imwrite(str(path), im)
    out["odd"] = root / "odd"
    return out


def config_of(seq):
    return load_config(None, None, calibration_of(seq.meta))


@pytest.fixture(scope="module")
def uninterrupted(sequences, tmp_path_factory):
    """The odd-frame sequence tracked without interruption."""
    seq = open_sequence(sequences["odd"])
    out = tmp_path_factory.mktemp("uninterrupted") / "run"
    run_odometry(seq, out, config_of(seq), progress=False)
    return out


def assert_same_run(a: pathlib.Path, b: pathlib.Path) -> None:
    """Same frames, statuses, keyframes and poses (to 1e-6) in the two run folders."""
    for name in ("trajectory.txt", "keyframes.txt"):
        (ta, pa), (tb, pb) = read_tum_trajectory(a / name), read_tum_trajectory(b / name)
        assert np.array_equal(ta, tb), name
        assert np.abs(pa - pb).max() <= 1e-6, (name, np.abs(pa - pb).max())
    ea, eb = read_exposure_file(a / "exposure.txt"), read_exposure_file(b / "exposure.txt")
    assert all(np.abs(x - y).max() <= 1e-6 for x, y in zip(ea, eb))
    ra, rb = committed_rows(a), committed_rows(b)
    assert [(r["index"], r["status"], r["keyframe"]) for r in ra] == [(r["index"], r["status"], r["keyframe"]) for r in rb]


@pytest.mark.slow
@pytest.mark.parametrize("point", [pytest.param(p, id=p.id) for p in KILL_POINTS])
def test_resumed_run_equals_the_uninterrupted_one_wherever_it_was_killed(point, sequences, uninterrupted, tmp_path, monkeypatch):
    seq = open_sequence(sequences["odd"])
    out = tmp_path / "run"
    with monkeypatch.context() as m:
        arm(m, point)
        with pytest.raises(Killed):
            run_odometry(seq, out, config_of(seq), progress=False)
    rows = committed_rows(out)
    assert 0 < len(rows) < FRAMES, f"the kill point {point.id} was not reached"
    run_odometry(seq, out, config_of(seq), resume=True, progress=False)
    assert_same_run(uninterrupted, out)


@pytest.mark.slow
def test_resume_checks_the_settings_and_records_an_override(sequences, tmp_path):
    """--resume with other settings is refused; --resume-anyway goes on and says so in run.yaml (a
    segment per call) and config.resumed_at_<frame>.yaml, while config.yaml keeps the first settings."""
    import yaml

    from mbavo_jax.errors import MbavoError

    seq = open_sequence(sequences["main"])
    out, first = tmp_path / "run", config_of(seq)
    other = first.replace(tracker=dict(huber=0.05))
    run_odometry(seq, out, first, max_frames=4, progress=False)
    with pytest.raises(MbavoError, match="other settings than the run's \\(tracker.huber"):
        run_odometry(seq, out, other, resume=True, max_frames=6, progress=False)
    assert len(committed_rows(out)) == 4  # the refusal changed nothing
    run_odometry(seq, out, other, resume=True, resume_anyway=True, max_frames=6, progress=False)
    record = yaml.safe_load((out / "run.yaml").read_text())
    assert [(s["first_frame"], s["resume_anyway"]) for s in record["segments"]] == [(0, False), (4, True)]
    assert record["segments"][1]["settings"]["tracker"]["huber"] == 0.05
    assert load_config(out / "config.yaml") == first and load_config(out / "config.resumed_at_4.yaml") == other
    assert len(committed_rows(out)) == 6


def without(seq, k: int):
    """``seq`` with frame k left out (what a run that drops it at best sees)."""
    keep = [i for i in range(len(seq)) if i != k]
    return dataclasses.replace(seq, timestamps=seq.timestamps[keep], frame_loader=lambda i: seq.frame_loader(keep[i]))


@pytest.mark.slow
def test_odd_frames_are_dropped_as_implausible_not_tracked_metres_off(sequences, uninterrupted, tmp_path):
    """A frame with its top quarter black (on disk), its top half NaN, or from another sequence:
    dropped as implausible (never a keyframe), and the ATE within 2x the clean run's and within 2x
    that of the clean sequence without that frame (what dropping it costs at best)."""
    clean_seq, other = open_sequence(sequences["main"]), open_sequence(sequences["other"])
    ate = lambda out: evaluate_run(out, clean_seq.groundtruth)["ate_rmse_m"]
    for name, seq in (("clean", clean_seq), ("clean_without", without(clean_seq, ODD))):
        assert run_odometry(seq, tmp_path / name, config_of(clean_seq), progress=False)["dropped"] == 0, name
    reference = ate(tmp_path / "clean_without")
    runs = {"black": uninterrupted}
    for kind in ("nan", "foreign"):
        run_odometry(spoil(kind)(clean_seq, other), tmp_path / kind, config_of(clean_seq), progress=False)
        runs[kind] = tmp_path / kind
    for kind, out in runs.items():
        rows = committed_rows(out)
        assert rows[ODD]["status"] == "implausible" and rows[ODD]["keyframe"] == "0" and rows[ODD]["note"], (kind, rows[ODD])
        assert sum(r["status"] == "implausible" for r in rows) == 1, (kind, [r["status"] for r in rows])
        print(f"{kind}: ATE {ate(out):.4f} m; clean without frame {ODD} {reference:.4f} m, whole clean {ate(tmp_path / 'clean'):.4f} m")
        assert ate(out) <= 2 * reference and ate(out) <= 2 * ate(tmp_path / "clean"), (kind, ate(out), reference)


def test_track_without_an_image_is_one_clear_error():
    from mbavo_jax.geometry import PinholeCamera
    from mbavo_jax.tracking import Keyframe, track

    cam = PinholeCamera.create(40.0, 40.0, 31.5, 23.5, 64, 48)
    kf = Keyframe.create(np.random.default_rng(0).random((48, 64), np.float32), np.full((48, 64), 2.0, np.float32), cam)
    for frame, text in ((None, "got None"), (np.zeros(64, np.float32), "got shape (64,)"), (np.zeros((40, 64), np.float32), "frame is 64x40")):
        with pytest.raises(ArgumentError, match=re.escape(text)):
            track(kf, frame)


def test_reconcile_cuts_a_folder_back_to_its_last_complete_row(tmp_path):
    """A kill in the middle of writing: a row cut short, a trajectory line of the uncommitted frame,
    a half-written exposure line. reconcile keeps the committed frames only, in every file."""
    from mbavo_jax.odometry.folder import reconcile
    from mbavo_jax.odometry.outputs import CSV_COLUMNS

    pose = "0 0 0 0 0 0 1"
    row = lambda i, t: ",".join([str(i), t, "converged", "0.01"] + [""] * (len(CSV_COLUMNS) - 4)) + "\r\n"
    (tmp_path / "frames.csv").write_bytes((",".join(CSV_COLUMNS) + "\r\n" + row(0, "1.000000") + row(1, "1.033333")
                                           + row(2, "1.066667")[:9]).encode())
    (tmp_path / "trajectory.txt").write_text(f"# h\n1.000000 {pose}\n1.033333 {pose}\n1.066667 {pose}\n")
    (tmp_path / "exposure.txt").write_text(f"# h\n1.000000 {pose} {pose}\n1.033333 {pose} {pose}\n1.066667 0 0")
    (tmp_path / "keyframes.txt").write_text(f"# h\n1.000000 {pose}\n1.066667 {pose}\n")
    rows = reconcile(tmp_path)
    assert [r["index"] for r in rows] == ["0", "1"] and [r["index"] for r in committed_rows(tmp_path)] == ["0", "1"]
    assert (tmp_path / "frames.csv").read_bytes().endswith(row(1, "1.033333").encode())
    assert list(read_tum_trajectory(tmp_path / "trajectory.txt")[0]) == [1.0, 1.033333]
    assert list(read_exposure_file(tmp_path / "exposure.txt")[0]) == [1.0, 1.033333]
    assert list(read_tum_trajectory(tmp_path / "keyframes.txt")[0]) == [1.0]
    assert reconcile(tmp_path) == rows  # nothing more to cut
