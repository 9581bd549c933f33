"""`mbavo sweep`: the sweep file (products, one-line errors), the engines (local process pool and
Ray give the same table; a dying worker costs only its run), resuming (finished runs are kept),
failures as rows, and `mbavo bench odometry` as a sweep."""

from __future__ import annotations

import csv
import math
import os
import pathlib

import pytest
import yaml

from mbavo_jax.config import SweepConfig
from mbavo_jax.sweep import parse_sweep, run_sweep, tasks_of
from mbavo_jax.sweep.engine import MAX_TRIES, map_unordered

SMALL = {"tracker.levels": 3, "tracker.points": [192, 128, 64], "tracker.cell": [10, 7, 5], "tracker.max_steps": [10, 12, 20]}
SWEEPS = pathlib.Path(__file__).resolve().parents[1] / "configs" / "sweeps"
TINY = {"frames": 4, "width": 160, "height": 120, "subframes": 8, "real_textures": False}


# ------------------------------------------------------------------------------- the sweep file


def test_lists_make_products_of_sequences_and_configurations():
    spec = parse_sweep({"sequences": [{"preset": "strong", "seed": [1, 2], **TINY}, {"path": "some/where", "name": "real"}],
                        "base": SMALL, "configurations": {"ours": {"tracker.n": [1, 64], "tracker.blur_aware": True},
                                                          "pts": {"tracker.points": [[96, 64, 32], [192, 128, 64]]}},
                        "peers": ["opencv"]})
    assert [s.name for s in spec.sequences] == ["strong_seed=1", "strong_seed=2", "real"]
    assert [s.synth["seed"] for s in spec.sequences[:2]] == [1, 2] and spec.sequences[0].synth["exposure_ms"] == 25.0  # the preset's
    assert spec.methods == ["ours_n=1", "ours_n=64", "pts_points=96-64-32", "pts_points=192-128-64", "opencv"]
    assert spec.configurations["ours_n=64"][-2:] == ("tracker.n=64", "tracker.blur_aware=true")
    assert spec.configurations["pts_points=96-64-32"][-1] == "tracker.points=[96, 64, 32]"  # a list setting: a list of lists is the product
    tasks = tasks_of(spec, "/tmp/sweep_out")
    assert len(tasks) == 3 * 5
    assert tasks[0].out == "/tmp/sweep_out/runs/strong_seed=1/ours_n=1" and tasks[0].data == "/tmp/sweep_out/data/strong_seed=1"
    assert tasks[4].peer == "opencv" and tasks[4].overrides == spec.base and not tasks[0].peer
    assert tasks[-1].data == os.path.abspath("some/where")


@pytest.mark.parametrize("text, message", [
    ("sequences: [a]\nconfigurations: {ours: {}}\nworkers: 3\n", "unknown key(s) workers in the sweep file"),
    ("sequences: []\nconfigurations: {ours: {}}\n", "sequences: must be a non-empty list"),
    ("sequences: [{preset: strong, sed: 1}]\nconfigurations: {ours: {}}\n", "unknown key(s) sed in sequences[0]"),
    ("sequences: [{preset: blurry}]\nconfigurations: {ours: {}}\n", "unknown preset 'blurry'"),
    ("sequences: [{preset: strong, path: a}]\nconfigurations: {ours: {}}\n", "needs exactly one of path:, preset: or from:"),
    ("sequences: [{preset: strong, width: 4}]\nconfigurations: {ours: {}}\n", "width: must be >= 16"),
    ("sequences: [a]\nconfigurations: {ours: {tracker.nn: 3}}\n", "configurations.ours: --set tracker.nn=3: unknown setting"),
    ("sequences: [a]\nconfigurations: {ours: {tracker.n: [1, two]}}\n", "configurations.ours: --set tracker.n=two"),
    ("sequences: [a]\nbase: {odometry.mode: sideways}\nconfigurations: {ours: {}}\n", "odometry.mode"),
    ("sequences: [a]\npeers: [orb_slam]\n", "peers: must be a list of open3d, open3d_color, opencv"),
    ("sequences: [a]\n", "nothing to run"),
    ("sequences: [x/a, y/a]\nconfigurations: {ours: {}}\n", "sequence name(s) a appear twice"),
    ("sequences: [a]\nconfigurations: {opencv: {}}\npeers: [opencv]\n", "method name(s) opencv appear twice"),
    ("sequences: [a\n", "not valid YAML"),
])
def test_sweep_file_errors_are_one_line_before_any_work(tmp_path, mbavo, text, message):
    path = tmp_path / "sweep.yaml"
    path.write_text(text)
    r = mbavo("sweep", path, "--out", tmp_path / "out")
    assert r.returncode == 1 and len(r.stderr.strip().splitlines()) == 1, r.stderr
    assert r.stderr.startswith(f"mbavo: error: {path}: ") and message in r.stderr, r.stderr
    assert not (tmp_path / "out").exists()


