"""IMU measurements as loaded from a sequence, their noise figures and fixed-size windows of samples.

Units are SI: gyroscope rad/s, accelerometer m/s² (specific force), timestamps s on the IMU's clock.
``time_offset_s`` is Kalibr's ``timeshift_cam_imu``: t_imu = t_cam + time_offset_s, so a sample
stamped t was taken at camera time t − time_offset_s. ``T_cam_imu`` maps IMU-frame points into the
camera frame (the project's ``T_a_b`` convention).
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import ArgumentError

__all__ = ["ImuNoise", "ImuData", "ImuWindow", "window", "EUROC_ADIS16448"]


@dataclasses.dataclass(frozen=True)
class ImuNoise:
    """Continuous-time noise densities (Kalibr's IMU noise model): white noise of the gyroscope
    (rad/s/√Hz) and accelerometer (m/s²/√Hz), and the bias random walks (rad/s²/√Hz, m/s³/√Hz)."""

    gyro_noise: float
    gyro_walk: float
    accel_noise: float
    accel_walk: float

    def white(self, dt: float) -> tuple[float, float]:
        """Per-sample std of the white noise at sample period ``dt``: σ_d = σ_c / √dt (gyro, accel)."""
        return self.gyro_noise / np.sqrt(dt), self.accel_noise / np.sqrt(dt)

    def walk(self, dt: float) -> tuple[float, float]:
        """Per-sample std of the bias random-walk step: σ_bd = σ_bc · √dt (gyro, accel)."""
        return self.gyro_walk * np.sqrt(dt), self.accel_walk * np.sqrt(dt)


# EuRoC MAV's ADIS16448 (mav0/imu0/sensor.yaml)
EUROC_ADIS16448 = ImuNoise(gyro_noise=1.6968e-4, gyro_walk=1.9393e-5, accel_noise=2.0e-3, accel_walk=3.0e-3)


@dataclasses.dataclass(frozen=True)
class ImuData:
    """A sequence's IMU: ``timestamps`` (M,) s on the IMU clock (strictly increasing), ``gyro`` (M, 3)
    rad/s and ``accel`` (M, 3) m/s² in the IMU frame, ``T_cam_imu`` (4, 4), ``noise``, the nominal
    ``rate_hz`` and ``time_offset_s`` (t_imu = t_cam + time_offset_s)."""

    timestamps: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    T_cam_imu: np.ndarray
    noise: ImuNoise
    rate_hz: float
    time_offset_s: float = 0.0

    def __len__(self) -> int:
        return len(self.timestamps)

    def camera_times(self) -> np.ndarray:
        """The samples' times on the camera clock: timestamps − time_offset_s."""
        return self.timestamps - self.time_offset_s


@dataclasses.dataclass(frozen=True)
class ImuWindow:
    """``size`` samples around [t0, t1] on the camera clock, padded (``valid`` false) with copies of
    the last one, so that every window of a sequence has the same shape (one compiled program).
    ``t`` is relative to t0 (float32 keeps sub-microsecond stamps near 0, not near 1e9 s), ``span``
    is t1 − t0: ``preintegrate(w.t, w.gyro, w.accel, 0.0, w.span, ..., valid=w.valid)``."""

    t: np.ndarray
    gyro: np.ndarray
    accel: np.ndarray
    valid: np.ndarray
    span: float


def window(imu: ImuData, t0: float, t1: float, size: int) -> ImuWindow:
    """The samples from the last one at or before ``t0`` to the first one at or after ``t1`` (camera
    clock), padded to ``size``. ArgumentError when the IMU does not span [t0, t1] or they need more
    than ``size`` samples."""
    t = imu.camera_times()
    i0 = int(np.searchsorted(t, t0, side="right")) - 1
    i1 = int(np.searchsorted(t, t1, side="left"))
    if not t0 <= t1 or i0 < 0 or i1 >= len(t):
        raise ArgumentError(f"the IMU samples ({t[0]:.6f} to {t[-1]:.6f} s, camera clock) do not span {t0:.6f} to {t1:.6f} s")
    n = i1 - i0 + 1
    if n > size:
        raise ArgumentError(f"{t0:.6f} to {t1:.6f} s spans {n} IMU samples, more than the window's {size}")
    pick = np.minimum(np.arange(i0, i0 + size), i1)
    return ImuWindow(t[pick] - t0, imu.gyro[pick], imu.accel[pick], np.arange(size) < n, float(t1 - t0))
