"""File formats: TUM trajectories (strict 8 columns), exposure paths, camera YAML, depth PNGs.

Every reader validates what it reads and raises :class:`~mbavo_jax.errors.DataError` naming the
file and line. Writers flush per call so an interrupted run keeps what it wrote.
"""

from __future__ import annotations

import os
import pathlib

import numpy as np
import yaml

from .errors import DataError

__all__ = [
    "read_tum_trajectory",
    "write_tum_trajectory",
    "TrajectoryWriter",
    "read_exposure_file",
    "write_exposure_file",
    "read_camera_yaml",
    "write_camera_yaml",
    "read_image_gray",
    "read_depth_png",
    "read_file_list",
    "check_unit_quaternions",
    "check_stamps",
    "read_table",
]


def read_table(path, ncols: int | tuple[int, ...], what: str):
    """Yield (line_number, float columns) of a whitespace/comma table, skipping '#' comments."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise DataError(path, f"{what} not found")
    allowed = (ncols,) if isinstance(ncols, int) else ncols
    with open(path, "r", encoding="utf-8", errors="replace") as fh:
        for k, line in enumerate(fh, start=1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.replace(",", " ").split()
            if len(parts) not in allowed:
                exp = " or ".join(str(a) for a in allowed)
                raise DataError(path, f"expected {exp} columns, found {len(parts)}", k)
            try:
                vals = [float(p) for p in parts]
            except ValueError:
                raise DataError(path, f"not a number in '{s[:60]}'", k) from None
            if not all(np.isfinite(vals)):
                raise DataError(path, "non-finite value", k)
            yield k, vals


def check_unit_quaternions(path, q: np.ndarray, lines, tol: float = 1e-3) -> np.ndarray:
    """Reject quaternions far from unit norm (a sign of a wrong column order); renormalise the rest."""
    norms = np.linalg.norm(q, axis=1)
    bad = np.nonzero(np.abs(norms - 1.0) > tol)[0]
    if bad.size:
        i = int(bad[0])
        raise DataError(path, f"quaternion norm {norms[i]:.4f} is not 1 (expected qx qy qz qw)", lines[i])
    return q / norms[:, None]


def check_stamps(path, stamps: np.ndarray, lines=None) -> np.ndarray:
    """``stamps`` if they strictly increase; else a DataError naming the file and the line (``lines[i]``
    is the line of ``stamps[i]``) of the first duplicate or decreasing one."""
    d = np.diff(stamps)
    bad = np.nonzero(d <= 0)[0]
    if bad.size:
        i = int(bad[0]) + 1
        kind = "duplicate" if d[i - 1] == 0 else "decreasing"
        raise DataError(path, f"{kind} timestamp {stamps[i]!r} (timestamps must increase)", None if lines is None else lines[i])
    return stamps


def _stamped_rows(path, ncols: int, what: str, empty: str) -> tuple[np.ndarray, list]:
    """(rows (N, ncols), their line numbers) of a table whose first column are increasing stamps."""
    table = list(read_table(path, ncols, what))
    if not table:
        raise DataError(path, empty)
    lines = [k for k, _ in table]
    arr = np.asarray([vals for _, vals in table], dtype=np.float64)
    check_stamps(path, arr[:, 0], lines)
    return arr, lines


def read_tum_trajectory(path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``timestamp tx ty tz qx qy qz qw`` lines. Returns (stamps (N,), poses (N, 7) [t, q])."""
    arr, lines = _stamped_rows(path, 8, "trajectory file", "trajectory file has no poses")
    q = check_unit_quaternions(path, arr[:, 4:8], lines)
    return arr[:, 0], np.concatenate([arr[:, 1:4], q], axis=1)


def _fmt_pose(v) -> str:
    return " ".join(f"{x:.9f}" for x in v)


def write_tum_trajectory(path, stamps, poses, header: str | None = None) -> None:
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "w") as fh:
        fh.write(f"# {header or 'timestamp tx ty tz qx qy qz qw'}\n")
        for t, p in zip(stamps, poses):
            fh.write(f"{t:.6f} {_fmt_pose(p)}\n")