def test_engine_options_are_checked(tmp_path, mbavo):
    r = mbavo("sweep", tmp_path / "missing.yaml", "--out", tmp_path / "out")
    assert r.returncode == 1 and r.stderr.strip() == f"mbavo: error: {tmp_path / 'missing.yaml'}: sweep file not found"
    r = mbavo("sweep", tmp_path / "missing.yaml", "--out", tmp_path / "out", "--address", "auto")
    assert r.returncode == 1 and r.stderr.strip() == "mbavo: error: address needs engine: ray"
    r = mbavo("sweep", tmp_path / "missing.yaml", "--out", tmp_path / "out", "--jobs", "0")
    assert r.returncode == 1 and "jobs: must be >= 1" in r.stderr


# ------------------------------------------------------------------------------------- engines


def square_or_die(x: int) -> int:
    """A worker's job for the engine test: x squared, or the worker process dies (x < 0)."""
    if x < 0:
        os._exit(3)
    return x * x


def test_a_dying_worker_costs_only_its_own_item():
    items = [1, 2, -1, 3, 4]
    got = dict(map_unordered(square_or_die, items, SweepConfig(jobs=2), lambda item, exc: f"died: {item}"))
    assert got == {0: 1, 1: 4, 2: "died: -1", 3: 9, 4: 16}
    assert MAX_TRIES == 2  # the dying item was given one more try in a fresh pool


def test_bench_odometry_is_a_sweep_of_its_methods():
    from mbavo_jax.bench.odometry import nested_results, odometry_sweep

    spec = odometry_sweep({"strong": "a/strong", "tum": "b/tum"}, {"levels": 3}, depth_weight=0.01,
                          methods=["ours_n1_depth", "ours_n64", "opencv", "open3d"])
    assert spec.methods == ["ours_n64", "ours_n1_depth", "open3d", "opencv"]  # the benchmark's order
    assert spec.configurations["ours_n1_depth"] == ("tracker.levels=3", "tracker.blur_aware=false", "tracker.depth_weight=0.01")
    assert [s.path for s in spec.sequences] == ["a/strong", "b/tum"]
    rows = [{"sequence": "strong", "method": "ours_n64", "status": "ok", "ate_rmse_m": 0.001, "frames": 4, "mean_blur_px": 3.0,
             "depth_sigma": [0.0005, 0.0], "psnr_deblurred": 30.0, "psnr_blurry": 25.0, "ssim_deblurred": 0.9, "ssim_blurry": 0.8,
             "deblur_keyframes": 1, "seconds": 2.0, "overrides": ""},
            {"sequence": "strong", "method": "opencv", "status": "error", "error": "opencv unavailable: no cv2"}]
    res = nested_results(rows, 0.01)
    assert res == {"strong": {"mean_blur_px": 3.0, "frames": 4, "depth_sigma": [0.0005, 0.0], "depth_weight": 0.01, "methods": {
        "ours_n64": {"ate_rmse_m": 0.001, "deblur": {"keyframes": 1, "psnr_deblurred": 30.0, "psnr_blurry": 25.0,
                                                      "ssim_deblurred": 0.9, "ssim_blurry": 0.8}},
        "opencv": {"error": "opencv unavailable: no cv2"}}}}


# ------------------------------------------------------------------------- end to end, two engines


@pytest.fixture(scope="module")
def sweep_file(tmp_path_factory):
    """Two tiny generated sequences, a folder that does not exist, n = 1 and 4, and a configuration
    that passes the checks but fails at run time (no level can hold that many points)."""
    root = tmp_path_factory.mktemp("sweep")
    spec = {"sequences": [{"preset": "strong", "seed": [1, 2], **TINY}, {"path": str(root / "no_such_sequence")}],
            "base": SMALL, "configurations": {"ours": {"tracker.n": [1, 4]}, "strict": {"tracker.min_valid": 100000}}}
    (root / "sweep.yaml").write_text(yaml.safe_dump(spec))
    return root / "sweep.yaml"


def read_rows(path) -> list[dict]:
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def ok_runs(rows) -> dict:
    return {(r["sequence"], r["method"]): float(r["ate_rmse_m"]) for r in rows if r["status"] == "ok"}


