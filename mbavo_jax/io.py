"""File formats: TUM trajectories (strict 8 columns), exposure paths (per frame, and per image row
for a rolling shutter), camera YAML, depth PNGs.

Every reader validates what it reads and raises :class:`~mbavo_jax.errors.DataError` naming the
file and line; text files are read as UTF-8 through :func:`read_text`. Writers flush per call so an
interrupted run keeps what it wrote; output folders are made by :func:`prepare_out_dir`.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib

import numpy as np
import yaml

from .errors import DataError, MbavoError

__all__ = [
    "read_tum_trajectory",
    "write_tum_trajectory",
    "TrajectoryWriter",
    "PlyWriter",
    "read_ply",
    "read_exposure_file",
    "read_exposure_spline_file",
    "write_exposure_file",
    "ExposureRows",
    "read_exposure_rows",
    "write_exposure_rows",
    "sampled_rows",
    "read_camera_yaml",
    "read_camera",
    "checked_camera",
    "yaml_number",
    "exposure_problem",
    "frame_interval_ms",
    "check_exposures",
    "write_camera_yaml",
    "read_image_gray",
    "read_depth_png",
    "read_file_list",
    "check_unit_quaternions",
    "check_stamps",
    "read_table",
    "read_text",
    "data_lines",
    "format_stamp",
    "check_size",
    "prepare_out_dir",
]


def read_text(path, what: str) -> str:
    """The text of a UTF-8 file (a leading byte-order mark dropped). DataError naming the file when it
    is missing or unreadable, and the line of the first byte that is not UTF-8."""
    path = pathlib.Path(path)
    if not path.is_file():
        raise DataError(path, f"{what} not found")
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise DataError(path, f"cannot read the {what}: {exc.strerror}") from None
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise DataError(path, f"byte 0x{data[exc.start]:02x} is not UTF-8 text (save it as UTF-8)", line) from None


def data_lines(path, what: str, text: str | None = None) -> list[tuple[int, str]]:
    """(line number, stripped text) of each line of a UTF-8 text file that is neither blank nor a '#'
    comment. ``text``: the file's text, when :func:`read_text` already read it."""
    text = read_text(path, what) if text is None else text
    text = text.replace("\r\n", "\n").replace("\r", "\n")  # universal newlines, as open() reads
    lines = (line.strip() for line in text.split("\n"))
    return [(k, s) for k, s in enumerate(lines, start=1) if s and not s.startswith("#")]


def format_stamp(t) -> str:
    """A timestamp as a plain number for messages: ``1.033333``, ``inf``, ``nan`` (never ``np.float64(...)``)."""
    return repr(float(t))


def prepare_out_dir(path, what: str = "--out") -> pathlib.Path:
    """The output folder ``path``, created (with its parents) if needed. A one-line MbavoError when
    ``path`` or a parent is not a folder, or the folder cannot be created or written to."""
    path = pathlib.Path(path)
    existing = next((p for p in (path, *path.parents) if p.exists()), None)
    if existing is not None and not existing.is_dir():
        which = "exists and is not a folder" if existing == path else f"cannot be created: {existing} is not a folder"
        raise MbavoError(f"{path}: {what} {which} (choose another {what})")
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise MbavoError(f"{path}: {what} cannot be created: {exc.strerror} (choose another {what})") from None
    if not os.access(path, os.W_OK | os.X_OK):
        raise MbavoError(f"{path}: {what} is not writable (choose another {what})")
    return path


def read_table(path, ncols: int | tuple[int, ...], what: str, at_least: bool = False):
    """Yield (line_number, float columns) of a whitespace/comma table, skipping '#' comments.
    ``ncols``: the column counts allowed; with ``at_least``, the fewest (the first ``ncols`` columns
    are read, the rest ignored)."""
    allowed = (ncols,) if isinstance(ncols, int) else ncols
    for k, s in data_lines(path, what):
        parts = s.replace(",", " ").split()
        if at_least and len(parts) > min(allowed):
            parts = parts[: min(allowed)]
        if len(parts) not in allowed:
            exp = ("at least " if at_least else "") + " or ".join(str(a) for a in allowed)
            raise DataError(path, f"expected {exp} columns, found {len(parts)}", k)
        try:
            vals = [float(p) for p in parts]
        except ValueError:
            raise DataError(path, f"not a number in '{s[:60]}'", k) from None
        if not all(np.isfinite(vals)):
            raise DataError(path, "non-finite value", k)
        yield k, vals


