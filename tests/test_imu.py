"""The simulated IMU (``mbavo synth --imu``), the IMU loaders and on-manifold preintegration
(Forster et al. TRO 2017): truth, Jacobians against autodiff, covariance against Monte Carlo, noise
statistics, file round trips and malformed files."""

from __future__ import annotations

import dataclasses
import math

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.config import PRESETS, SynthConfig
from mbavo_jax.datasets import open_sequence
from mbavo_jax.errors import DataError
from mbavo_jax.imu import EUROC_ADIS16448, NavState, correct, preintegrate, residual, residual_jacobians, window
from mbavo_jax.imu.preintegration import so3_exp, so3_log
from mbavo_jax.synthetic.imu import GRAVITY_WORLD, extrinsics, imu_truth, read_imu_groundtruth, simulate_imu

from .conftest import run_cli

CFG = SynthConfig(**{**PRESETS["strong"], "imu": True})  # 103 deg/s peak rotation, 0.77 m/s peak speed
RATE = 200.0
TI, TJ = 1.0 + 1 / 30, 1.0 + 2 / 30  # two frame times (mid-exposure) at 30 fps: between IMU samples
EXPOSURE = (TJ - 0.0125, TJ + 0.0125)  # frame j's 25 ms exposure


@pytest.fixture(scope="module")
def truth():
    """Noise-free samples at 200 Hz over 0.95-1.25 s (camera clock = IMU clock) and the true IMU
    states at the frame times and the exposure's ends, as float64 numpy."""
    stamps, ends = np.arange(190, 250) / RATE, (TI, TJ, *EXPOSURE)
    tr = imu_truth(np.concatenate([stamps, ends]), CFG, extrinsics(CFG))
    pick = lambda s: type(tr)(*(x[s] for x in dataclasses.astuple(tr)))
    return stamps, pick(slice(0, len(stamps))), {t: pick(slice(len(stamps) + i, len(stamps) + i + 1)) for i, t in enumerate(ends)}


def _f64(*xs):
    return [jnp.asarray(x, jnp.float64) for x in xs]


def _state(tr, bias=np.zeros(6)) -> NavState:
    """The IMU's state (its float32 rotation made orthonormal in float64: the analytic Jacobians assume it)."""
    R, v, p, bg, ba = _f64(tr.R[0], tr.v[0], tr.p[0], bias[:3], bias[3:])
    return NavState(so3_exp(so3_log(R)), v, p, bg, ba)


def _pre(truth, t0, t1, bias=np.zeros(6), gyro=None, accel=None):
    stamps, tr, _ = truth
    g = tr.gyro if gyro is None else gyro
    a = tr.accel if accel is None else accel
    return preintegrate(*_f64(stamps, g, a), t0, t1, *_f64(bias[:3], bias[3:]), EUROC_ADIS16448)


@pytest.mark.parametrize("t0, t1", [(TI, TJ), EXPOSURE], ids=["frame-to-frame", "within-exposure"])
def test_noise_free_preintegration_reproduces_the_true_motion(truth, x64, t0, t1):
    """Integration error of the midpoint rule at 200 Hz over 25-33 ms: measured 5e-7 rad (the
    float32 path), 1.4e-6 m/s, 5e-8 m; the tolerances (2e-6 rad, 1e-5 m/s, 3e-7 m) are at least 10x
    below the ADIS16448's noise on the increment (σ from the covariance: 2.7e-5 rad, 3.2e-4 m/s,
    4.5e-6 m over the 25 ms exposure).
    Forster's hold of ΔR over an interval is off by 6.5e-4 m/s here; no gravity term, by 0.33 m/s."""
    si, sj = truth[2][t0], truth[2][t1]
    pre = _pre(truth, t0, t1)
    dt = t1 - t0
    assert float(pre.dt) == pytest.approx(dt, abs=1e-12)
    dR = si.R[0].T @ sj.R[0]
    dv = si.R[0].T @ (sj.v[0] - si.v[0] - GRAVITY_WORLD * dt)
    dp = si.R[0].T @ (sj.p[0] - si.p[0] - si.v[0] * dt - 0.5 * GRAVITY_WORLD * dt * dt)
    assert np.linalg.norm(so3_log(jnp.asarray(dR.T) @ pre.delta_R)) < 2e-6
    assert np.abs(np.asarray(pre.delta_v) - dv).max() < 1e-5
    assert np.abs(np.asarray(pre.delta_p) - dp).max() < 3e-7
    r = jax.jit(residual)(pre, _state(si), _state(sj), jnp.asarray(GRAVITY_WORLD))  # Eq. 45 vanishes at the truth
    assert np.abs(np.asarray(r)).max() < 1e-5
    sigma = np.sqrt(np.diag(np.asarray(pre.covariance)))
    assert sigma[0] > 10 * 2e-6 and sigma[3] > 10 * 1e-5 and sigma[6] > 10 * 3e-7


