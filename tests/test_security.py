"""Run folders and sweep files from someone else: sweep names never reach outside --out, settings are
taken as written (no interpolation: no environment variable reaches a message or a run's files), one
writer per run folder, sweep workers end with their sweep, Ray Client without its package, and
sweeps that run nothing or whose every run failed. Processes are killed only by their pid."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time

import cv2
import numpy as np
import psutil
import pytest
import yaml

from mbavo_jax.config import load_config
from mbavo_jax.errors import ConfigError
from mbavo_jax.sweep import parse_sweep

from .conftest import BLOCK_AT_FRAME, REPO

SMALL_SET = ["tracker.levels=3", "tracker.points=[192,128,64]", "tracker.cell=[10,7,5]", "tracker.max_steps=[10,12,20]"]
SMALL = [arg for item in SMALL_SET for arg in ("--set", item)]
SECRET = "s3cret-home-4711"  # HOME's value in the interpolation tests: it must appear nowhere


def tiny_tum(root, n: int = 3, w: int = 160, h: int = 120):
    """A TUM layout of ``n`` smooth random frames at ``w`` x ``h`` with a flat depth of 1.5 m."""
    rng = np.random.default_rng(1)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    with open(root / "rgb.txt", "w") as f, open(root / "depth.txt", "w") as g:
        for k in range(n):
            t = 10.0 + k / 30
            image = cv2.GaussianBlur(rng.integers(0, 255, (h, w), dtype=np.uint8), (0, 0), 1.5)
            cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), image)
            cv2.imwrite(str(root / "depth" / f"{t:.6f}.png"), np.full((h, w), 7500, np.uint16))
            f.write(f"{t:.6f} rgb/{t:.6f}.png\n")
            g.write(f"{t:.6f} depth/{t:.6f}.png\n")
    (root / "camera.yaml").write_text(f"fx: 150\nfy: 150\ncx: {(w - 1) / 2}\ncy: {(h - 1) / 2}\nwidth: {w}\nheight: {h}\n")
    return root


def write_sweep(path, spec: dict):
    path.write_text(yaml.safe_dump(spec))
    return path


def one_line_error(r, *parts) -> str:
    assert r.returncode == 1, (r.returncode, r.stdout, r.stderr)
    lines = r.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("mbavo: error: "), r.stderr
    for part in parts:
        assert part in lines[0], (part, lines[0])
    return lines[0]


def listing(root) -> set:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


# ------------------------------------------------------------------ 2. names never leave --out


@pytest.mark.parametrize("name", [".", "..", ".hidden", "...", "ok\n"])
def test_sweep_names_that_are_not_one_safe_folder_name_are_refused(name):
    for what, data in (("sequence", {"sequences": [{"path": "some/where", "name": name}], "configurations": {"ours": {}}}),
                       ("method", {"sequences": [{"path": "some/where"}], "configurations": {name: {}}})):
        with pytest.raises(ConfigError) as err:
            parse_sweep(data, "my_sweep.yaml")
        message = str(err.value)
        assert message.startswith(f"my_sweep.yaml: {what} name {name!r} cannot be a folder name") and "\n" not in message


def test_default_names_from_paths_and_names_with_slashes_are_refused():
    with pytest.raises(ConfigError, match="sequence name '..' cannot be a folder name"):  # a path's last part is its default name
        parse_sweep({"sequences": [{"path": "some/where/.."}], "configurations": {"ours": {}}}, "s.yaml")
    for bad in ("a/../..", "/tmp/abs", "a b", "x" * 201):  # slashes, absolute paths, spaces, too long
        with pytest.raises(ConfigError, match="cannot be a folder name"):
            parse_sweep({"sequences": [{"path": "some/where", "name": bad}], "configurations": {"ours": {}}}, "s.yaml")


def test_a_sweep_named_dotdot_writes_nothing_outside_out(tmp_path, mbavo):
    home = tmp_path / "home"
    home.mkdir()
    (home / "trajectory.txt").write_text("mine\n")
    sweep = write_sweep(home / "sweep.yaml", {"sequences": [{"path": str(tmp_path / "missing"), "name": ".."}],
                                              "configurations": {"..": {}}})
    before = listing(tmp_path)
    r = mbavo("sweep", sweep, "--out", home / "out", "-q")
    one_line_error(r, str(sweep), "'..'", "cannot be a folder name")
    assert listing(tmp_path) == before and (home / "trajectory.txt").read_text() == "mine\n"


# ------------------------------------------------------------- 3. settings are taken as written


@pytest.fixture
def secret_home(tmp_path, monkeypatch):
    home = tmp_path / SECRET
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    return home


@pytest.mark.parametrize("override", ["tracker.n=${oc.env:HOME}", "runtime.cache_dir=${oc.env:HOME}",
                                      "evaluation.align=x${oc.env:HOME}", "tracker.n=${oc.env:HOME,1}"])
def test_set_never_expands_interpolation(override, secret_home):
    with pytest.raises(ConfigError) as err:
        load_config(None, [override])
    assert SECRET not in str(err.value) and "\n" not in str(err.value) and "taken as written" in str(err.value)


def test_config_files_never_expand_interpolation(tmp_path, secret_home):
    path = tmp_path / "config.yaml"
    path.write_text("tracker:\n  n: 4\nruntime:\n  cache_dir: ${oc.env:HOME}/cache\n")
    with pytest.raises(ConfigError) as err:
        load_config(path)
    assert SECRET not in str(err.value) and str(err.value).startswith(f"{path}: runtime.cache_dir: ")


def test_a_second_sweep_into_a_busy_folder_is_refused(tmp_path, mbavo):
    """Two sweeps into one ``--out``: the second would rewrite the first's result.json files while
    its runs go on; it is one line naming the folder and the holder's pid, and writes nothing."""
    from mbavo_jax.lock import RunLock

    out = tmp_path / "out"
    out.mkdir()
    sweep = write_sweep(tmp_path / "sweep.yaml", {"sequences": [{"preset": "strong", "frames": 2, "width": 64, "height": 48}],
                                                  "configurations": {"ours": {}}})
    with RunLock(out) as held:
        held.sign()
        r = mbavo("sweep", sweep, "--out", out, "-q")
    one_line_error(r, f"pid {os.getpid()}")
    assert sorted(p.name for p in out.iterdir()) == []


