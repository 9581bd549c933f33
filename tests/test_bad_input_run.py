"""The second round of bad input to a run (issue 55): ``--rrd`` places checked before any work, JAX's
environment variables (``JAX_PLATFORMS``, ``XLA_FLAGS``) as one line, monocular runs scored after
Sim(3) and saying so, and a monocular run that poses no frame as one line with the initialiser's
last note (its folder kept)."""

from __future__ import annotations

import csv
import json
import os
import pathlib
import subprocess
import sys

import cv2
import numpy as np
import pytest

from mbavo_jax.evaluation import ape, evaluate_run
from mbavo_jax.evaluation import plots as plots_module
from mbavo_jax.io import read_tum_trajectory
from tests.conftest import make_tum

REPO = pathlib.Path(__file__).resolve().parents[1]


def one_line(r, *needles: str) -> None:
    """Exit status 1, one ``mbavo: error:`` line holding every needle, nothing on stdout."""
    lines = r.stderr.strip().splitlines()
    assert r.returncode == 1 and len(lines) == 1 and lines[0].startswith("mbavo: error: "), (r.returncode, r.stderr[-2000:])
    assert all(n in lines[0] for n in needles), (needles, lines[0])
    assert r.stdout == "", r.stdout


# ------------------------------------------------------------------------------------------ --rrd


def bad_rrd_places(tmp_path: pathlib.Path) -> dict[str, tuple[str, str]]:
    """--rrd value -> what its line must say: an existing folder, a place under a file, an empty
    name, and (as root too) a place no file can be made."""
    (tmp_path / "adir").mkdir()
    return {"folder": (str(tmp_path / "adir"), "is a folder"), "under_a_file": ("/dev/null/x.rrd", "/dev/null is not a folder"),
            "empty": ("", "--rrd is empty"), "proc": ("/proc/x.rrd", "cannot be written")}


@pytest.mark.parametrize("place", ["folder", "under_a_file", "empty", "proc"])
def test_track_rrd_place_is_checked_before_any_work(place, tmp_path, mbavo):
    seq = make_tum(tmp_path / "seq")
    rrd, says = bad_rrd_places(tmp_path)[place]
    r = mbavo("track", seq, "--out", tmp_path / "run", "--rrd", rrd, "-q")
    one_line(r, "--rrd", says)
    assert not (tmp_path / "run").exists()  # nothing ran


@pytest.mark.parametrize("place", ["folder", "under_a_file"])
def test_demo_and_view_rrd_place_is_checked_first(place, tmp_path, mbavo):
    rrd, says = bad_rrd_places(tmp_path)[place]
    r = mbavo("demo", "--out", tmp_path / "demo", "--frames", "3", "--rrd", rrd, "-q")
    one_line(r, "--rrd", says)
    assert not (tmp_path / "demo").exists()
    seq, run = make_tum(tmp_path / "seq"), tmp_path / "run"
    run.mkdir()
    (run / "frames.csv").write_text("index,timestamp,status,note\n")
    r = mbavo("view", run, "--sequence", seq, "--rrd", rrd, "-q")
    one_line(r, "--rrd", says)


# ------------------------------------------------------------------------ JAX_PLATFORMS, XLA_FLAGS


def mbavo_process(env: dict[str, str], *args) -> subprocess.CompletedProcess:
    """``python -m mbavo_jax.cli ARGS`` in a fresh interpreter with ``env`` added to this one's."""
    full = {**{k: v for k, v in os.environ.items() if k not in ("JAX_PLATFORMS", "XLA_FLAGS")}, **env}
    return subprocess.run([sys.executable, "-m", "mbavo_jax.cli", *map(str, args)], env=full, cwd=REPO, capture_output=True,
                          text=True, timeout=300)


@pytest.fixture(scope="module")
def trajectories(tmp_path_factory) -> tuple[pathlib.Path, pathlib.Path]:
    """(reference, estimate) TUM files of 5 poses for ``mbavo eval ape``."""
    root = tmp_path_factory.mktemp("traj")
    lines = "".join(f"{t:.6f} {0.1 * t:.4f} {0.05 * t * t:.4f} {0.02 * t ** 3:.4f} 0 0 0 1\n" for t in range(5))
    (root / "ref.txt").write_text(lines)
    (root / "est.txt").write_text(lines)
    return root / "ref.txt", root / "est.txt"