def test_window_pads_to_a_fixed_shape(truth, x64):
    """A padded window gives the result of the exact samples, at any padding."""
    from mbavo_jax.imu import ImuData

    stamps, tr, _ = truth
    imu = ImuData(stamps + 0.002, tr.gyro, tr.accel, np.eye(4), EUROC_ADIS16448, RATE, 0.002)  # IMU clock 2 ms ahead
    exact = _pre(truth, TI, TJ)
    for size in (9, 16):
        w = window(imu, TI, TJ, size)
        assert w.t.shape == (size,) and w.valid.sum() == 9
        pre = preintegrate(*_f64(w.t, w.gyro, w.accel), 0.0, w.span, *_f64(np.zeros(3), np.zeros(3)), EUROC_ADIS16448,
                           valid=jnp.asarray(w.valid))
        np.testing.assert_allclose(np.asarray(pre.delta_v), np.asarray(exact.delta_v), atol=1e-9)
        np.testing.assert_allclose(np.asarray(pre.covariance), np.asarray(exact.covariance), rtol=1e-6, atol=1e-18)
    with pytest.raises(Exception, match="more than the window's 8"):
        window(imu, TI, TJ, 8)


def test_bias_jacobians_match_autodiff(truth, x64):
    """∂(Log(ΔR̄ᵀΔR), Δv, Δp)/∂(b_g, b_a) by jax.jacfwd of preintegrate against the Appendix B
    recursions, at biases away from 0; and Eq. 44's correction is first order (error ∝ |δb|²)."""
    b0 = np.array([0.01, -0.02, 0.015, 0.1, -0.05, 0.08])
    pre = _pre(truth, TI, TJ, b0)

    def increments(b):
        p = preintegrate(*_f64(truth[0], truth[1].gyro, truth[1].accel), TI, TJ, b[:3], b[3:], EUROC_ADIS16448)
        return jnp.concatenate([so3_log(pre.delta_R.T @ p.delta_R), p.delta_v, p.delta_p])

    J = np.asarray(jax.jit(jax.jacfwd(increments))(jnp.asarray(b0)))
    z = np.zeros((3, 3))
    expected = np.block([[np.asarray(pre.dR_dbg), z], [np.asarray(pre.dv_dbg), np.asarray(pre.dv_dba)],
                         [np.asarray(pre.dp_dbg), np.asarray(pre.dp_dba)]])
    np.testing.assert_allclose(J, expected, rtol=1e-7, atol=1e-12)
    errors = []
    for scale in (1e-2, 1e-3):
        db = scale * np.array([1.0, -2.0, 1.5, 3.0, 1.0, -2.0])
        c, exact = correct(pre, *_f64(b0[:3] + db[:3], b0[3:] + db[3:])), _pre(truth, TI, TJ, b0 + db)
        errors.append([float(np.linalg.norm(so3_log(exact.delta_R.T @ c.delta_R))),
                       float(np.abs(np.asarray(c.delta_v) - np.asarray(exact.delta_v)).max()),
                       float(np.abs(np.asarray(c.delta_p) - np.asarray(exact.delta_p)).max())])
    assert np.all(np.array(errors[1]) < np.array(errors[0]) / 50), errors  # second order: 100x smaller for a 10x smaller step


def _moved(s: NavState, d) -> NavState:
    """The local move [δφ, δv, δp, δb_g, δb_a] of residual_jacobians."""
    return NavState(s.R @ so3_exp(d[:3]), s.v + d[3:6], s.p + s.R @ d[6:9], s.bias_g + d[9:12], s.bias_a + d[12:15])