def check_unit_quaternions(path, q: np.ndarray, lines, tol: float = 1e-3) -> np.ndarray:
    """Reject quaternions far from unit norm (a sign of a wrong column order); renormalise the rest
    (those already unit to float32 precision are kept as written)."""
    norms = np.linalg.norm(q, axis=1)
    bad = np.nonzero(np.abs(norms - 1.0) > tol)[0]
    if bad.size:
        i = int(bad[0])
        raise DataError(path, f"quaternion norm {norms[i]:.4f} is not 1 (expected qx qy qz qw)", lines[i])
    return np.where(np.abs(norms - 1.0)[:, None] < 1e-6, q, q / norms[:, None])


def check_stamps(path, stamps: np.ndarray, lines=None) -> np.ndarray:
    """``stamps`` if they are finite and strictly increase; else a DataError naming the file and the
    line (``lines[i]`` is the line of ``stamps[i]``) of the first NaN, infinite, duplicate or decreasing one."""
    line = lambda i: None if lines is None else lines[i]
    stamps = np.asarray(stamps, np.float64)
    bad = np.nonzero(~np.isfinite(stamps))[0]
    if bad.size:
        i = int(bad[0])
        raise DataError(path, f"timestamp {format_stamp(stamps[i])} is not a finite number", line(i))
    d = np.diff(stamps)
    bad = np.nonzero(d <= 0)[0]
    if bad.size:
        i = int(bad[0]) + 1
        kind = "duplicate" if d[i - 1] == 0 else "decreasing"
        raise DataError(path, f"{kind} timestamp {format_stamp(stamps[i])} (timestamps must increase)", line(i))
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
    """A pose vector as text: float32 values exactly (shortest digits that read back to the same
    float32, so that --resume continues from the very poses in memory), others to 9 decimals."""
    v = np.asarray(v)
    if v.dtype == np.float32:
        return " ".join(np.format_float_positional(x, unique=True, trim="-") for x in v)
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


class PlyWriter:
    """A point cloud file (PLY, ASCII: x y z intensity) that grows: points are appended and the
    vertex count in the fixed-width header is rewritten, each call flushed."""

    HEADER = "ply\nformat ascii 1.0\nelement vertex {:012d}\nproperty float x\nproperty float y\nproperty float z\n" \
             "property float intensity\nend_header\n"

    def __init__(self, path, append: bool = False):
        self.path = pathlib.Path(path)
        if append and self.path.is_file():
            self.count = read_ply(self.path)[0].shape[0]
            self._fh = open(self.path, "r+")
        else:
            self.count = 0
            self._fh = open(self.path, "w+")
            self._fh.write(self.HEADER.format(0))
        self._fh.seek(0, 2)

    def write(self, xyz, intensity) -> None:
        xyz, intensity = np.asarray(xyz, np.float32).reshape(-1, 3), np.asarray(intensity, np.float32).reshape(-1)
        self._fh.writelines(f"{x:.6g} {y:.6g} {z:.6g} {i:.4f}\n" for (x, y, z), i in zip(xyz.tolist(), intensity.tolist()))
        self.count += len(xyz)
        self._fh.seek(0)
        self._fh.write(self.HEADER.format(self.count))
        self._fh.seek(0, 2)
        self._fh.flush()

    def close(self) -> None:
        self._fh.close()


def read_ply(path) -> tuple[np.ndarray, np.ndarray]:
    """(xyz (N, 3), intensity (N,)) of a PLY file written by :class:`PlyWriter`."""
    text = read_text(path, "point cloud").split("end_header\n", 1)
    rows = np.loadtxt(text[1].splitlines(), dtype=np.float64, ndmin=2) if len(text) == 2 and text[1].strip() else np.zeros((0, 4))
    return rows[:, :3], rows[:, 3]


