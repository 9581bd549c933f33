"""``mbavo bench speed``'s parts: the profile's split of a run's time and the memory growth read
from frames.csv (no timing asserts: only that the parts are found and add up)."""

import csv

import pytest

from mbavo_jax.bench.speed import PROFILE_PARTS, format_speed_table, memory_growth, profile_run, timed_runs, variant_scores
from mbavo_jax.config import RunConfig, TrackerConfig
from mbavo_jax.datasets import open_sequence
from mbavo_jax.odometry.outputs import CSV_COLUMNS

from .conftest import run_cli


def _frames_csv(folder, rss):
    with open(folder / "frames.csv", "w", newline="") as fh:
        w = csv.DictWriter(fh, CSV_COLUMNS)
        w.writeheader()
        for i, r in enumerate(rss):
            w.writerow({"index": i, "timestamp": f"{1 + i / 30:.6f}", "status": "converged", "rss_mb": f"{r:.1f}"})


def test_memory_growth_is_the_ratio_of_late_to_early_resident_memory(tmp_path):
    _frames_csv(tmp_path, [500.0] * 5 + [800.0] * 95 + [820.0] * 100 + [880.0])
    g = memory_growth(tmp_path, early=100)
    assert g["frames"] == 201 and g["rss_mb_at_100"] == 800.0 and g["rss_mb_at_end"] == 880.0
    assert g["ratio"] == pytest.approx(1.1) and g["peak_rss_mb"] == 880.0
    with pytest.raises(ValueError, match="need more than 300"):
        memory_growth(tmp_path, early=300)


@pytest.mark.slow
def test_profile_splits_a_run_into_its_parts(tmp_path):
    seq_dir = tmp_path / "seq"
    assert run_cli("synth", "--out", str(seq_dir), "--preset", "strong", "--frames", "4", "--width", "160", "--height", "120", "-q") == 0
    seq = open_sequence(seq_dir)
    config = RunConfig(tracker=TrackerConfig(response_gamma=2.2, n=8))
    r = profile_run(seq, tmp_path / "run", config)
    assert set(r["parts"]) == set(PROFILE_PARTS) and r["frames"] == 4
    assert r["parts"]["tracking"] > 0 and r["parts"]["writing outputs"] > 0 and r["parts"]["reading frames"] > 0
    assert r["parts"]["back-end (mono)"] == 0  # an RGB-D run
    assert sum(r["parts"].values()) + r["rest"] == pytest.approx(r["seconds"])
    assert 0 <= sum(r["parts"].values()) <= r["seconds"]
    assert (tmp_path / "run" / "trajectory.txt").is_file()


@pytest.mark.slow
def test_timed_runs_alternate_after_a_warm_up(tmp_path):
    seq_dir = tmp_path / "seq"
    assert run_cli("synth", "--out", str(seq_dir), "--preset", "none", "--frames", "3", "--width", "96", "--height", "72", "-q") == 0
    seq = open_sequence(seq_dir)
    config = RunConfig()
    variants = {"a": config.replace(tracker=dict(n=2)), "b": config.replace(tracker=dict(blur_aware=False))}
    runs = timed_runs(seq, tmp_path / "t", variants, frames=3, reps=2)
    assert set(runs) == {"a", "b"} and all(len(v) == 2 and min(v) > 0 for v in runs.values())
    # the warm-up (run0) and both timed runs of each variant wrote a whole trajectory
    for name in runs:
        for rep in range(3):
            lines = (tmp_path / "t" / name / f"run{rep}" / "trajectory.txt").read_text().splitlines()
            assert len([x for x in lines if not x.startswith("#")]) == 3
    # each variant scored on its first timed run (tracked, so an ATE, not NaN; the sharp keyframe near its truth)
    scores = variant_scores(seq, tmp_path / "t", variants)
    assert set(scores) == {"a", "b"}
    assert all(0 <= s["ate_m"] < 1.0 and s["keyframes"] >= 1 and s["keyframe_psnr"] > 30 for s in scores.values()), scores


def test_speed_table_takes_its_ratios_from_the_medians_of_the_unprofiled_runs():
    profile = {"seconds": 9.0, "parts": dict.fromkeys(PROFILE_PARTS, 1.0), "rest": 3.0, "compile_seconds": 0.0}
    res = {"p": {"frames": 10, "seconds": {"ours": [3.0, 2.0, 9.0], "n1": [1.0, 1.0, 5.0]}, "profile": profile,
                 "open3d_s_per_frame": 0.1, "startup": {}}}
    head = format_speed_table(res).splitlines()[0]
    assert "whole loop 0.300 s/frame" in head and "3.0x Open3D" in head and "3.00x ours blind to blur (n = 1, 0.100 s)" in head


def test_speed_table_puts_the_compared_settings_beside_ours():
    profile = {"seconds": 9.0, "parts": dict.fromkeys(PROFILE_PARTS, 1.0), "rest": 3.0, "compile_seconds": 0.0}
    score = lambda ate, psnr: {"ate_m": ate, "keyframes": 4, "keyframe_psnr": psnr}
    res = {"p": {"frames": 10, "seconds": {"ours": [3.0, 2.0, 9.0], "n1": [1.0, 1.0, 5.0], "compare": [1.5, 1.5, 7.0]}, "profile": profile,
                 "scores": {"ours": score(0.002, 25.0), "n1": score(float("nan"), None), "compare": score(0.0031, 25.5)},
                 "compare": "deblur.iterations=8", "open3d_s_per_frame": 0.1, "startup": {}}}
    lines = format_speed_table(res).splitlines()
    assert "| ours | 0.300 | 1.00 | 2.00 | 4 | 25.00 |" in lines
    assert "| n = 1 | 0.100 | 0.33 | lost | 4 | - |" in lines
    assert "| ours with deblur.iterations=8 | 0.150 | 0.50 | 3.10 | 4 | 25.50 |" in lines