def test_residual_jacobians_match_autodiff(truth, x64):
    rng = np.random.default_rng(3)
    pre = _pre(truth, TI, TJ, np.array([0.01, 0.0, -0.01, 0.05, 0.02, -0.03]))
    g = jnp.asarray(GRAVITY_WORLD)
    off = lambda s, scale: _moved(s, jnp.asarray(rng.normal(size=15) * scale))
    si = off(_state(truth[2][TI]), [0.05] * 3 + [0.1] * 6 + [0.01] * 3 + [0.05] * 3)
    sj = off(_state(truth[2][TJ]), [0.05] * 3 + [0.1] * 6 + [0.0] * 6)
    J = jax.jit(residual_jacobians)(pre, si, sj, g)
    J_auto = jax.jit(jax.jacfwd(lambda d: residual(pre, _moved(si, d[0]), _moved(sj, d[1]), g)))(jnp.zeros((2, 15)))
    Ji, Jj = J_auto[:, 0], J_auto[:, 1]
    np.testing.assert_allclose(np.asarray(J.i), np.asarray(Ji), rtol=1e-7, atol=1e-10)
    np.testing.assert_allclose(np.asarray(J.j), np.asarray(Jj), rtol=1e-7, atol=1e-10)


def test_covariance_matches_monte_carlo(truth, x64):
    """400 draws of the ADIS16448's white noise (σ_c/√Δt per sample, Kalibr) on the noise-free
    samples: the spread of the increments against the propagated covariance (Eqs. 62-63). Measured:
    variance ratios 0.88-1.03, mean Mahalanobis² 8.19 (9 expected; the interval means average
    neighbouring samples' noise, so the draws spread a little less than the continuous model says)."""
    stamps, tr, _ = truth
    sg, sa = EUROC_ADIS16448.white(1.0 / RATE)
    draws = 400
    noise = np.random.default_rng(0).normal(size=(draws, len(stamps), 6)) * np.repeat([sg, sa], 3)
    pre0 = _pre(truth, TI, TJ)
    one = lambda n: _pre(truth, TI, TJ, gyro=tr.gyro + n[:, :3], accel=tr.accel + n[:, 3:])

    def error(n):
        p = one(n)
        return jnp.concatenate([so3_log(pre0.delta_R.T @ p.delta_R), p.delta_v - pre0.delta_v, p.delta_p - pre0.delta_p])

    e = np.asarray(jax.vmap(error)(jnp.asarray(noise)))
    cov = np.asarray(pre0.covariance)
    ratio = e.var(axis=0) / np.diag(cov)
    assert np.all((ratio > 0.75) & (ratio < 1.3)), ratio
    mahalanobis = np.einsum("ni,ij,nj->n", e, np.linalg.inv(cov), e)  # chi-square, 9 dof: mean 9
    assert 7.5 < mahalanobis.mean() < 10.5, mahalanobis.mean()


def test_simulated_noise_statistics():
    """gyro/accel minus truth minus the true biases: white with σ_c/√Δt (Kalibr's discrete model);
    the biases' steps: σ_bc·√Δt; the IMU clock t_imu = t_cam + offset. 3000 samples: 5 % tolerance
    is 4 standard errors of a sample std."""
    cfg = SynthConfig(**{**PRESETS["strong"], "imu": True, "imu_time_offset_ms": 3.0})
    imu, biases = simulate_imu(cfg, 1.0, 16.0)
    assert len(imu) == 3000 and imu.timestamps[0] == 1.005 and imu.time_offset_s == 0.003  # IMU clock: 1.003 to 16.003 s
    tr = imu_truth(imu.timestamps - 0.003, cfg, imu.T_cam_imu)
    white = np.concatenate([imu.gyro - tr.gyro, imu.accel - tr.accel], axis=1) - biases
    dt = 1.0 / cfg.imu_rate_hz
    sigma = np.repeat([cfg.imu_gyro_noise / math.sqrt(dt), cfg.imu_accel_noise / math.sqrt(dt)], 3)
    np.testing.assert_allclose(white.std(axis=0) / sigma, 1.0, atol=0.05)
    assert np.all(np.abs(white.mean(axis=0)) < 5 * sigma / math.sqrt(len(imu)))
    walk = np.repeat([cfg.imu_gyro_walk * math.sqrt(dt), cfg.imu_accel_walk * math.sqrt(dt)], 3)
    np.testing.assert_allclose(np.diff(biases, axis=0).std(axis=0) / walk, 1.0, atol=0.05)


@pytest.fixture(scope="module")
def synth_imu(tmp_path_factory):
    out = tmp_path_factory.mktemp("imu") / "seq"
    assert run_cli("synth", "--preset", "strong", "--frames", 2, "--width", 32, "--height", 24, "--subframes", 2,
                   "--no-real-textures", "--imu", "--imu-time-offset-ms", 2.5, "--out", out, "-q") == 0
    return out