def read_exposure_file(path) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Read ``timestamp`` + start ``tx ty tz qx qy qz qw`` + end ``tx ty tz qx qy qz qw`` (15 columns).

    Returns (stamps, start (N, 7), end (N, 7)), camera-to-world poses.
    """
    arr, lines = _stamped_rows(path, 15, "exposure file", "exposure file has no rows")
    q0 = check_unit_quaternions(path, arr[:, 4:8], lines)
    q1 = check_unit_quaternions(path, arr[:, 11:15], lines)
    return arr[:, 0], np.concatenate([arr[:, 1:4], q0], 1), np.concatenate([arr[:, 8:11], q1], 1)


def read_exposure_spline_file(path) -> tuple[np.ndarray, np.ndarray]:
    """Read ``timestamp`` + four control poses ``tx ty tz qx qy qz qw`` of cubic exposure paths
    (29 columns, ``exposure_spline.txt``). Returns (stamps, controls (N, 4, 7)), camera-to-world."""
    arr, lines = _stamped_rows(path, 29, "exposure spline file", "exposure spline file has no rows")
    poses = arr[:, 1:].reshape(-1, 4, 7)
    for j in range(4):
        check_unit_quaternions(path, poses[:, j, 3:], lines)
    return arr[:, 0], poses


def write_exposure_file(path, stamps, starts, ends) -> None:
    path = pathlib.Path(path)
    with open(path, "w") as fh:
        fh.write("# timestamp start:tx ty tz qx qy qz qw end:tx ty tz qx qy qz qw (camera-to-world)\n")
        for t, a, b in zip(stamps, starts, ends):
            fh.write(f"{t:.6f} {_fmt_pose(a)} {_fmt_pose(b)}\n")


@dataclasses.dataclass(frozen=True)
class ExposureRows:
    """Per-row exposure paths of N frames at K sampled image rows each (a rolling shutter):
    ``rows`` (N, K) row indices, ``starts`` and ``ends`` (N, K, 7) camera-to-world poses at each
    row's exposure start and end; ``stamps`` (N,) the frames' mid-exposure timestamps."""

    stamps: np.ndarray
    rows: np.ndarray
    starts: np.ndarray
    ends: np.ndarray


def sampled_rows(height: int, k: int = 9) -> np.ndarray:
    """The k image rows (evenly spaced, first and last included) of an exposure rows file."""
    return np.unique(np.round(np.linspace(0, height - 1, min(k, height))).astype(np.int64))


def _frame_groups(path, stamps: np.ndarray, lines) -> list[np.ndarray]:
    """Indices of the lines of each frame (consecutive equal stamps, frames in increasing time)."""
    bounds = np.flatnonzero(np.diff(stamps)) + 1
    groups = np.split(np.arange(len(stamps)), bounds)
    check_stamps(path, stamps[[g[0] for g in groups]], [lines[g[0]] for g in groups])
    return groups


def read_exposure_rows(path) -> ExposureRows:
    """Read ``timestamp row`` + start ``tx ty tz qx qy qz qw`` + end ``tx ty tz qx qy qz qw`` (16
    columns), K lines per frame (its sampled rows, increasing; every frame the same K)."""
    table = list(read_table(path, 16, "exposure rows file"))
    if not table:
        raise DataError(path, "exposure rows file has no rows")
    lines, arr = [k for k, _ in table], np.asarray([v for _, v in table], np.float64)
    groups = _frame_groups(path, arr[:, 0], lines)
    k = len(groups[0])
    for g in groups:
        rows = arr[g, 1]
        if len(g) != k:
            raise DataError(path, f"frame {format_stamp(arr[g[0], 0])} has {len(g)} rows, the first frame {k}", lines[g[0]])
        bad = np.flatnonzero((rows != np.round(rows)) | (rows < 0) | (np.diff(rows, prepend=-1) <= 0))
        if bad.size:
            raise DataError(path, f"row {arr[g[bad[0]], 1]:g} is not a whole number >= 0 above the frame's previous row", lines[g[bad[0]]])
    q0 = check_unit_quaternions(path, arr[:, 5:9], lines)
    q1 = check_unit_quaternions(path, arr[:, 12:16], lines)
    n = len(groups)
    pose = lambda t, q: np.concatenate([t, q], 1).reshape(n, k, 7)
    return ExposureRows(arr[::k, 0], arr[:, 1].astype(np.int64).reshape(n, k), pose(arr[:, 2:5], q0), pose(arr[:, 9:12], q1))


def write_exposure_rows(path, rows: ExposureRows) -> None:
    with open(pathlib.Path(path), "w") as fh:
        fh.write("# timestamp row start:tx ty tz qx qy qz qw end:tx ty tz qx qy qz qw (camera-to-world at the exposure start "
                 "and end of image row `row`; each frame's sampled rows)\n")
        for t, rs, a, b in zip(rows.stamps, rows.rows, rows.starts, rows.ends):
            fh.writelines(f"{t:.6f} {int(r)} {_fmt_pose(x)} {_fmt_pose(y)}\n" for r, x, y in zip(rs, a, b))


CAMERA_KEYS = ("fx", "fy", "cx", "cy", "width", "height")
CAMERA_RULES = {"fx": "> 0", "fy": "> 0", "width": "> 0", "height": "> 0", "cx": "", "cy": "",
                "depth_scale": "> 0", "fps": "> 0", "response_gamma": "> 0", "exposure_ms": "",
                "readout_ms": ">= 0"}  # numeric keys (exposure_ms: checked by exposure_problem)


def yaml_number(where, what: str, value, line: int | None = None) -> float:
    """A number read from YAML (or text holding one, as YAML reads ``1e3``) as a finite float; a
    DataError naming ``where`` and ``what`` for a boolean (``true`` is not 1), nothing, other text or
    a non-finite value."""
    try:
        if isinstance(value, bool) or value is None:
            raise TypeError
        v = float(value)
    except (TypeError, ValueError):
        raise DataError(where, f"{what} is not a number: {value!r}", line) from None
    if not np.isfinite(v):
        raise DataError(where, f"{what} is not finite: {v}", line)
    return v


EXPOSURE_SLACK = (0.01, 0.1)  # exposure_problem's tolerance: 1 % of the frame interval plus 0.1 ms


def exposure_problem(exposure_ms: float, interval_ms: float | None) -> str:
    """What is wrong with an exposure time (ms), or '': the one rule for every exposure read,
    0 <= exposure <= the frame interval (``interval_ms``, when known; ``EXPOSURE_SLACK`` of slack).
    0 is an instantaneous exposure (a sharp image, as ``mbavo synth --preset none`` writes)."""
    if not np.isfinite(exposure_ms):
        return f"is not finite: {exposure_ms}"
    if exposure_ms < 0:
        return f"must be >= 0 ms, got {exposure_ms:g}"
    if interval_ms is not None and exposure_ms > interval_ms * (1 + EXPOSURE_SLACK[0]) + EXPOSURE_SLACK[1]:
        return f"must be at most the frame interval {interval_ms:.4g} ms (the time between frames), got {exposure_ms:g} ms"
    return ""


def frame_interval_ms(stamps) -> float | None:
    """The frame interval (ms) of timestamps (s): the median time between frames; None for one frame."""
    stamps = np.asarray(stamps, np.float64)
    return float(np.median(np.diff(stamps))) * 1000.0 if len(stamps) > 1 else None


def check_exposures(path, exposures_ms, stamps, lines=None, what: str = "exposure") -> np.ndarray:
    """``exposures_ms`` if each obeys :func:`exposure_problem` at the frame interval of ``stamps`` (s);
    else a DataError naming ``path`` and the line (``lines[i]`` is the line of ``exposures_ms[i]``)."""
    exposures_ms = np.asarray(exposures_ms, np.float64)
    interval = frame_interval_ms(stamps)
    for i, e in enumerate(exposures_ms):
        problem = exposure_problem(float(e), interval)
        if problem:
            raise DataError(path, f"{what} {problem}", None if lines is None else lines[i])
    return exposures_ms


def _camera_number(path, key: str, value, rule: str) -> float:
    """camera.yaml's ``key`` as a finite float obeying ``rule`` ('> 0', '>= 0' or ''), else a DataError naming the key."""
    v = yaml_number(path, f"camera key '{key}'", value)
    if (rule == "> 0" and v <= 0) or (rule == ">= 0" and v < 0):
        raise DataError(path, f"camera key '{key}' must be {rule}, got {v:g}")
    if key in ("width", "height") and v != int(v):
        raise DataError(path, f"camera key '{key}' must be a whole number of pixels, got {v:g}")
    return int(v) if key in ("width", "height") else v


