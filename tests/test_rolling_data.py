"""Rolling-shutter data: `mbavo synth --readout-ms`, the curved-path shake, exposure_rows.txt, the
loaders' readout, the per-row endpoint error and `mbavo bench rolling-shutter`."""

from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import yaml

from mbavo_jax.config import SynthConfig
from mbavo_jax.datasets import open_sequence
from mbavo_jax.errors import ConfigError, DataError
from mbavo_jax.evaluation import global_shutter_rows, row_fractions, row_path_error
from mbavo_jax.evaluation.metrics import _along
from mbavo_jax.geometry import quaternion as quat
from mbavo_jax.geometry.camera import PinholeCamera
from mbavo_jax.geometry.pose import Pose
from mbavo_jax.geometry.trajectory import readout_fraction
from mbavo_jax.image import delinearize
from mbavo_jax.io import ExposureRows, read_exposure_rows, read_image_gray, write_exposure_rows
from mbavo_jax.synthetic import camera_path, default_scene, generate_sequence, render_exposure, scene_arrays
from mbavo_jax.synthetic.scene import render_rolling_exposure

from .conftest import make_tum

W, H = 160, 120


def small(**kw) -> SynthConfig:
    """A small strong-blur sequence (160x120) with the given changes."""
    base = dict(exposure_ms=25.0, speed=0.77, rotation_rate=103.0, frames=3, width=W, height=H, subframes=8, seed=1,
                real_textures=False)
    return SynthConfig(**{**base, **kw})


@pytest.fixture(scope="module")
def rolling(tmp_path_factory):
    """A rolling-shutter sequence: 30 ms readout, 25 ms exposure."""
    out = tmp_path_factory.mktemp("rs") / "seq"
    generate_sequence(small(readout_ms=30.0), out, progress=False)
    return out


def _camera(cfg: SynthConfig) -> PinholeCamera:
    f = 525.0 * cfg.width / 640.0
    return PinholeCamera.create(f, f, (cfg.width - 1) / 2, (cfg.height - 1) / 2, cfg.width, cfg.height)


def _u8(img) -> np.ndarray:
    return np.clip(np.round(np.asarray(img) * 255.0), 0, 255).astype(np.uint8)


# ------------------------------------------------------------------------------------ generator


@pytest.mark.slow
def test_readout_zero_renders_as_the_global_shutter_generator(tmp_path):
    """R = 0: each frame is exactly the mean of the sub-frame renders over [t - τ/2, t + τ/2] (the
    generator before rolling shutter), and nothing of a rolling shutter is written."""
    cfg = small(frames=2, noise=0.0, subframes=4)
    generate_sequence(cfg, tmp_path / "s", progress=False)
    arrays, cam = scene_arrays(default_scene(cfg.seed, use_real_textures=False)), _camera(cfg)
    seq = open_sequence(tmp_path / "s")
    for i in range(len(seq)):
        t = 1.0 + i / cfg.fps
        times = jnp.asarray(t + np.linspace(-0.5, 0.5, 4) * 0.025, jnp.float32)
        poses = jax.vmap(lambda s: camera_path(s, cfg.speed, cfg.rotation_rate, cfg.seed))(times)
        mid = camera_path(t, cfg.speed, cfg.rotation_rate, cfg.seed)
        radiance, sharp, _ = render_exposure(arrays, cam, poses, mid, cfg.response_gamma)
        assert np.array_equal((read_image_gray(seq[i].path) * 255).round().astype(np.uint8), _u8(delinearize(radiance, 2.2)))
        np.testing.assert_allclose(seq.exposure_paths[1][i], np.asarray(jax.tree.map(lambda a: a[0], poses).to_vector()), atol=1e-6)
    assert not (tmp_path / "s" / "exposure_rows.txt").exists()
    assert "readout_ms" not in yaml.safe_load((tmp_path / "s" / "camera.yaml").read_text()) and seq.readout_s == 0.0