@pytest.mark.slow
def test_synth_imu_round_trips_through_the_loader(synth_imu):
    cfg = SynthConfig(**{**PRESETS["strong"], "frames": 2, "width": 32, "height": 24, "subframes": 2, "real_textures": False,
                         "imu": True, "imu_time_offset_ms": 2.5})
    seq = open_sequence(synth_imu)
    imu = seq.imu
    assert (synth_imu / "imu.txt").read_text().startswith("# timestamp gx gy gz ax ay az")
    assert imu.rate_hz == 200.0 and imu.time_offset_s == 0.0025 and imu.noise == EUROC_ADIS16448
    np.testing.assert_allclose(imu.T_cam_imu, extrinsics(cfg), atol=1e-12)
    assert imu.camera_times()[0] < seq.timestamps[0] - 0.5 and imu.camera_times()[-1] > seq.timestamps[-1] + 0.5
    expected, biases = simulate_imu(cfg, seq.timestamps[0] - 0.5125, seq.timestamps[-1] + 0.5125)
    np.testing.assert_allclose(imu.timestamps, expected.timestamps, atol=1e-9)
    np.testing.assert_allclose(imu.gyro, expected.gyro, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(imu.accel, expected.accel, rtol=1e-8, atol=1e-12)
    stamps, true_biases = read_imu_groundtruth(synth_imu / "imu_groundtruth.txt")
    np.testing.assert_allclose(true_biases, biases, rtol=1e-8, atol=1e-12)
    assert window(imu, seq.timestamps[0], seq.timestamps[1], 10).valid.sum() == 9  # 0.9975 to 1.0375 s, camera clock


H, W = 24, 32


def _euroc(root, imu_rows=None, imu_yaml=None):
    """A minimal EuRoC folder: 2 frames, the camera 0.1 m along the body's x; the IMU turned 90° about z."""
    cam = root / "mav0" / "cam0"
    (cam / "data").mkdir(parents=True)
    names = [f"{1403636579763555584 + i * 50000000}" for i in range(2)]
    for n in names:
        cv2.imwrite(str(cam / "data" / f"{n}.png"), np.full((H, W), 50, np.uint8))
    (cam / "data.csv").write_text("#timestamp [ns],filename\n" + "".join(f"{n},{n}.png\n" for n in names))
    (cam / "sensor.yaml").write_text("%YAML:1.0\nT_BS:\n  cols: 4\n  rows: 4\n  data: [1,0,0,0.1, 0,1,0,0, 0,0,1,0, 0,0,0,1]\n"
                                     f"resolution: [{W}, {H}]\nintrinsics: [30.0, 31.0, 15.5, 11.5]\n")
    imu = root / "mav0" / "imu0"
    imu.mkdir()
    rows = imu_rows if imu_rows is not None else [f"{1403636579758555648 + k * 5000000},0.1,0.2,0.3,9.7,0.1,-0.2" for k in range(25)]
    (imu / "data.csv").write_text("#timestamp [ns],w_RS_S_x [rad s^-1],w_RS_S_y [rad s^-1],w_RS_S_z [rad s^-1],"
                                  "a_RS_S_x [m s^-2],a_RS_S_y [m s^-2],a_RS_S_z [m s^-2]\n" + "\n".join(rows) + "\n")
    (imu / "sensor.yaml").write_text(imu_yaml if imu_yaml is not None else
                                     "%YAML:1.0\nsensor_type: imu\nT_BS:\n  cols: 4\n  rows: 4\n  data: [0,-1,0,0, 1,0,0,0, 0,0,1,0.05, 0,0,0,1]\n"
                                     "rate_hz: 200\ngyroscope_noise_density: 1.6968e-04\ngyroscope_random_walk: 1.9393e-05\n"
                                     "accelerometer_noise_density: 2.0000e-3\naccelerometer_random_walk: 3.0000e-3\n")
    return root


def test_euroc_imu(tmp_path):
    seq = open_sequence(_euroc(tmp_path / "euroc"))
    imu = seq.imu
    assert len(imu) == 25 and imu.noise == EUROC_ADIS16448 and imu.rate_hz == 200.0
    np.testing.assert_allclose(np.diff(imu.timestamps), 0.005, atol=1e-6)
    np.testing.assert_allclose(imu.gyro[3], [0.1, 0.2, 0.3]) and np.testing.assert_allclose(imu.accel[3], [9.7, 0.1, -0.2])
    expected = np.array([[0, -1, 0, -0.1], [1, 0, 0, 0], [0, 0, 1, 0.05], [0, 0, 0, 1]])  # inv(T_BS_cam) @ T_BS_imu
    np.testing.assert_allclose(imu.T_cam_imu, expected, atol=1e-12)


def _tum(root, imu_txt: str | None, block: str | None):
    """A minimal TUM folder (1 frame) with camera.yaml's imu block and imu.txt as given."""
    root.mkdir(parents=True)
    cv2.imwrite(str(root / "0.png"), np.zeros((H, W), np.uint8))
    (root / "rgb.txt").write_text("1.0 0.png\n")
    (root / "camera.yaml").write_text(f"fx: 30\nfy: 30\ncx: 15\ncy: 11\nwidth: {W}\nheight: {H}\n" + (block or ""))
    if imu_txt is not None:
        (root / "imu.txt").write_text(imu_txt)
    return root


BLOCK = ("imu:\n  T_cam_imu: [[1, 0, 0, 0.1], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]\n  rate_hz: 200\n  time_offset_s: 0.0\n"
         "  gyroscope_noise_density: 1.6968e-4\n  gyroscope_random_walk: 1.9393e-5\n"
         "  accelerometer_noise_density: 2.0e-3\n  accelerometer_random_walk: 3.0e-3\n")
GOOD = "# timestamp gx gy gz ax ay az\n0.995 0 0 0 0 9.81 0\n1.0 0 0 0 0 9.81 0\n1.005 0 0 0 0 9.81 0\n"


@pytest.mark.parametrize("where, imu_txt, block, message", [
    ("imu.txt:3", GOOD.replace("1.0 0 0 0 0 9.81 0", "1.0 0 0 0 9.81 0"), BLOCK, "expected 7 columns, found 6"),
    ("imu.txt:4", GOOD.replace("1.005 0 0 0", "1.005 nan 0 0"), BLOCK, "non-finite value"),
    ("imu.txt:4", GOOD.replace("1.005", "0.999"), BLOCK, "decreasing timestamp 0.999"),
    ("imu.txt:3", GOOD.replace("1.0 0", "0.995 0"), BLOCK, "duplicate timestamp"),
    ("imu.txt", None, BLOCK, "IMU file not found"),
    ("camera.yaml", GOOD, None, "has no 'imu:' block"),
    ("camera.yaml", GOOD, BLOCK.replace("  gyroscope_random_walk: 1.9393e-5\n", ""), "missing 'gyroscope_random_walk'"),
    ("camera.yaml", GOOD, BLOCK.replace("[1, 0, 0, 0.1]", "[2, 0, 0, 0.1]"), "is not a rigid transform"),
    ("camera.yaml", GOOD, BLOCK.replace("rate_hz: 200", "rate_hz: -1"), "'rate_hz' must be > 0"),
])
def test_malformed_imu_files(tmp_path, where, imu_txt, block, message):
    root = _tum(tmp_path / "seq", imu_txt, block)
    with pytest.raises(DataError) as info:
        open_sequence(root)
    text = str(info.value)
    assert "\n" not in text and text.startswith(str(root / where.split(":")[0])) and message in text, text
    assert (where.split(":")[1] if ":" in where else "") in text.split(": ")[0]


def test_our_layout_round_trip_and_euroc_errors(tmp_path):
    imu = open_sequence(_tum(tmp_path / "ok", GOOD, BLOCK)).imu
    assert len(imu) == 3 and imu.T_cam_imu[0, 3] == 0.1 and imu.accel[1, 1] == 9.81
    assert open_sequence(_tum(tmp_path / "none", None, None)).imu is None
    rows = [f"{1403636579758555648 + k * 5000000},0.1,0.2,0.3,9.7,0.1" for k in range(3)]
    with pytest.raises(DataError, match=r"imu0/data.csv:2: expected 7 columns .* found 6"):
        open_sequence(_euroc(tmp_path / "e1", imu_rows=rows))
    rows = [f"{1403636579758555648 - k * 5000000},0.1,0.2,0.3,9.7,0.1,0" for k in range(3)]
    with pytest.raises(DataError, match=r"imu0/data.csv:3: decreasing timestamp"):
        open_sequence(_euroc(tmp_path / "e2", imu_rows=rows))
    with pytest.raises(DataError, match=r"imu0/sensor.yaml: sensor.yaml is missing 'accelerometer_random_walk'"):
        open_sequence(_euroc(tmp_path / "e3", imu_yaml="rate_hz: 200\ngyroscope_noise_density: 1\ngyroscope_random_walk: 1\n"
                                                       "accelerometer_noise_density: 1\n"))