@pytest.mark.parametrize("command", ["eval", *(pytest.param(c, marks=pytest.mark.slow) for c in ("jacobians", "track", "info", "sweep"))])
def test_jax_platforms_without_that_backend_is_one_line(command, trajectories, tmp_path):
    """'tpu': a backend JAX knows, absent on CPU and GPU machines alike. A sweep (its runs use JAX
    in its workers) is refused as well, before any run."""
    seq = make_tum(tmp_path / "seq")
    (tmp_path / "sweep.yaml").write_text(f"sequences:\n  - {{path: {seq}, name: tum}}\nconfigurations:\n  ours: {{}}\n")
    args = {"jacobians": ("jacobians",), "eval": ("eval", "ape", *trajectories), "info": ("info", seq),
            "track": ("track", seq, "--out", tmp_path / "run", "-q"),
            "sweep": ("sweep", tmp_path / "sweep.yaml", "--out", tmp_path / "run", "-q", "--jobs", "1")}[command]
    r = mbavo_process({"JAX_PLATFORMS": "tpu"}, *args)
    one_line(r, "JAX_PLATFORMS=tpu", "no such backend here", "available: ", "cpu")
    assert not (tmp_path / "run").exists()


def test_xla_flags_xla_does_not_know_is_one_line_naming_the_variable(trajectories):
    r = mbavo_process({"XLA_FLAGS": "--garbage"}, "eval", "ape", *trajectories)
    one_line(r, "XLA_FLAGS", "--garbage")


@pytest.mark.slow
def test_xla_flags_value_xla_cannot_read_is_one_line_and_good_flags_run(trajectories):
    r = mbavo_process({"XLA_FLAGS": "--xla_force_host_platform_device_count=abc"}, "eval", "ape", *trajectories)
    one_line(r, "XLA_FLAGS", "xla_force_host_platform_device_count")
    r = mbavo_process({"XLA_FLAGS": "--xla_cpu_multi_thread_eigen=false"}, "eval", "ape", *trajectories)  # a flag XLA knows
    assert r.returncode == 0 and "rmse" in r.stdout, r.stderr


# ------------------------------------------------------------------- monocular runs: Sim(3), said so