@pytest.mark.slow
def test_local_sweep_table_failures_and_resume(sweep_file, tmp_path_factory, mbavo):
    out = tmp_path_factory.getbasetemp() / "sweep_local"
    r = mbavo("sweep", sweep_file, "--out", out, "--jobs", "2", "-q")
    assert r.returncode == 0, r.stderr
    rows = read_rows(out / "results.csv")
    assert [(x["sequence"], x["method"]) for x in rows] == [(s, m) for s in ("strong_seed=1", "strong_seed=2", "no_such_sequence")
                                                            for m in ("ours_n=1", "ours_n=4", "strict")]
    good = ok_runs(rows)
    assert set(good) == {(s, m) for s in ("strong_seed=1", "strong_seed=2") for m in ("ours_n=1", "ours_n=4")}
    assert all(0 < ate < 0.02 for ate in good.values()), good
    bad = {(x["sequence"], x["method"]): x["error"] for x in rows if x["status"] == "error"}
    assert all("no_such_sequence: sequence folder not found" in e for (s, _), e in bad.items() if s == "no_such_sequence")
    assert all("too small to track" in e for (s, m), e in bad.items() if m == "strict" and s != "no_such_sequence"), bad
    assert "| strong_seed=1 | ours_n=4 |" in (out / "results.md").read_text() and (out / "ate.png").stat().st_size > 0
    assert r.stdout.startswith("| sequence | method | ATE mm") and "9 runs: 9 executed, 0 kept, 5 failed" in r.stderr
    assert (out / "runs" / "strong_seed=2" / "ours_n=4" / "trajectory.txt").is_file()
    assert sorted(p.name for p in (out / "data").iterdir()) == ["strong_seed=1", "strong_seed=2"]

    results = {k: out / "runs" / k[0] / k[1] / "result.json" for k in good}
    before = {k: p.stat().st_mtime_ns for k, p in results.items()}
    data_before = (out / "data" / "strong_seed=1" / "rgb.txt").stat().st_mtime_ns
    again = run_sweep(parse_sweep(yaml.safe_load(sweep_file.read_text())), out, SweepConfig(jobs=2), progress=False)
    assert again.executed == len(bad) and again.kept == len(good)  # only the failed runs ran again
    assert {k: p.stat().st_mtime_ns for k, p in results.items()} == before
    assert (out / "data" / "strong_seed=1" / "rgb.txt").stat().st_mtime_ns == data_before  # the sequences were not made again
    assert ok_runs(read_rows(out / "results.csv")) == good


@pytest.mark.slow
def test_ray_gives_the_local_table(sweep_file, tmp_path_factory):
    """Ray started here (as on one machine of a cluster): the same rows and ATE as the local pool."""
    import ray

    local = tmp_path_factory.getbasetemp() / "sweep_local"
    if not (local / "results.csv").is_file():  # run alone: make the local table first
        run_sweep(parse_sweep(yaml.safe_load(sweep_file.read_text())), local, SweepConfig(jobs=2), progress=False)
    out = tmp_path_factory.getbasetemp() / "sweep_ray"
    ray.init(num_cpus=2, include_dashboard=False)
    try:
        res = run_sweep(parse_sweep(yaml.safe_load(sweep_file.read_text())), out, SweepConfig(engine="ray", jobs=2), progress=False)
    finally:
        ray.shutdown()
    assert res.executed == 9 and res.kept == 0
    want, got = read_rows(local / "results.csv"), read_rows(out / "results.csv")
    assert [(r["sequence"], r["method"], r["status"]) for r in got] == [(r["sequence"], r["method"], r["status"]) for r in want]
    a, b = ok_runs(want), ok_runs(got)
    assert a.keys() == b.keys() and all(math.isclose(a[k], b[k], rel_tol=1e-3, abs_tol=1e-7) for k in a), (a, b)


@pytest.mark.parametrize("name", ["example", "odometry", "seeds"])
def test_shipped_sweep_files_parse(name):
    from mbavo_jax.sweep import load_sweep

    spec = load_sweep(SWEEPS / f"{name}.yaml")
    assert spec.sequences and spec.methods


def test_odometry_sweep_file_is_the_benchmark():
    """configs/sweeps/odometry.yaml runs what `mbavo bench odometry` runs with its defaults."""
    from mbavo_jax.bench.odometry import odometry_sweep
    from mbavo_jax.config import BenchConfig
    from mbavo_jax.sweep import load_sweep

    cfg, spec = BenchConfig(), load_sweep(SWEEPS / "odometry.yaml")
    bench = odometry_sweep({}, depth_weight=cfg.depth_weight, peer_depth_max=cfg.peer_depth_max)
    assert spec.configurations == bench.configurations and spec.peers == bench.peers
    assert spec.peer_depth_max == bench.peer_depth_max
    names = [*cfg.presets.split(","), *(f"{p}_sensor" for p in cfg.sensor_presets.split(",")), *(f"tum_blurred{b:g}" for b in cfg.tum_blur_list())]
    assert [s.name for s in spec.sequences] == names
    for s in spec.sequences[:-1]:
        assert (s.synth["frames"], s.synth["width"], s.synth["height"], s.synth["seed"]) == (cfg.frames, cfg.width, cfg.height, cfg.seed)
    assert spec.sequences[-1].source == cfg.tum and spec.sequences[-1].blur_px == 20.0