@pytest.mark.slow
def test_rows_are_rendered_at_their_own_times(tmp_path):
    """Sharp frames (τ = 0) with a 30 ms readout: row v is row v of the global-shutter render at
    t0 + v/(H-1)·R, where t0 = t_mid - R/2."""
    cfg = small(frames=1, noise=0.0, exposure_ms=0.0, subframes=1, readout_ms=30.0)
    generate_sequence(cfg, tmp_path / "s", progress=False)
    image = read_image_gray(open_sequence(tmp_path / "s")[0].path)
    arrays, cam = scene_arrays(default_scene(cfg.seed, use_real_textures=False)), _camera(cfg)
    for v in (0, 37, H - 1):
        T = camera_path(1.0 - 0.015 + 0.030 * v / (H - 1), cfg.speed, cfg.rotation_rate, cfg.seed)
        radiance, _, _ = render_exposure(arrays, cam, jax.tree.map(lambda a: a[None], T), T, cfg.response_gamma)
        row = _u8(delinearize(radiance, 2.2))[v].astype(int)
        assert np.abs((image[v] * 255).round().astype(int) - row).max() <= 1


def _shift(a: np.ndarray, b: np.ndarray, max_shift: int = 16) -> float:
    """Horizontal shift (px, sub-pixel) that best moves band ``b`` onto band ``a`` (SSD over the central columns)."""
    cols = slice(max_shift + 8, a.shape[1] - max_shift - 8)
    cost = np.array([np.mean((a[:, cols] - np.roll(b, k, axis=1)[:, cols]) ** 2) for k in range(-max_shift, max_shift + 1)])
    k = int(np.argmin(cost))
    c0, c1, c2 = cost[k - 1], cost[k], cost[k + 1]
    return k - max_shift + 0.5 * (c0 - c2) / (c0 - 2 * c1 + c2)


@pytest.mark.parametrize("readout", [0.0, 0.030])
def test_a_panning_camera_slants_vertical_edges_by_the_readout(readout):
    """A camera panning at ω rad/s: rows read R later are seen turned by ω·R more, so the shift of
    the bottom rows against the top rows is f·tan(ω·R) at the image centre (none for R = 0)."""
    omega, cam = 2.0, _camera(small())
    arrays = scene_arrays(default_scene(0, use_real_textures=False))
    yaw = lambda t: Pose(quat.exp(jnp.array([0.0, 1.0, 0.0]) * omega * t), jnp.array([0.0, 0.0, -0.5]))
    times = jnp.asarray(readout * np.arange(H) / (H - 1), jnp.float32)
    rolling = np.asarray(render_rolling_exposure(arrays, cam, jax.tree.map(lambda a: a[None], jax.vmap(yaw)(times)), 1.0))
    still = np.asarray(render_exposure(arrays, cam, jax.tree.map(lambda a: a[None], yaw(0.0)), yaw(0.0), 1.0)[0])
    top, bottom = slice(0, 12), slice(H - 12, H)
    slant = _shift(still[bottom], rolling[bottom]) - _shift(still[top], rolling[top])
    expected = float(cam.fx) * np.tan(omega * readout * (H - 12) / (H - 1))  # band centres are (H - 12) rows apart
    assert abs(abs(slant) - expected) < 0.5, (slant, expected)


def test_exposure_rows_agree_with_the_exposure_path(rolling):
    seq = open_sequence(rolling)
    rows, (stamps, starts, ends) = seq.exposure_rows, seq.exposure_paths
    assert np.array_equal(rows.stamps, stamps) and rows.rows.shape == (3, 9)
    assert rows.rows[0, 0] == 0 and rows.rows[0, -1] == H - 1 and np.all(np.diff(rows.rows, axis=1) > 0)
    np.testing.assert_allclose(rows.starts[:, 0], starts, atol=1e-6)  # the first row starts the frame's exposure
    np.testing.assert_allclose(rows.ends[:, -1], ends, atol=1e-6)  # the last row ends it
    assert np.abs(rows.starts[:, -1] - starts).max() > 1e-3  # the last row starts R later
    synth = yaml.safe_load((rolling / "synth.yaml").read_text())
    assert synth["readout_ms"] == 30.0 and synth["exposure_ms"] == 25.0 and len(synth["bend_px"]) == 3