def _depth_sigma(path, ds) -> list[float]:
    """camera.yaml's ``depth_sigma`` [a > 0, b >= 0] as floats, else a DataError."""
    try:
        ok = len(ds) == 2 and not any(isinstance(x, bool) for x in ds)  # true is not 1
        ok = ok and float(ds[0]) > 0 and float(ds[1]) >= 0 and all(np.isfinite([float(x) for x in ds]))
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise DataError(path, f"depth_sigma must be [a > 0, b >= 0] (metres), got {ds!r}")
    return [float(ds[0]), float(ds[1])]


def checked_camera(where, fx, fy, cx, cy, width, height, line: int | None = None):
    """``PinholeCamera.create``, its complaint about the values a DataError naming ``where`` (the file
    they come from) and ``line``."""
    from .geometry.camera import PinholeCamera  # here, not at the top: it imports JAX

    try:
        return PinholeCamera.create(fx, fy, cx, cy, width, height)
    except ValueError as exc:
        raise DataError(where, str(exc), line) from None


def read_camera(path):
    """Camera YAML as (PinholeCamera, its values): ``fx fy cx cy width height`` required; optional
    ``depth_scale``, ``exposure_ms``, ``readout_ms`` (rolling shutter: first row's exposure start to
    the last row's), ``fps``, ``response_gamma``, ``depth_sigma`` ([a, b] of the
    depth noise σ(z) = a + b·(z − 0.4)² m). Every value is checked (numbers, ranges, the camera's
    intrinsics by :func:`checked_camera`); a DataError names the file and the key."""
    path = pathlib.Path(path)
    text = read_text(path, "camera file")
    try:
        data = yaml.safe_load(text) or {}
    except yaml.YAMLError as exc:
        raise DataError(path, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(data, dict):
        raise DataError(path, "camera file must be a mapping of keys to values")
    missing = [k for k in CAMERA_KEYS if k not in data]
    if missing:
        raise DataError(path, f"missing camera key(s): {', '.join(missing)}")
    for k, rule in CAMERA_RULES.items():
        if k in data:
            data[k] = _camera_number(path, k, data[k], rule)
    if "exposure_ms" in data:
        problem = exposure_problem(data["exposure_ms"], 1000.0 / data["fps"] if "fps" in data else None)
        if problem:
            raise DataError(path, f"camera key 'exposure_ms' {problem}")
    camera = checked_camera(path, *(data[k] for k in CAMERA_KEYS))
    if "depth_sigma" in data:
        data["depth_sigma"] = _depth_sigma(path, data["depth_sigma"])
    return camera, data


def read_camera_yaml(path) -> dict:
    """The checked values of a camera YAML (:func:`read_camera`)."""
    return read_camera(path)[1]


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


def check_size(path, image: np.ndarray, shape: tuple[int, int], what: str = "image") -> np.ndarray:
    """``image`` if its (height, width) is ``shape`` (the camera's), else a DataError naming ``path``."""
    if image.shape[:2] != tuple(shape):
        h, w = image.shape[:2]
        raise DataError(path, f"{what} size {w}x{h} differs from the camera's {shape[1]}x{shape[0]}")
    return image


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
    """16-bit depth PNG → metres (float32); 0 becomes NaN (no measurement). ``shape``: the (height,
    width) it must have."""
    path = pathlib.Path(path)
    d = _imread(path, "depth image")
    if d.dtype != np.uint16 or d.ndim != 2:
        raise DataError(path, f"depth must be single-channel 16-bit, got {d.dtype} with shape {d.shape}")
    if shape is not None:
        check_size(path, d, shape, "depth")
    out = d.astype(np.float32) / np.float32(scale)
    out[d == 0] = np.nan
    return out


def read_file_list(path, what: str = "file list", text: str | None = None) -> list[tuple[int, float, str]]:
    """TUM-style ``timestamp filename`` list: returns (line, stamp, relative path), checked finite and
    sorted. ``text``: the file's text, when :func:`read_text` already read it."""
    path = pathlib.Path(path)
    out = []
    for k, s in data_lines(path, what, text):
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