class TrajectoryWriter:
    """Appends one TUM line per frame and flushes + fsyncs it, so a killed run keeps every pose."""

    def __init__(self, path, header: str = "timestamp tx ty tz qx qy qz qw", append: bool = False):
        self.path = pathlib.Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        fresh = not (append and self.path.exists())
        self._fh = open(self.path, "a" if not fresh else "w")
        if fresh:
            self._fh.write(f"# {header}\n")
            self._flush()

    def _flush(self):
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def write(self, stamp: float, *vectors) -> None:
        self._fh.write(f"{stamp:.6f} " + " ".join(_fmt_pose(v) for v in vectors) + "\n")
        self._flush()

    def close(self):
        self._fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def read_exposure_file(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read ``timestamp`` + start ``tx ty tz qx qy qz qw`` + end ``tx ty tz qx qy qz qw`` (15 columns).

    Returns (stamps, start (N, 7), end (N, 7)), camera-to-world poses.
    """
    arr, lines = _stamped_rows(path, 15, "exposure file", "exposure file has no rows")
    q0 = check_unit_quaternions(path, arr[:, 4:8], lines)
    q1 = check_unit_quaternions(path, arr[:, 11:15], lines)
    return arr[:, 0], np.concatenate([arr[:, 1:4], q0], 1), np.concatenate([arr[:, 8:11], q1], 1)


def write_exposure_file(path, stamps, starts, ends) -> None:
    path = pathlib.Path(path)
    with open(path, "w") as fh:
        fh.write("# timestamp start:tx ty tz qx qy qz qw end:tx ty tz qx qy qz qw (camera-to-world)\n")
        for t, a, b in zip(stamps, starts, ends):
            fh.write(f"{t:.6f} {_fmt_pose(a)} {_fmt_pose(b)}\n")


CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height")


def read_camera_yaml(path) -> dict:
    """Camera YAML: ``fx fy cx cy width height`` required; optional ``depth_scale``,
    ``exposure_ms``, ``fps``, ``response_gamma``, ``depth_sigma`` ([a, b] of the depth noise
    σ(z) = a + b·(z − 0.4)² m)."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise DataError(path, "camera file not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as exc:
        raise DataError(path, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise DataError(path, "camera file must be a mapping of keys to values")
    missing = [k for k in CAMERA_KEYS if k not in data]
    if missing:
        raise DataError(path, f"missing camera key(s): {', '.join(missing)}")
    for k in CAMERA_KEYS:
        try:
            v = float(data[k])
        except (TypeError, ValueError):
            raise DataError(path, f"camera key '{k}' is not a number: {data[k]!r}") from None
        if not np.isfinite(v):
            raise DataError(path, f"camera key '{k}' is not finite: {v}")
        if k in ("fx", "fy", "width", "height") and v <= 0:
            raise DataError(path, f"camera key '{k}' must be positive, got {v}")
        if v < 0:
            raise DataError(path, f"camera key '{k}' must not be negative, got {v}")
        data[k] = int(v) if k in ("width", "height") else v
    if "depth_sigma" in data:
        ds = data["depth_sigma"]
        try:
            ok = len(ds) == 2 and float(ds[0]) > 0 and float(ds[1]) >= 0
        except (TypeError, ValueError):
            ok = False
        if not ok:
            raise DataError(path, f"depth_sigma must be [a > 0, b >= 0] (metres), got {ds!r}")
        data["depth_sigma"] = [float(ds[0]), float(ds[1])]
    return data


def write_camera_yaml(path, **values) -> None:
    pathlib.Path(path).write_text(yaml.safe_dump(values, sort_keys=False))


def _cv2():
    """OpenCV with its own logging silenced (we report unreadable files ourselves, in one line)."""
    import cv2

    try:
        cv2.utils.logging.setLogLevel(cv2.utils.logging.LOG_LEVEL_SILENT)
    except AttributeError:  # pragma: no cover - older OpenCV
        cv2.setLogLevel(0)
    return cv2


def _imread(path, what: str) -> np.ndarray:
    """``cv2.imread`` unchanged, with one-line errors for a missing or corrupt ``what`` file."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise DataError(path, f"{what} not found")
    img = _cv2().imread(str(path), _cv2().IMREAD_UNCHANGED)
    if img is None:
        raise DataError(path, f"unreadable or corrupt {what}")
    return img


def read_image_gray(path) -> np.ndarray:
    """Read an image as float32 grey in [0, 1] (8- or 16-bit, grey or colour)."""
    cv2 = _cv2()
    img = _imread(path, "image")
    if img.ndim == 3:
        code = cv2.COLOR_BGRA2GRAY if img.shape[2] == 4 else cv2.COLOR_BGR2GRAY
        img = cv2.cvtColor(img, code)
    scale = 65535.0 if img.dtype == np.uint16 else 255.0 if img.dtype == np.uint8 else 1.0
    return img.astype(np.float32) / np.float32(scale)


def read_depth_png(path, scale: float = 5000.0, shape: tuple[int, int] | None = None) -> np.ndarray:
    """16-bit depth PNG → metres (float32); 0 becomes NaN (no measurement)."""
    path = pathlib.Path(path)
    d = _imread(path, "depth image")
    if d.dtype != np.uint16 or d.ndim != 2:
        raise DataError(path, f"depth must be single-channel 16-bit, got {d.dtype} with shape {d.shape}")
    if shape is not None and d.shape != tuple(shape):
        raise DataError(path, f"depth size {d.shape[1]}x{d.shape[0]} differs from image size {shape[1]}x{shape[0]}")
    out = d.astype(np.float32) / np.float32(scale)
    out[d == 0] = np.nan
    return out


def read_file_list(path, what: str = "file list") -> list[tuple[int, float, str]]:
    """TUM-style ``timestamp filename`` list: returns (line, stamp, relative path), checked sorted."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise DataError(path, f"{what} not found")
    out = []
    with open(path) as fh:
        for k, line in enumerate(fh, start=1):
            s = line.strip()
            if not s or s.startswith("#"):
                continue
            parts = s.split()
            if len(parts) < 2:
                raise DataError(path, "expected 'timestamp filename'", k)
            try:
                stamp = float(parts[0])
            except ValueError:
                raise DataError(path, f"not a timestamp: '{parts[0]}'", k) from None
            out.append((k, stamp, parts[1]))
    if not out:
        raise DataError(path, f"{what} is empty")
    stamps = np.array([s for _, s, _ in out])
    check_stamps(path, stamps, [k for k, _, _ in out])
    return out