@pytest.mark.slow
def test_shake_bends_the_exposure_path(tmp_path):
    bends = {}
    for shake in (0.0, 1.0):
        generate_sequence(small(frames=2, subframes=2, readout_ms=30.0, shake_deg=shake), tmp_path / str(shake), progress=False)
        bends[shake] = yaml.safe_load((tmp_path / str(shake) / "synth.yaml").read_text())["mean_bend_px"]
    assert bends[1.0] > 1.0 and bends[1.0] > 4 * bends[0.0]


def test_readout_longer_than_a_frame_is_refused(mbavo, tmp_path):
    res = mbavo("synth", "--preset", "strong", "--frames", 1, "--readout-ms", 40, "--out", tmp_path / "s")
    assert res.returncode == 1 and "readout_ms" in res.stderr and "Traceback" not in res.stderr


@pytest.mark.slow
def test_blurring_a_real_clip_with_a_readout(tmp_path, mbavo):
    """synth --from --readout-ms: camera.yaml's readout, rows along the model's per-row paths."""
    src = make_tum(tmp_path / "tum", n=3)
    out = tmp_path / "blurred"
    assert mbavo("synth", "--from", src, "--blur-px", 2, "--subframes", 4, "--readout-ms", 20, "--out", out, "-q").returncode == 0
    seq = open_sequence(out)
    assert seq.readout_s == pytest.approx(0.020)
    rho = readout_fraction(seq.readout_s, float(seq.exposures[0]))
    err = row_path_error(seq.exposure_rows, seq.exposure_paths, seq.camera.as_dict(), rho)
    assert err["reprojection_px"]["max"] < 1e-3  # the truth is the model's per-row path
    assert mbavo("synth", "--from", src, "--readout-ms", 40, "--out", tmp_path / "x", "-q").returncode == 1


# ---------------------------------------------------------------------------------- file formats


def test_exposure_rows_round_trip_and_errors(tmp_path):
    rng = np.random.default_rng(0)
    q = rng.normal(size=(2, 3, 4))
    poses = np.concatenate([rng.normal(size=(2, 3, 3)), q / np.linalg.norm(q, axis=-1, keepdims=True)], -1).astype(np.float32)
    rows = ExposureRows(np.array([1.0, 1.5]), np.array([[0, 5, 9], [0, 5, 9]]), poses, poses[::-1].copy())
    write_exposure_rows(tmp_path / "r.txt", rows)
    back = read_exposure_rows(tmp_path / "r.txt")
    assert np.array_equal(back.rows, rows.rows) and np.array_equal(back.stamps, rows.stamps)
    np.testing.assert_allclose(back.starts, rows.starts, atol=1e-6)
    lines = (tmp_path / "r.txt").read_text().splitlines()
    (tmp_path / "short.txt").write_text("\n".join(lines[:-1]) + "\n")  # the second frame lacks a row
    with pytest.raises(DataError, match="has 2 rows"):
        read_exposure_rows(tmp_path / "short.txt")
    (tmp_path / "order.txt").write_text("\n".join([lines[0], lines[2], lines[1], *lines[3:]]) + "\n")
    with pytest.raises(DataError, match=":3:"):
        read_exposure_rows(tmp_path / "order.txt")