def write_run(run: pathlib.Path, stamps, poses, statuses) -> None:
    """A run folder as the loop leaves it (frames.csv rows, trajectory.txt of the posed frames)."""
    run.mkdir(parents=True)
    with open(run / "frames.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["index", "timestamp", "status", "note"])
        for i, (t, s) in enumerate(zip(stamps, statuses)):
            w.writerow([i, f"{t:.6f}", s, ""])
    posed = [k for k, s in enumerate(statuses) if s != "initialising"]
    (run / "trajectory.txt").write_text("# timestamp tx ty tz qx qy qz qw\n" + "".join(
        f"{stamps[k]:.6f} " + " ".join(f"{v:.9f}" for v in poses[k]) + "\n" for k in posed))


def truth(n: int = 12):
    """(stamps, poses (n, 7)): a curved walk with a turn, camera-to-world [t, q]."""
    t = 1.0 + np.arange(n) / 30
    a = np.linspace(0, 0.4, n)
    xyz = np.stack([0.5 * np.sin(a), 0.05 * a, 0.5 * (1 - np.cos(a)) + 0.2 * a], 1)
    q = np.stack([np.zeros(n), np.sin(a / 2), np.zeros(n), np.cos(a / 2)], 1)
    return t, np.concatenate([xyz, q], 1)


def test_monocular_run_is_scored_and_plotted_after_sim3(tmp_path, monkeypatch):
    """A scale-free trajectory (the truth at 0.3x, moved): ATE 0 after Sim(3), as the result and the
    plot titles say; the same folder as an RGB-D run is scored with evaluation.align (SE(3))."""
    t, p = truth()
    est = p.copy()
    est[:, :3] = 0.3 * p[:, :3] + [1.0, -2.0, 0.5]
    titles = []
    monkeypatch.setattr(plots_module, "plot_trajectories", lambda path, ref, e, title="", **k: titles.append(title))
    monkeypatch.setattr(plots_module, "plot_error_over_time", lambda path, s, err, title="", *a, **k: titles.append(title))
    write_run(tmp_path / "mono", t, est, ["initialising"] * 3 + ["converged"] * 9)
    res = evaluate_run(tmp_path / "mono", (t, p), t, plots=True)
    assert res["ate_alignment"] == "sim3" and res["ate_rmse_m"] < 1e-6 and res["ate_scale"] == pytest.approx(1 / 0.3, rel=1e-5), res
    assert all("Sim(3)" in title for title in titles) and len(titles) == 2, titles
    write_run(tmp_path / "rgbd", t, est, ["keyframe"] + ["converged"] * 11)
    rgbd = evaluate_run(tmp_path / "rgbd", (t, p), t)
    assert rgbd["ate_alignment"] == "se3" and rgbd["ate_rmse_m"] > 0.01, rgbd
    told = evaluate_run(tmp_path / "rgbd", (t, p), t, monocular=True)  # the caller knows best
    assert told["ate_alignment"] == "sim3" and told["ate_rmse_m"] < 1e-6


@pytest.mark.slow
def test_monocular_track_prints_its_sim3_ate(tmp_path, mbavo):
    """``mbavo track`` of a sequence without depth: the printed ATE is the Sim(3) one, with its
    alignment named; SE(3) would score the missing scale."""
    from mbavo_jax.synthetic import PRESETS, SynthConfig, generate_sequence

    seq = tmp_path / "seq"
    cfg = SynthConfig(**{**PRESETS["mild"], "frames": 12, "width": 160, "height": 120, "subframes": 8, "seed": 1, "real_textures": False})
    generate_sequence(cfg, seq, progress=False)
    (seq / "depth.txt").unlink()  # a monocular sequence
    r = mbavo("track", seq, "--out", tmp_path / "run", "-q", "--format", "json", "--set", "mono.init_min_parallax_deg=0.2")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["mode"] == "mono" and summary["ate_alignment"] == "sim3", summary
    t_gt, p_gt = read_tum_trajectory(seq / "groundtruth.txt")
    t_est, p_est = read_tum_trajectory(tmp_path / "run" / "trajectory.txt")
    sim3, se3 = (ape(t_gt, p_gt, t_est, p_est, align=a, max_diff=0.02)["rmse"] for a in ("sim3", "se3"))
    assert summary["ate_rmse_m"] == pytest.approx(sim3, rel=1e-9) and sim3 < 0.5 * se3, (sim3, se3)


# --------------------------------------------------------------------- monocular runs without a pose


def image_folder(root: pathlib.Path, n: int, shift_px: float = 0.0) -> pathlib.Path:
    """A plain image folder (camera.yaml + frameK.png) of a smooth random texture, each frame moved
    ``shift_px`` sideways from the one before (0: a static camera)."""
    root.mkdir(parents=True)
    rng = np.random.default_rng(0)
    texture = cv2.GaussianBlur(rng.random((200, 260)).astype(np.float32), (0, 0), 2.0)
    texture = (texture - texture.min()) / np.ptp(texture)
    for k in range(n):
        M = np.float32([[1, 0, -20 - k * shift_px], [0, 1, -20]])
        frame = cv2.warpAffine(texture, M, (160, 120), flags=cv2.INTER_LINEAR)
        cv2.imwrite(str(root / f"frame{k}.png"), np.clip(frame * 255, 0, 255).astype(np.uint8))
    (root / "camera.yaml").write_text("fx: 130\nfy: 130\ncx: 79.5\ncy: 59.5\nwidth: 160\nheight: 120\n")
    return root


@pytest.mark.parametrize("frames, shift", [(3, 0.5), (6, 0.0)], ids=["three_frames", "static_camera"])
def test_monocular_run_without_a_pose_is_one_line_with_the_last_note(frames, shift, tmp_path, mbavo):
    seq = image_folder(tmp_path / "seq", frames, shift)
    run = tmp_path / "run"
    r = mbavo("track", seq, "--out", run, "-q")
    with open(run / "frames.csv", newline="") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == frames and rows[-1]["note"], rows  # the folder keeps its files
    one_line(r, "no frame posed", f"frame {frames - 1}: {rows[-1]['note']}", str(run))
    assert (run / "run.yaml").is_file() and (run / "trajectory.txt").is_file()


def test_monocular_run_stopped_by_max_frames_before_a_pose_is_not_an_error(tmp_path, mbavo):
    """--max-frames stops the run on purpose (--resume continues it)."""
    seq = image_folder(tmp_path / "seq", 4, 0.0)
    r = mbavo("track", seq, "--out", tmp_path / "run", "-q", "--max-frames", "2", "--format", "json")
    assert r.returncode == 0 and json.loads(r.stdout)["tracked"] == 0, r.stderr
    r = mbavo("track", seq, "--out", tmp_path / "run", "-q", "--resume")  # to the end, still nothing posed
    one_line(r, "no frame posed", "frame 3: ")
