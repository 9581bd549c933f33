"""``mbavo bench odometry``'s goals as columns (issue 57): each rule met and not met on constructed
results, the sequences' names over sizes and seeds, and the tables with methods missing. No run."""

from __future__ import annotations

import json

import pytest

from mbavo_jax.bench.goals import GOALS, format_goals_table, has_metadata, sequence_goals, with_goals
from mbavo_jax.config import BenchConfig
from mbavo_jax.errors import ConfigError


def entry(blur, n64=None, n1=None, depth=None, o3d=None, path=None, exposure="known") -> dict:
    """A sequence's results as ``odometry.nested_results`` gives them (ATE in mm here, m there)."""
    methods = {}
    for name, ate in (("ours_n64", n64), ("ours_n1", n1), ("ours_n64_depth", depth), ("open3d", o3d)):
        if ate is not None:
            methods[name] = {"ate_rmse_m": ate / 1000.0, "frame_drop_rate": 0.0}
            if name.startswith("ours_n64"):
                methods[name].update(exposure=exposure, exposure_ms=20.0, exposure_samples=7)
    if path is not None:
        methods["ours_n64"]["exposure_length_ratio"] = path
    return {"mean_blur_px": blur, "frames": 30, "depth_sigma": [0.0005, 0.0], "depth_weight": 0.03, "methods": methods}


def verdicts(row: dict) -> dict:
    return {k: (None if row[k] is None else row[k]["met"]) for k in ("n64_n1", "depth_open3d", "path_true", "sharp_n64_n1")}


def test_mild_blur_n64_at_most_1_05_of_n1_and_the_depth_term_at_most_open3d_with_or_without_metadata():
    for exposure, name in (("known", "mild"), ("estimate", "mild_noexp")):
        met = sequence_goals(name, entry(4.0, n64=1.04, n1=1.0, depth=0.5, o3d=0.5, exposure=exposure))
        assert met["metadata"] == (exposure == "known") and met["n64_n1"]["bound"] == 1.05
        assert verdicts(met) == {"n64_n1": True, "depth_open3d": True, "path_true": None, "sharp_n64_n1": None}
        missed = sequence_goals(name, entry(5.0, n64=1.06, n1=1.0, depth=0.51, o3d=0.5, exposure=exposure))
        assert verdicts(missed) == {"n64_n1": False, "depth_open3d": False, "path_true": None, "sharp_n64_n1": None}
    assert sequence_goals("m", entry(4.0, n64=1.04, n1=1.0))["n64_n1"]["value"] == pytest.approx(1.04)


def test_strong_blur_n64_at_most_0_55_of_n1_without_metadata_and_the_depth_term_at_most_0_7_of_open3d():
    met = sequence_goals("strong_noexp", entry(20.0, n64=5.4, n1=10.0, depth=0.69, o3d=1.0, exposure="estimate"))
    assert verdicts(met) == {"n64_n1": True, "depth_open3d": True, "path_true": None, "sharp_n64_n1": None}
    missed = sequence_goals("strong_noexp", entry(40.0, n64=5.6, n1=10.0, depth=0.71, o3d=1.0, exposure="estimate"))
    assert verdicts(missed) == {"n64_n1": False, "depth_open3d": False, "path_true": None, "sharp_n64_n1": None}
    known = sequence_goals("strong", entry(20.0, n64=9.0, n1=10.0, depth=0.69, o3d=1.0))
    assert known["n64_n1"] is None and known["depth_open3d"]["met"] is True  # n64 / n1 is a goal without metadata only
    between = sequence_goals("x_noexp", entry(7.5, n64=9.0, n1=1.0, depth=9.0, o3d=1.0, exposure="estimate"))
    assert between["n64_n1"] is None and between["depth_open3d"] is None  # 5-10 px: neither goal
    beyond = sequence_goals("x_noexp", entry(41.0, n64=9.0, n1=1.0, depth=9.0, o3d=1.0, exposure="estimate"))
    assert beyond["n64_n1"] is None and beyond["depth_open3d"] is None


def test_the_path_length_within_20_percent_from_3_px_of_blur():
    assert sequence_goals("m", entry(3.0, n64=1.0, n1=1.0, path=1.19))["path_true"]["met"] is True
    assert sequence_goals("m", entry(3.0, n64=1.0, n1=1.0, path=0.81))["path_true"]["met"] is True
    assert sequence_goals("m", entry(3.0, n64=1.0, n1=1.0, path=1.21))["path_true"]["met"] is False
    assert sequence_goals("m", entry(30.0, n64=1.0, n1=1.0, path=0.79))["path_true"]["met"] is False
    assert sequence_goals("m", entry(2.9, n64=1.0, n1=1.0, path=2.0))["path_true"] is None
    assert sequence_goals("m", entry(4.0, n64=1.0, n1=1.0))["path_true"]["met"] is None  # goal applies, no number


def test_sharp_frames_n64_within_10_percent_of_n1():
    sharp = sequence_goals("none", entry(0.0, n64=1.09, n1=1.0))
    assert sharp["sharp_n64_n1"]["met"] is True and sharp["n64_n1"]["met"] is False  # the 5 px goal is the stricter
    assert sequence_goals("none", entry(0.0, n64=1.11, n1=1.0))["sharp_n64_n1"]["met"] is False
    assert sequence_goals("mild", entry(GOALS.sharp_px, n64=1.0, n1=1.0))["sharp_n64_n1"] is None