def test_loaders_read_the_readout(rolling, tmp_path, mbavo):
    seq = open_sequence(rolling)
    assert seq.readout_s == pytest.approx(0.030) and seq.meta["readout_ms"] == 30.0
    assert "readout_ms: 30.0" in mbavo("info", rolling).stdout
    folder = tmp_path / "folder"
    folder.mkdir()
    (folder / "a.png").write_bytes((rolling / "rgb" / sorted(p.name for p in (rolling / "rgb").iterdir())[0]).read_bytes())
    (folder / "camera.yaml").write_text(f"fx: 131.25\nfy: 131.25\ncx: 79.5\ncy: 59.5\nwidth: {W}\nheight: {H}\nreadout_ms: 12.5\n")
    assert open_sequence(folder).readout_s == pytest.approx(0.0125)
    (folder / "camera.yaml").write_text(f"fx: 131.25\nfy: 131.25\ncx: 79.5\ncy: 59.5\nwidth: {W}\nheight: {H}\nreadout_ms: -1\n")
    with pytest.raises(DataError, match="readout_ms"):
        open_sequence(folder)


def test_hidden_exposure_copy_keeps_the_readout(rolling, tmp_path):
    from mbavo_jax.synthetic import exposure_hidden_copy

    hidden = open_sequence(exposure_hidden_copy(rolling, tmp_path / "hidden"))
    assert hidden.exposures is None and hidden.readout_s == pytest.approx(0.030)
    assert hidden.exposure_rows is not None and np.array_equal(hidden.exposure_rows.starts, open_sequence(rolling).exposure_rows.starts)


# ---------------------------------------------------------------------------------- evaluation


def _linear_truth(rho: float, height: int = H) -> tuple[ExposureRows, tuple]:
    """Two frames moving along straight paths, their per-row truth for readout fraction ``rho``."""
    start = np.array([[0.0, 0.0, 0.0, 0, 0, 0, 1], [0.1, 0.0, 0.0, 0, 0.0499792, 0, 0.9987503]])
    end = start + np.array([0.03, 0.01, 0.0, 0, 0, 0, 0])
    end[:, 3:] = [[0.0, 0.0499792, 0.0, 0.9987503], [0.0, 0.0998334, 0.0, 0.9950042]]
    rows = np.array([0, 30, 60, 90, height - 1])
    s = row_fractions(rows, height, rho)
    per = lambda i, j: _along(start[i], end[i], s[:, j])
    truth = ExposureRows(np.array([1.0, 2.0]), np.tile(rows, (2, 1)), np.stack([per(0, 0), per(1, 0)]), np.stack([per(0, 1), per(1, 1)]))
    return truth, (truth.stamps, start, end)


@pytest.mark.slow
def test_row_error_is_zero_for_the_true_path_and_not_for_a_global_shutter_estimate(x64):
    cam = _camera(small()).as_dict()
    truth, path = _linear_truth(0.5)
    assert row_path_error(truth, path, cam, readout=0.5)["reprojection_px"]["max"] < 1e-9
    gs = row_path_error(truth, path, cam, readout=0.0)
    assert gs["reprojection_px"]["mean"] > 1.0 and len(gs["per_row_px"]) == 5
    flat = row_path_error(global_shutter_rows(path, H, rows=5), path, cam, readout=0.0)  # a global shutter's truth
    assert flat["reprojection_px"]["max"] < 1e-9


def test_row_error_on_generated_rolling_data(rolling):
    seq = open_sequence(rolling)
    cam = seq.camera.as_dict()
    rho = readout_fraction(seq.readout_s, float(seq.exposures[0]))
    rs = row_path_error(seq.exposure_rows, seq.exposure_paths, cam, rho)["reprojection_px"]["mean"]
    gs = row_path_error(seq.exposure_rows, seq.exposure_paths, cam, 0.0)["reprojection_px"]["mean"]
    assert rs < 0.5 and gs > 4 * rs  # the true path's straight chord: only its bend is left


def test_eval_exposure_reports_rows_when_present(rolling, mbavo):
    exp, cam = rolling / "exposure.txt", rolling / "camera.yaml"
    res = mbavo("eval", "exposure", exp, exp, "--camera", cam, "--readout-ms", 30, "--format", "json")
    assert res.returncode == 0
    out = json.loads(res.stdout)
    assert out["rows"] == 9 and out["readout_fraction"] == pytest.approx(30 / 55) and out["row_reprojection_px"]["mean"] < 0.5
    gs = json.loads(mbavo("eval", "exposure", exp, exp, "--camera", cam, "--format", "json").stdout)
    assert gs["row_reprojection_px"]["mean"] > 4 * out["row_reprojection_px"]["mean"]


