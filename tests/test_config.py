"""Settings (``mbavo_jax.config``): configs/default.yaml is generated from the dataclasses, files and
``--set`` overrides load through one path, and every bad value is a one-line ConfigError (also a
ValueError) naming its key."""

from __future__ import annotations

import dataclasses

import pytest

from mbavo_jax.config import DeblurConfig, OdometryConfig, RunConfig, TrackerConfig, default_yaml, load_config
from mbavo_jax.errors import ConfigError

from .conftest import REPO, make_tum


def test_default_yaml_is_generated_from_the_dataclasses():
    """`mbavo config` writes configs/default.yaml; the checked-in file must be its current output."""
    text = (REPO / "configs" / "default.yaml").read_text()
    assert text == default_yaml(), "configs/default.yaml is stale: regenerate it from mbavo_jax.config.default_yaml()"
    assert load_config(REPO / "configs" / "default.yaml") == RunConfig()


def test_fast_preset_changes_only_what_it_lists():
    fast = load_config(REPO / "configs" / "fast.yaml")
    assert fast.tracker.n_mode == "adaptive" and fast.tracker.points == (256, 192, 128, 96)
    assert fast.odometry == OdometryConfig() and fast.deblur == DeblurConfig()


def test_overrides_files_and_calibration_layer_in_order(tmp_path):
    cfg = load_config(None, ["tracker.n=16", "deblur.n=32", "deblur.regularization=0.05", "odometry.keyframe_max_blur_px=1e9"])
    assert cfg.tracker.n == 16 and cfg.deblur.n == 32 and cfg.deblur.regularization == 0.05
    assert cfg.odometry.keyframe_max_blur_px == 1e9  # YAML 1.1 reads a bare 1e9 as a string
    assert cfg.tracker.points == TrackerConfig().points and isinstance(cfg.tracker.points, tuple)
    # a file, then the sequence's camera.yaml calibration, then --set: the later wins
    path = tmp_path / "c.yaml"
    path.write_text("tracker:\n  n: 8\n  response_gamma: 1.8\ndeblur:\n  iterations: 12\n")
    cfg = load_config(path, ["tracker.n=4"], calibration={"response_gamma": 2.2, "depth_sigma": (0.0005, 0.0)})
    assert cfg.tracker.n == 4 and cfg.tracker.response_gamma == 2.2 and cfg.tracker.depth_sigma == (0.0005, 0.0)
    assert cfg.deblur.iterations == 12
    cfg = load_config(path, ["tracker.response_gamma=1.5"], calibration={"response_gamma": 2.2})
    assert cfg.tracker.response_gamma == 1.5
    assert RunConfig().replace(tracker=dict(n=32)).tracker.n == 32


@pytest.mark.parametrize(
    "override, key",
    [
        ("tracker.huber=-1", "tracker.huber"),
        ("tracker.max_steps=[0,1,1,1]", "tracker.max_steps"),
        ("tracker.affine=3", "tracker.affine"),
        ("tracker.nope=3", "tracker.nope"),
        ("nope.n=3", "nope"),
        ("tracker.n_mode=sometimes", "tracker.n_mode"),
        ("tracker.n=3.5", "tracker.n"),
        ("tracker.points=5", "tracker.points"),
        ("odometry.deblur_n=0", "odometry.deblur_n"),  # moved to deblur.n
        ("deblur.iterations=0", "deblur.iterations"),
        ("evaluation.align=affine", "evaluation.align"),
    ],
)
def test_bad_setting_is_a_one_line_config_error_naming_the_key(override, key):
    with pytest.raises(ConfigError) as info:
        load_config(None, [override])
    message = str(info.value)
    assert isinstance(info.value, ValueError)
    assert key in message and "\n" not in message.strip(), message


def test_bad_values_are_rejected_from_files_and_from_python(tmp_path):
    path = tmp_path / "bad.yaml"
    path.write_text("tracker:\n  huber: -1\n")
    with pytest.raises(ConfigError, match="tracker.huber"):
        load_config(path)
    path.write_text("tracker: [1, 2]\n")
    with pytest.raises(ConfigError, match="bad.yaml"):
        load_config(path)
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "missing.yaml")
    with pytest.raises(ConfigError, match="tracker.huber"):
        TrackerConfig(huber=-1.0)  # a config built in Python is checked the same way
    with pytest.raises(ConfigError, match="deblur.iterations"):
        DeblurConfig(iterations=0)
    with pytest.raises(ConfigError, match="depth_outlier"):
        TrackerConfig(depth_huber=30.0)  # a relation between fields: the outlier cut must exceed the Huber threshold
    with pytest.raises(ConfigError, match="section.key=value"):
        load_config(None, ["tracker=3"])
    assert dataclasses.replace(TrackerConfig(), n=8).n == 8
    for bad in ("tracker.n=${x}", "tracker.points.0=100"):  # OmegaConf's own failures are one-line errors too
        with pytest.raises(ConfigError, match="tracker"):
            load_config(None, [bad])


def test_bad_config_key_on_the_command_line_is_one_line_error(tmp_path, mbavo):
    seq = make_tum(tmp_path / "seq")
    for args, key in ((["--set", "tracker.bogus=1"], "tracker.bogus"), (["--set", "tracker.huber=-1"], "tracker.huber"),
                      (["--config", tmp_path / "none.yaml"], "none.yaml")):
        r = mbavo("track", seq, "--out", tmp_path / "x", *args)
        assert r.returncode == 1, r
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("mbavo: error:") and key in lines[0], r.stderr
    assert not (tmp_path / "x" / "trajectory.txt").exists()


def test_settings_reference_in_docs_is_generated_from_the_dataclasses():
    """docs/settings.md's reference tables are `mbavo config --markdown`'s current output."""
    import subprocess
    import sys

    r = subprocess.run([sys.executable, str(REPO / "scripts" / "settings_docs.py"), "--check"], capture_output=True, text=True)
    assert r.returncode == 0, "docs/settings.md is stale: run python scripts/settings_docs.py"
