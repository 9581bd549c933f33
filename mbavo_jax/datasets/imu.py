"""IMU files: ``imu.txt`` with camera.yaml's ``imu:`` block (our layout, what ``mbavo synth --imu``
writes) and EuRoC's ``mav0/imu0/data.csv`` with ``mav0/imu0/sensor.yaml``.

``imu.txt``: ``timestamp gx gy gz ax ay az`` per line (s on the IMU clock, rad/s, m/s², IMU frame), a
``#`` header line. camera.yaml's ``imu:`` block: ``T_cam_imu`` (4x4, rows), ``rate_hz``,
``time_offset_s`` (t_imu = t_cam + time_offset_s, Kalibr's ``timeshift_cam_imu``) and Kalibr's noise
names ``gyroscope_noise_density``, ``gyroscope_random_walk``, ``accelerometer_noise_density``,
``accelerometer_random_walk``. Every value is checked; a DataError names the file and line or key.
"""

from __future__ import annotations

import pathlib

import numpy as np

from ..errors import DataError
from ..imu.data import ImuData, ImuNoise
from ..io import check_stamps, data_lines, read_table, yaml_number
from .calibration import check_rigid, euroc_T_BS, read_euroc_yaml

__all__ = ["IMU_FILE", "read_imu_txt", "write_imu_txt", "imu_block", "open_imu", "open_euroc_imu"]

IMU_FILE = "imu.txt"
IMU_HEADER = "# timestamp gx gy gz ax ay az (s on the IMU clock; rad/s; m/s^2 specific force; IMU frame)"
NOISE_KEYS = {"gyroscope_noise_density": "gyro_noise", "gyroscope_random_walk": "gyro_walk",
              "accelerometer_noise_density": "accel_noise", "accelerometer_random_walk": "accel_walk"}