# ---------------------------------------------------------------------------------- benchmark


def test_bench_rejects_unknown_methods_and_presets(mbavo, tmp_path):
    res = mbavo("bench", "rolling-shutter", "--methods", "rs,nope", "--out", tmp_path)
    assert res.returncode == 1 and "nope" in res.stderr
    res = mbavo("bench", "rolling-shutter", "--presets", "hard", "--out", tmp_path)
    assert res.returncode == 1 and "hard" in res.stderr


def test_rolling_sequences_cover_presets_readouts_and_shake():
    from mbavo_jax.bench.rolling import ROLLING_DEFAULTS, rolling_sequences
    from mbavo_jax.config import BenchConfig

    seqs = rolling_sequences(BenchConfig(**{**ROLLING_DEFAULTS, "readouts": "0,15,30", "shake_deg": 0.5}))
    assert [s.name for s in seqs][:3] == ["strong_ro0", "strong_ro15", "strong_ro30"] and len(seqs) == 12
    assert {s.synth.shake_deg for s in seqs if s.name.endswith("_shake")} == {0.5}
    assert seqs[2].synth.readout_ms == 30.0 and seqs[2].synth.exposure_ms == 25.0


@pytest.mark.slow
def test_bench_rolling_shutter_end_to_end(mbavo, tmp_path):
    out = tmp_path / "bench"
    args = ("bench", "rolling-shutter", "--frames", 3, "--width", W, "--height", H, "--presets", "strong", "--readouts", "30",
            "--shake-deg", 0, "--methods", "rs,blur", "--out", out, "-q")
    res = mbavo(*args)
    assert res.returncode == 0, res.stderr
    results = json.loads((out / "results.json").read_text())
    seq = results["sequences"]["strong_ro30"]
    assert seq["readout_ms"] == 30.0 and set(seq["methods"]) == {"rs", "blur"}
    rs, blur = seq["methods"]["rs"], seq["methods"]["blur"]
    assert rs["model_readout_fraction"] == pytest.approx(30 / 55) and blur["model_readout_fraction"] == 0.0
    assert np.isfinite(rs["ate_rmse_m"]) and np.isfinite(rs["row_endpoint_px"]) and len(rs["per_row_px"]) == 9
    assert "strong_ro30" in results["cost"]["rs_over_blur_track_ms"]
    side = results["cost"]["side_by_side"]["strong_ro30"]
    assert side["rs"]["lm_steps"] >= 1 and np.isfinite(side["call_ratio"]) and np.isfinite(side["step_ratio"])
    table = (out / "table.md").read_text()
    assert table.startswith("| sequence |") and "| strong_ro30 | 30 |" in table and "rs / blur" in table
    mtime = (out / "data" / "strong_ro30" / "rgb.txt").stat().st_mtime_ns
    assert mbavo(*args[:-5], "--methods", "blur", "--out", out, "-q").returncode == 0  # the sequence is reused
    assert (out / "data" / "strong_ro30" / "rgb.txt").stat().st_mtime_ns == mtime


def test_row_error_leaves_out_frames_the_tracker_did_not_estimate(tmp_path):
    from mbavo_jax.bench.rolling import _tracked_only

    (tmp_path / "frames.csv").write_text("index,timestamp,status\n0,1.000000,keyframe\n1,1.033333,converged\n"
                                         "2,1.066667,lost\n3,1.100000,max_steps\n")
    stamps = np.array([1.0, 1.033333, 1.066667, 1.1])
    kept = _tracked_only((stamps, np.arange(4.0), np.arange(4.0) + 10), tmp_path)
    assert kept[0].tolist() == [1.033333, 1.1] and kept[1].tolist() == [1.0, 3.0] and kept[2].tolist() == [11.0, 13.0]