def test_a_file_cannot_choose_where_compiled_programs_are_loaded_from(tmp_path, mbavo):
    """``runtime.cache_dir`` names the folder whose compiled programs a run loads and runs: a
    ``--config`` file or a sweep file from someone else may not set it (one line); ``--set`` may."""
    path = tmp_path / "config.yaml"
    path.write_text("runtime:\n  cache_dir: shipped_cache\n")
    with pytest.raises(ConfigError, match="cannot be set in a file"):
        load_config(path)
    assert load_config(None, ["runtime.cache_dir=mine"]).runtime.cache_dir == "mine"
    assert load_config(REPO / "configs" / "default.yaml").runtime.cache_dir == ""  # the default folder is no choice
    for where in ("base", "configurations"):
        settings = {"runtime.cache_dir": "shipped_cache"}
        sweep = write_sweep(tmp_path / "sweep.yaml", {"sequences": [{"preset": "strong", "frames": 2, "width": 64, "height": 48}],
                                                      "base": settings if where == "base" else {},
                                                      "configurations": {"ours": settings if where != "base" else {}}})
        r = mbavo("sweep", sweep, "--out", tmp_path / "out", "-q")
        one_line_error(r, "cannot be set in a file")
        assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("override", ["tracker.n=${oc.env:HOME}", "runtime.cache_dir=${oc.env:HOME}"])
def test_track_never_copies_the_environment_into_messages_or_run_files(override, tmp_path, secret_home, mbavo):
    """A type error names the setting without its expanded value; a string setting is not filled in."""
    out = tmp_path / "run"
    r = mbavo("track", tiny_tum(tmp_path / "seq"), "--out", out, "--max-frames", "1", "-q", *SMALL, "--set", override)
    one_line_error(r, "taken as written")
    assert SECRET not in r.stdout + r.stderr
    for name in ("config.yaml", "run.yaml"):
        assert not (out / name).is_file() or SECRET not in (out / name).read_text()


