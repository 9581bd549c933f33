"""A simulated IMU along the generator's camera path (``mbavo synth --imu``).

The path (:func:`~mbavo_jax.synthetic.generator.camera_path`) is a closed form, so its derivatives
are exact: ``jax.jacfwd`` of it in t. With T_world_imu = T_world_cam · T_cam_imu,

    gyro  = R_ci^T ω_c,  [ω_c]× = R_wcᵀ Ṙ_wc                  (angular velocity in the IMU frame)
    accel = R_wbᵀ (p̈_wb − g_w),  p_wb = p_wc + R_wc t_ci       (specific force in the IMU frame)

Gravity: the generator's world has y pointing down (the camera at rest looks along +z with the
image's rows along +y), so g_w = (0, +9.81, 0) there (:data:`GRAVITY_WORLD`); in the z-up world W
with x_W = x, y_W = z, z_W = −y it is (0, 0, −9.81).

Noise (Kalibr's IMU noise model): per-sample white noise σ_c/√Δt and bias random-walk steps
σ_bc·√Δt at the sample period Δt; the initial biases are drawn per axis with std
``imu_gyro_bias`` and ``imu_accel_bias``. Samples are stamped on the IMU clock, t_imu = t_cam +
``imu_time_offset_ms``; a seed of their own, so the images are the same with or without the IMU.
"""

from __future__ import annotations

import dataclasses
import math
import pathlib

import jax
import jax.numpy as jnp
import numpy as np

from ..config import SynthConfig
from ..datasets.imu import write_imu_txt
from ..geometry import quaternion as quat
from ..imu.data import ImuData, ImuNoise
from ..io import read_table
from .path import camera_path

__all__ = ["GRAVITY_WORLD", "IMU_GROUNDTRUTH", "ImuTruth", "imu_truth", "simulate_imu", "extrinsics", "write_imu", "read_imu_groundtruth"]

GRAVITY_WORLD = np.array([0.0, 9.81, 0.0])  # the generator's world: y points down
IMU_GROUNDTRUTH = "imu_groundtruth.txt"  # the true biases at each sample


@dataclasses.dataclass(frozen=True)
class ImuTruth:
    """The noise-free IMU at M times: ``gyro``, ``accel`` (M, 3) in the IMU frame, and the IMU's
    ``R`` (M, 3, 3), ``v``, ``p`` (M, 3) in the generator's world (world-from-IMU)."""

    gyro: np.ndarray
    accel: np.ndarray
    R: np.ndarray
    v: np.ndarray
    p: np.ndarray


def extrinsics(cfg: SynthConfig) -> np.ndarray:
    """T_cam_imu (4, 4) of ``cfg.imu_extrinsics``."""
    v = cfg.imu_pose()
    T = np.eye(4)
    T[:3, :3] = np.asarray(quat.to_matrix(jnp.asarray(v[3:], jnp.float32)), np.float64)
    T[:3, 3] = v[:3]
    return T


def _truth_at(t, cfg: SynthConfig, T_cam_imu):
    """gyro, accel, R_wb, v_wb, p_wb at camera time ``t`` (a float32 scalar)."""
    R_ci, t_ci = jnp.asarray(T_cam_imu[:3, :3], jnp.float32), jnp.asarray(T_cam_imu[:3, 3], jnp.float32)
    g = jnp.asarray(GRAVITY_WORLD, jnp.float32)

    def pose(s):
        T = camera_path(s, cfg.speed, cfg.rotation_rate, cfg.seed, cfg.shake_deg, cfg.shake_hz)
        R_wc = quat.to_matrix(T.q)
        return R_wc, T.t + R_wc @ t_ci

    R_wc, p = pose(t)
    dR, v = jax.jacfwd(pose)(t)
    a = jax.jacfwd(jax.jacfwd(lambda s: pose(s)[1]))(t)
    W = R_wc.T @ dR
    omega_c = 0.5 * jnp.stack([W[2, 1] - W[1, 2], W[0, 2] - W[2, 0], W[1, 0] - W[0, 1]])
    R_wb = R_wc @ R_ci
    return R_ci.T @ omega_c, R_wb.T @ (a - g), R_wb, v, p


def imu_truth(times, cfg: SynthConfig, T_cam_imu: np.ndarray) -> ImuTruth:
    """The noise-free IMU of ``cfg``'s path at camera-clock ``times`` (M,) with ``T_cam_imu``."""
    fn = jax.jit(jax.vmap(lambda t: _truth_at(t, cfg, T_cam_imu)))
    out = [np.asarray(x, np.float64) for x in fn(jnp.asarray(times, jnp.float32))]
    return ImuTruth(*out)


def simulate_imu(cfg: SynthConfig, t_begin: float, t_end: float) -> tuple[ImuData, np.ndarray]:
    """The noisy IMU of ``cfg`` sampled at ``cfg.imu_rate_hz`` on the IMU clock over camera times
    [t_begin, t_end], and its true biases (M, 6) [b_g, b_a] at each sample."""
    rate, offset = cfg.imu_rate_hz, cfg.imu_time_offset_ms / 1000.0
    stamps = np.arange(math.ceil((t_begin + offset) * rate), math.floor((t_end + offset) * rate) + 1) / rate
    T = extrinsics(cfg)
    truth = imu_truth(stamps - offset, cfg, T)
    noise = ImuNoise(cfg.imu_gyro_noise, cfg.imu_gyro_walk, cfg.imu_accel_noise, cfg.imu_accel_walk)
    rng = np.random.default_rng(cfg.seed + 2000)
    per_axis = lambda g, a: np.repeat([g, a], 3)
    b0 = rng.normal(size=6) * per_axis(cfg.imu_gyro_bias, cfg.imu_accel_bias)
    steps = rng.normal(size=(len(stamps), 6)) * per_axis(*noise.walk(1.0 / rate))
    steps[0] = 0.0
    biases = b0 + np.cumsum(steps, axis=0)
    white = rng.normal(size=(len(stamps), 6)) * per_axis(*noise.white(1.0 / rate))
    meas = np.concatenate([truth.gyro, truth.accel], axis=1) + biases + white
    return ImuData(stamps, meas[:, :3], meas[:, 3:], T, noise, rate, offset), biases


def write_imu(out, cfg: SynthConfig, t_begin: float, t_end: float) -> ImuData:
    """Simulate the IMU over camera times [t_begin, t_end]; write imu.txt and imu_groundtruth.txt
    (``timestamp bgx bgy bgz bax bay baz``, the true biases) into ``out``."""
    imu, biases = simulate_imu(cfg, t_begin, t_end)
    out = pathlib.Path(out)
    write_imu_txt(out / "imu.txt", imu)
    with open(out / IMU_GROUNDTRUTH, "w") as fh:
        fh.write("# timestamp bgx bgy bgz bax bay baz (true biases, rad/s and m/s^2; IMU clock; "
                 f"gravity in the generator's world (y down): {GRAVITY_WORLD.tolist()} m/s^2)\n")
        fh.writelines(f"{t:.9f} " + " ".join(f"{x:.9e}" for x in b) + "\n" for t, b in zip(imu.timestamps, biases))
    return imu


def read_imu_groundtruth(path) -> tuple[np.ndarray, np.ndarray]:
    """(timestamps (M,), true biases (M, 6)) of an imu_groundtruth.txt."""
    arr = np.asarray([v for _, v in read_table(path, 7, "IMU ground truth")], np.float64)
    return arr[:, 0], arr[:, 1:]