def read_imu_txt(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(timestamps (M,), gyro (M, 3), accel (M, 3)) of an ``imu.txt``; DataError on a wrong column
    count, a non-number or non-finite value, a timestamp that does not increase, or no samples."""
    rows = list(read_table(path, 7, "IMU file"))
    if len(rows) < 2:
        raise DataError(path, f"IMU file has {len(rows)} samples (need at least 2)")
    arr = np.asarray([v for _, v in rows], np.float64)
    check_stamps(path, arr[:, 0], [k for k, _ in rows])
    return arr[:, 0], arr[:, 1:4], arr[:, 4:7]


def write_imu_txt(path, imu: ImuData) -> None:
    lines = [IMU_HEADER + "\n"]
    lines += [f"{t:.9f} " + " ".join(f"{x:.9e}" for x in (*g, *a)) + "\n" for t, g, a in zip(imu.timestamps, imu.gyro, imu.accel)]
    pathlib.Path(path).write_text("".join(lines))


def imu_block(imu: ImuData) -> dict:
    """camera.yaml's ``imu:`` block of ``imu`` (everything but the samples)."""
    n = imu.noise
    return {"T_cam_imu": [[float(x) for x in row] for row in np.asarray(imu.T_cam_imu)], "rate_hz": float(imu.rate_hz),
            "time_offset_s": float(imu.time_offset_s),
            **{key: float(getattr(n, field)) for key, field in NOISE_KEYS.items()}}


def _matrix(path, value) -> np.ndarray:
    """camera.yaml's ``imu: T_cam_imu``: 4 rows of 4 numbers, a rigid transform."""
    if not (isinstance(value, list) and len(value) == 4 and all(isinstance(r, list) and len(r) == 4 for r in value)):
        raise DataError(path, f"imu 'T_cam_imu' must be 4 rows of 4 numbers, got {value!r}"[:200])
    T = np.array([[yaml_number(path, f"imu 'T_cam_imu' row {i + 1}", x) for x in r] for i, r in enumerate(value)])
    return check_rigid(path, "imu: T_cam_imu", T)


def _noise(path, info: dict, where: str) -> ImuNoise:
    """Kalibr's four noise figures (each a number >= 0) of ``info``."""
    values = {}
    for key, field in NOISE_KEYS.items():
        if key not in info:
            raise DataError(path, f"{where} is missing '{key}'")
        values[field] = yaml_number(path, f"{where} '{key}'", info[key])
        if values[field] < 0:
            raise DataError(path, f"{where} '{key}' must be >= 0, got {values[field]:g}")
    return ImuNoise(**values)


def _rate(path, info: dict, where: str) -> float:
    rate = yaml_number(path, f"{where} 'rate_hz'", info.get("rate_hz"))
    if rate <= 0:
        raise DataError(path, f"{where} 'rate_hz' must be > 0, got {rate:g}")
    return rate


def open_imu(root, cam_info: dict) -> ImuData | None:
    """Our layout's IMU: ``imu.txt`` with camera.yaml's ``imu:`` block (``cam_info``), None when
    neither is there; DataError when one is there without the other or either is malformed."""
    root = pathlib.Path(root)
    txt, cam_yaml, block = root / IMU_FILE, root / "camera.yaml", cam_info.get("imu")
    if block is None:
        if txt.is_file():
            raise DataError(cam_yaml, f"{IMU_FILE} is there but camera.yaml has no 'imu:' block (T_cam_imu, rate_hz, noise)")
        return None
    if not isinstance(block, dict):
        raise DataError(cam_yaml, "'imu' must be a mapping (T_cam_imu, rate_hz, time_offset_s, the noise figures)")
    if "T_cam_imu" not in block:
        raise DataError(cam_yaml, "the 'imu' block is missing 'T_cam_imu'")
    T, noise, rate = _matrix(cam_yaml, block["T_cam_imu"]), _noise(cam_yaml, block, "the 'imu' block"), _rate(cam_yaml, block, "imu")
    offset = yaml_number(cam_yaml, "imu 'time_offset_s'", block.get("time_offset_s", 0.0))
    if not txt.is_file():
        raise DataError(txt, "IMU file not found (camera.yaml has an 'imu:' block)")
    t, gyro, accel = read_imu_txt(txt)
    return ImuData(t, gyro, accel, T, noise, rate, offset)


def _euroc_rows(csv) -> tuple[np.ndarray, np.ndarray]:
    """(stamps in s, values (M, 6)) of EuRoC's imu0/data.csv (integer ns stamps, 6 numbers each)."""
    stamps, values, lines = [], [], []
    for k, line in data_lines(csv, "EuRoC imu0/data.csv"):
        parts = [p.strip() for p in line.split(",")]
        if len(parts) != 7:
            raise DataError(csv, f"expected 7 columns (timestamp [ns], w_RS_S x y z, a_RS_S x y z), found {len(parts)}", k)
        if not parts[0].isdigit():
            raise DataError(csv, f"timestamp {parts[0][:30]!r} is not a whole number of nanoseconds", k)
        try:
            vals = [float(p) for p in parts[1:]]
        except ValueError:
            raise DataError(csv, f"not a number in '{line[:60]}'", k) from None
        if not all(np.isfinite(vals)):
            raise DataError(csv, "non-finite value", k)
        stamps.append(int(parts[0]) * 1e-9)
        values.append(vals)
        lines.append(k)
    if len(stamps) < 2:
        raise DataError(csv, f"EuRoC IMU file has {len(stamps)} samples (need at least 2)")
    return check_stamps(csv, np.array(stamps), lines), np.array(values)


def open_euroc_imu(root, T_BS_cam: np.ndarray) -> ImuData | None:
    """EuRoC's ``mav0/imu0``: data.csv and sensor.yaml (T_BS, rate_hz, Kalibr's noise figures), None
    when there is no data.csv. T_cam_imu = T_BS_cam⁻¹ T_BS_imu; EuRoC's clocks are one (offset 0)."""
    folder = pathlib.Path(root) / "mav0" / "imu0"
    csv, sensor = folder / "data.csv", folder / "sensor.yaml"
    if not csv.is_file():
        return None
    info = read_euroc_yaml(sensor, "EuRoC imu0/sensor.yaml")
    T_BS_imu = euroc_T_BS(sensor, info)
    noise, rate = _noise(sensor, info, "sensor.yaml"), _rate(sensor, info, "sensor.yaml")
    t, values = _euroc_rows(csv)
    return ImuData(t, values[:, :3], values[:, 3:], np.linalg.inv(T_BS_cam) @ T_BS_imu, noise, rate, 0.0)