def test_sweep_files_never_expand_interpolation(tmp_path, secret_home, mbavo):
    sweep = write_sweep(tmp_path / "sweep.yaml", {"sequences": [{"path": str(tmp_path / "missing")}],
                                                  "configurations": {"ours": {"runtime.cache_dir": "${oc.env:HOME}"}}})
    r = mbavo("sweep", sweep, "--out", tmp_path / "out", "-q")
    one_line_error(r, str(sweep), "runtime.cache_dir", "taken as written")
    assert SECRET not in r.stdout + r.stderr and not (tmp_path / "out").exists()


# --------------------------------------------------------------------- 4. one writer per folder


def wait_for(what, ok, proc, seconds: float = 120.0) -> None:
    deadline = time.monotonic() + seconds
    while not ok():
        assert proc.poll() is None, f"the process ended (status {proc.returncode}) before {what}"
        assert time.monotonic() < deadline, f"no {what} within {seconds} s"
        time.sleep(0.05)


@pytest.mark.slow
def test_a_second_writer_is_refused_and_a_killed_holder_blocks_nothing(tmp_path, mbavo):
    seq, out, flag = tiny_tum(tmp_path / "seq"), tmp_path / "run", tmp_path / "blocked"
    args = ["track", str(seq), "--out", str(out), "-q", *SMALL]
    # blocks at the first image read once run.yaml exists: the folder is held, its records begun
    holder = subprocess.Popen([sys.executable, "-c", BLOCK_AT_FRAME, "*", str(flag), str(out / "run.yaml"), *args],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        wait_for("a run holding its folder", flag.exists, holder)
        record = (out / "run.yaml").read_text()
        r = mbavo(*args, "--max-frames", "1")
        one_line_error(r, str(out), f"pid {holder.pid}")
        assert (out / "run.yaml").read_text() == record  # the holder's records untouched
    finally:
        holder.send_signal(signal.SIGKILL)  # the OS ends its lock with it
        holder.wait(timeout=60)
    assert (out / ".mbavo.pid").read_text() == f"{holder.pid}\n"  # left behind by the killed holder
    r = mbavo(*args, "--resume", "--max-frames", "1", "--format", "json")
    assert r.returncode == 0, r.stderr  # the killed holder's lock ended with it; --resume works beside its pid file
    assert (out / "trajectory.txt").is_file() and not (out / ".mbavo.pid").exists()  # removed when the run ended


@pytest.mark.slow
def test_an_interrupted_run_gives_its_folder_back(tmp_path):
    """Ctrl-C (SIGTERM is the same KeyboardInterrupt) inside a run releases the lock in this very
    process: the next run in the same process may write the folder."""
    from mbavo_jax.datasets import open_sequence
    from mbavo_jax.odometry import run_odometry
    from mbavo_jax.lock import RunLock

    def interrupt(*_):
        raise KeyboardInterrupt

    seq, out = open_sequence(tiny_tum(tmp_path / "seq")), tmp_path / "run"
    with pytest.raises(KeyboardInterrupt):
        run_odometry(seq, out, load_config(None, SMALL_SET), progress=False, observer=interrupt)
    assert (out / "run.yaml").is_file() and not (out / ".mbavo.pid").exists()  # the run went ahead, then gave the folder back
    RunLock(out).release()  # free again: acquired and released at once


# -------------------------------------------------------- 5. sweep workers end with the sweep

def children_of(pid: int) -> list[psutil.Process]:
    return psutil.Process(pid).children(recursive=True)


def gone(procs: list[psutil.Process], seconds: float = 30.0) -> list[int]:
    """The pids of ``procs`` still running (not ended, not a zombie) after up to ``seconds``."""
    deadline = time.monotonic() + seconds
    while True:
        alive = []
        for p in procs:
            try:
                if p.is_running() and p.status() != psutil.STATUS_ZOMBIE:
                    alive.append(p.pid)
            except psutil.NoSuchProcess:
                pass
        if not alive or time.monotonic() > deadline:
            return alive
        time.sleep(0.2)


@pytest.fixture
def long_sweep(tmp_path):
    """A sweep whose one worker generates a long sequence (minutes): it is busy once its first frames are on disk."""
    sweep = write_sweep(tmp_path / "long.yaml", {"sequences": [{"preset": "strong", "name": "long", "frames": 3000, "width": 32,
                                                                "height": 24, "subframes": 8, "real_textures": False}],
                                                 "configurations": {"ours": {}}})
    return sweep, tmp_path / "out"


@pytest.mark.slow
@pytest.mark.parametrize("sig", [signal.SIGKILL, signal.SIGTERM], ids=["SIGKILL", "SIGTERM"])
def test_sweep_workers_end_with_the_sweep(sig, long_sweep):
    sweep, out = long_sweep
    proc = subprocess.Popen([sys.executable, "-m", "mbavo_jax.cli", "sweep", str(sweep), "--out", str(out), "-q"],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    workers = []
    try:
        wait_for("a busy worker", lambda: len(list((out / "data" / "long" / "rgb").glob("*.png"))) >= 2, proc, 300)
        workers = children_of(proc.pid)
        assert workers, "no worker process"
        proc.send_signal(sig)
        status = proc.wait(timeout=30)
        assert gone(workers) == [], "workers outlived the sweep"
    finally:
        for w in workers:  # the old behaviour: end them here, by pid
            try:
                w.kill()
            except psutil.NoSuchProcess:
                pass
        if proc.poll() is None:
            proc.kill()
            proc.wait(timeout=30)
    if sig == signal.SIGTERM:
        err = proc.stderr.read()
        lines = err.strip().splitlines()
        assert status != 0 and len(lines) == 1, err
        assert lines[0].startswith(f"mbavo: interrupted: sweep {sweep} stopped") and "--resume" not in err and "leaked" not in err


# ------------------------------------------------------------ 11. Ray Client without ray[client]


def test_a_ray_client_address_without_ray_client_is_one_line_before_connecting(tmp_path, mbavo, monkeypatch):
    import ray

    def connect(*args, **kwargs):
        raise AssertionError("ray.init was called: something tried to connect")

    monkeypatch.setitem(sys.modules, "grpc", None)  # Ray Client's package missing, wherever this runs
    monkeypatch.setattr(ray, "init", connect)
    sweep = write_sweep(tmp_path / "sweep.yaml", {"sequences": [{"path": str(tmp_path / "missing")}], "configurations": {"ours": {}}})
    r = mbavo("sweep", sweep, "--out", tmp_path / "out", "--engine", "ray", "--address", "ray://127.0.0.1:1", "-q")
    one_line_error(r, "ray://127.0.0.1:1", "ray[client]")
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------- 18. sweeps that run nothing or fail


def test_an_empty_list_in_a_sweep_is_one_line(tmp_path, mbavo):
    sweep = write_sweep(tmp_path / "sweep.yaml", {"sequences": [{"preset": "strong", "seed": []}], "configurations": {"ours": {}}})
    r = mbavo("sweep", sweep, "--out", tmp_path / "out", "-q")
    one_line_error(r, str(sweep), "sequences[0]: seed: []")
    assert not (tmp_path / "out").exists()
    with pytest.raises(ConfigError, match=r"configurations.ours: tracker.n: \[\]"):
        parse_sweep({"sequences": ["a"], "configurations": {"ours": {"tracker.n": []}, "other": {}}}, "s.yaml")


@pytest.mark.slow
def test_a_sweep_whose_every_run_failed_exits_1_with_the_table(tmp_path, mbavo):
    sweep = write_sweep(tmp_path / "sweep.yaml", {"sequences": [{"path": str(tmp_path / "missing")}],
                                                  "configurations": {"ours": {}, "blind": {"tracker.blur_aware": False}}})
    r = mbavo("sweep", sweep, "--out", tmp_path / "out", "-q")
    assert r.returncode == 1, r.stderr
    assert r.stderr.strip().splitlines()[-1] == (f"mbavo: error: {sweep}: all 2 runs failed "
                                                 f"(the errors are in {tmp_path / 'out' / 'results.md'})")
    assert (tmp_path / "out" / "results.csv").is_file() and "sequence folder not found" in (tmp_path / "out" / "results.md").read_text()