def test_missing_methods_and_unknown_blur_leave_the_goal_unscored():
    row = sequence_goals("mild", entry(2.0, n64=1.0))
    assert row["n64_n1"] == {"value": None, "bound": 1.05, "met": None, "around_one": False}
    assert row["depth_open3d"]["met"] is None
    failed = entry(2.0, n64=1.0, n1=1.0)
    failed["methods"]["ours_n1"] = {"error": "lost"}
    assert sequence_goals("mild", failed)["n64_n1"]["met"] is None
    real = sequence_goals("tum", entry(None, n64=1.0, n1=2.0))
    assert real["blur_px"] is None and verdicts(real) == dict.fromkeys(verdicts(real))


def test_metadata_is_read_from_our_runs_else_from_the_name():
    assert has_metadata("a_noexp", entry(2.0, n64=1.0, exposure="estimate")) is False
    assert has_metadata("a_noexp", entry(2.0, n64=1.0, exposure="known")) is True
    only_n1 = {"methods": {"ours_n1": {"exposure": "none"}, "open3d": {"ate_rmse_m": 0.001}}}
    assert has_metadata("a_noexp", only_n1) is False and has_metadata("a", only_n1) is True


def test_the_goals_table_renders_with_methods_missing_and_goes_into_the_results():
    from mbavo_jax.bench.odometry import format_odometry_table

    res = with_goals({"mild_320x240_s5": entry(3.2, n64=1.0, n1=1.1, path=1.1),
                      "mild_320x240_s5_noexp": entry(3.2, n64=1.2, exposure="estimate"),
                      "strong_noexp": {**entry(20.0, o3d=3.0), "methods": {"ours_n64": {"error": "lost"}, "open3d": {"ate_rmse_m": 0.003}}}})
    assert json.loads(json.dumps(res))["mild_320x240_s5"]["goals"]["n64_n1"]["met"] is True
    table = format_odometry_table(res)
    goals = table[table.index("goals (issue 57"):].splitlines()
    assert goals[2].split() == ["mild_320x240_s5", "3.2", "yes", "0.91", "<=1.05", "met", "?", "<=1.00", "1.10", "1±0.20", "met", "-"]
    assert goals[3].split() == ["mild_320x240_s5_noexp", "3.2", "no", "?", "<=1.05", "?", "<=1.00", "?", "1±0.20", "-"]
    assert goals[4].split() == ["strong_noexp", "20.0", "no", "?", "<=0.55", "?", "<=0.70", "?", "1±0.20", "-"]
    assert goals[-1] == "met 2 of 2 goals scored (7 without their methods' numbers)"
    assert "\nours_n1 " in table and "\nopencv " not in table and "\nours_n64_depth " not in table  # rows of the methods that ran
    assert format_goals_table({}).splitlines()[-1] == "met 0 of 0 goals scored (0 without their methods' numbers)"


def test_sequences_are_named_by_size_and_seed_when_a_run_has_several():
    from mbavo_jax.bench.sequences import Generated, generated_sequences

    one = BenchConfig(presets="mild", sensor_presets="strong", scenes="deep", scene_presets="extreme")
    assert generated_sequences(one) == {"mild": Generated("mild", 0, 640, 480), "strong_sensor": Generated("strong", 0, 640, 480, "sensor"),
                                        "extreme_deep": Generated("extreme", 0, 640, 480, scene="deep")}
    many = BenchConfig(presets="mild", sensor_presets="", width=320, height=240, seed=5, seeds="9,5", sizes="640x480,320x240")
    assert generated_sequences(many) == {"mild_320x240_s5": Generated("mild", 5, 320, 240), "mild_320x240_s9": Generated("mild", 9, 320, 240),
                                         "mild_640x480_s5": Generated("mild", 5, 640, 480), "mild_640x480_s9": Generated("mild", 9, 640, 480)}
    assert list(generated_sequences(many)) == ["mild_320x240_s5", "mild_320x240_s9", "mild_640x480_s5", "mild_640x480_s9"]
    seeds_only = BenchConfig(presets="none", sensor_presets="", seeds="1")
    assert list(generated_sequences(seeds_only)) == ["none_640x480_s0", "none_640x480_s1"]
    assert list(generated_sequences(BenchConfig())) == ["none", "mild", "strong", "extreme", "strong_sensor", "extreme_sensor"]


def test_sizes_and_tum_blurs_are_checked_and_listed():
    cfg = BenchConfig(sizes="640x480, 320X240", tum_blur_px="5,20,5")
    assert cfg.size_list() == [(640, 480), (320, 240)] and cfg.tum_blur_list() == [5.0, 20.0]
    assert BenchConfig().tum_blur_list() == [20.0] and BenchConfig().size_list() == [(640, 480)]
    for bad, key in (({"sizes": "640x8"}, "sizes"), ({"sizes": "640"}, "sizes"), ({"tum_blur_px": "0"}, "tum_blur_px"),
                     ({"tum_blur_px": "5,inf"}, "tum_blur_px"), ({"tum_blur_px": "nan"}, "tum_blur_px")):
        with pytest.raises(ConfigError, match=key):
            BenchConfig(**bad)
