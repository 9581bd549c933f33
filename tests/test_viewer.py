"""The rerun view of a run: ``mbavo track --rrd`` and ``mbavo view --rrd`` write recordings that
rerun's own reader loads back with the expected entities and one row per frame; the reblurred
synthesis matches the input; without rerun-sdk, ``--viewer`` is a one-line error before any run.
No viewer window is opened (recordings go to files)."""

from __future__ import annotations

import collections
import os
import re
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import run_cli

FRAMES = 6
PER_FRAME = ["/series/status", "/series/drops", "/series/seconds", "/log", "/images/blurry"]
TRACKED = ["/world/camera/start", "/world/camera/start/frustum", "/world/camera/end", "/world/camera/end/frustum",
           "/world/trajectory"]
FITTED = ["/series/rms", "/series/blur_px", "/series/n", "/images/reblurred", "/images/residual"]


def rrd_rows(path) -> dict[str, int]:
    """Rows per entity path of a recording, as ``rerun rrd print`` (rerun's own reader) lists its
    chunks, after ``rerun rrd verify`` accepted the file."""
    env = {**os.environ, "RERUN_ANALYTICS": "0"}
    rerun = [sys.executable, "-m", "rerun", "rrd"]
    verify = subprocess.run([*rerun, "verify", str(path)], capture_output=True, text=True, env=env, timeout=120)
    assert verify.returncode == 0, verify.stderr[-2000:]
    printed = subprocess.run([*rerun, "print", str(path)], capture_output=True, text=True, env=env, timeout=120)
    assert printed.returncode == 0, printed.stderr[-2000:]
    rows = collections.Counter()
    for m in re.finditer(r"^Chunk\(\S+\) with (\d+) rows \([^)]*\) - (/\S+) - ", printed.stdout, re.M):
        rows[m[2]] += int(m[1])
    return dict(rows)


def data_rows(path) -> int:
    return sum(1 for line in path.read_text().splitlines() if line.strip() and not line.startswith("#"))


@pytest.fixture(scope="module")
def tracked(tmp_path_factory):
    """A short generated sequence tracked with ``--rrd``: (sequence, run folder, recording)."""
    root = tmp_path_factory.mktemp("viewer")
    seq, run = root / "seq", root / "run"
    assert run_cli("synth", "--preset", "strong", "--frames", FRAMES, "--width", 160, "--height", 120, "--out", seq, "-q") == 0
    assert run_cli("track", seq, "--out", run, "--rrd", root / "live.rrd", "-q") == 0
    return seq, run, root / "live.rrd"


def check_recording(rows: dict[str, int], run) -> None:
    """The entities a run's recording must have, with one row per frame (tracked, fitted) and per keyframe."""
    tracked, keyframes = data_rows(run / "trajectory.txt"), data_rows(run / "keyframes.txt")
    assert tracked >= 3 and keyframes >= 1
    for entity in PER_FRAME:
        assert rows.get(entity) == FRAMES, (entity, rows.get(entity))
    for entity in TRACKED:
        assert rows.get(entity) == tracked, (entity, rows.get(entity))
    for entity in FITTED:  # every frame but the first has a tracking result
        assert rows.get(entity, 0) >= tracked - 1, (entity, rows.get(entity))
    assert rows.get("/world/groundtruth") == 1  # static, once
    for j in range(keyframes):
        for part in ("", "/frustum", "/points"):
            assert rows.get(f"/world/keyframes/{j}{part}", 0) >= 1, (j, part)
    assert f"/world/keyframes/{keyframes}" not in rows
    assert rows.get("/images/keyframe", 0) >= keyframes


@pytest.mark.slow
def test_track_rrd_records_every_frame(tracked):
    _, run, rrd = tracked
    check_recording(rrd_rows(rrd), run)


@pytest.mark.slow
def test_view_rebuilds_the_recording_from_the_run_folder(tracked, tmp_path, mbavo):
    _, run, live = tracked
    r = mbavo("view", run, "--rrd", tmp_path / "view.rrd", "-q")
    assert r.returncode == 0, r.stderr
    assert f"wrote {FRAMES} frames" in r.stdout
    rows = rrd_rows(tmp_path / "view.rrd")
    check_recording(rows, run)
    assert set(rows) == set(rrd_rows(live))  # the same entities as the live recording


@pytest.mark.slow
def test_reblurred_synthesis_matches_the_input(tracked):
    from mbavo_jax.datasets import open_sequence
    from mbavo_jax.viewer import FolderRun, at_level, reblurred, view_level

    seq, run, _ = tracked
    seq = open_sequence(seq)
    level, checked = view_level(seq.camera.width), 0
    for f in FolderRun(run, seq, 1.0).frames():
        synth = reblurred(f, seq.camera, 1.0, level)
        if f.reference is None:
            assert synth is None
            continue
        image, ok = synth
        blurry, sharp = at_level(f.image, level), at_level(f.reference.image, level)
        assert ok.mean() > 0.5
        # the model explains the input far better than the keyframe image itself does
        assert np.abs(blurry - image)[ok].mean() < 0.2 * np.abs(blurry - sharp)[ok].mean()
        checked += 1
    assert checked >= 3


def test_view_needs_a_run_folder(tmp_path, mbavo):
    r = mbavo("view", tmp_path, "--rrd", tmp_path / "x.rrd")
    assert r.returncode == 1 and r.stderr.strip() == f"mbavo: error: {tmp_path / 'frames.csv'}: missing: not a run folder (mbavo track SEQ --out DIR makes one)"


def test_without_rerun_the_viewer_is_a_one_line_error(tmp_path, mbavo, monkeypatch):
    monkeypatch.setitem(sys.modules, "rerun", None)  # import rerun raises ImportError
    line = 'mbavo: error: the viewer needs rerun-sdk: pip install -e ".[viewer]"'
    for args in (("track", tmp_path / "seq", "--out", tmp_path / "run", "--viewer"),
                 ("track", tmp_path / "seq", "--out", tmp_path / "run", "--rrd", tmp_path / "x.rrd"),
                 ("demo", "--out", tmp_path / "demo", "--viewer"),
                 ("view", tmp_path, "--rrd", tmp_path / "x.rrd")):
        (tmp_path / "frames.csv").write_text("index\n")
        r = mbavo(*args)
        assert r.returncode == 1 and r.stderr.strip() == line, (args, r.stderr)
    assert not (tmp_path / "run").exists() and not (tmp_path / "demo").exists()  # checked before the run starts


def test_a_viewer_window_without_a_display_is_a_one_line_error(tmp_path, mbavo, monkeypatch):
    monkeypatch.setattr(sys, "platform", "linux")
    for name in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET"):
        monkeypatch.delenv(name, raising=False)
    r = mbavo("track", tmp_path / "seq", "--out", tmp_path / "run", "--viewer")
    assert r.returncode == 1 and r.stderr.startswith("mbavo: error: the rerun viewer needs a display") and r.stderr.count("\n") == 1
    assert not (tmp_path / "run").exists()
