"""Camera calibration files of the datasets: EuRoC's ``sensor.yaml`` and DSO's ``camera.txt``.

Each reader checks every value (numbers, counts, the model's name) and returns the lens as a
:class:`~mbavo_jax.datasets.distortion.CameraModel` or its :class:`~mbavo_jax.datasets.distortion.Undistorter`;
a DataError names the file and the key or line.
"""

from __future__ import annotations

import pathlib
import re

import numpy as np
import yaml

from ..errors import DataError
from ..io import data_lines, read_image_gray, read_text, yaml_number
from .distortion import CameraModel, Undistorter, camera_model, undistorter

__all__ = ["read_euroc_sensor", "read_euroc_yaml", "euroc_T_BS", "check_rigid", "read_dso_camera", "EUROC_MODELS", "DSO_MODELS"]

# EuRoC / Kalibr distortion_model names and the model each is.
EUROC_MODELS = {"radial-tangential": "radtan", "radtan": "radtan", "plumb_bob": "radtan", "equidistant": "equidistant",
                "equi": "equidistant", "fov": "fov", "none": "pinhole"}
# DSO camera.txt model names (lower case) and the model each is (KannalaBrandt is the equidistant model).
DSO_MODELS = {"pinhole": "pinhole", "fov": "fov", "radtan": "radtan", "equidistant": "equidistant", "kannalabrandt": "equidistant"}
# How many numbers follow each DSO model name: fx fy cx cy and the coefficients.
DSO_COUNTS = {"pinhole": (4, 5), "fov": (5,), "radtan": (8,), "equidistant": (8,)}


def _yaml_numbers(path, info: dict, key: str, count: int | None = None) -> list[float]:
    """The list of numbers under ``key`` (``count`` of them, when given), each checked by :func:`yaml_number`."""
    value = info[key]
    if not isinstance(value, list) or (count is not None and len(value) != count):
        want = f"a list of {count} numbers" if count is not None else "a list of numbers"
        raise DataError(path, f"'{key}' must be {want}, got {value!r}"[:200])
    return [yaml_number(path, f"'{key}' entry {i + 1}", v) for i, v in enumerate(value)]


def _euroc_size(path, info: dict) -> tuple[int, int]:
    """``resolution`` [width, height] as whole numbers > 0."""
    w, h = _yaml_numbers(path, info, "resolution", 2)
    if w != int(w) or h != int(h) or w <= 0 or h <= 0:
        raise DataError(path, f"'resolution' must be two whole numbers > 0 (width, height), got {[w, h]}")
    return int(w), int(h)


def euroc_T_BS(path, info: dict) -> np.ndarray:
    """``T_BS`` (the camera in the body frame, 4x4 row by row under ``data``) as a rigid transform;
    the identity when absent."""
    if "T_BS" not in info:
        return np.eye(4)
    tbs = info["T_BS"]
    if not isinstance(tbs, dict) or "data" not in tbs:
        raise DataError(path, "'T_BS' must hold 'data': the 16 numbers of a 4x4 matrix, row by row")
    for key in ("rows", "cols"):
        if key in tbs and yaml_number(path, f"'T_BS' {key}", tbs[key]) != 4:
            raise DataError(path, f"'T_BS' {key} must be 4, got {tbs[key]!r}")
    T = np.array(_yaml_numbers(path, {"T_BS data": tbs["data"]}, "T_BS data", 16)).reshape(4, 4)
    return check_rigid(path, "T_BS", T)


def check_rigid(path, what: str, T: np.ndarray) -> np.ndarray:
    """``T`` (4, 4) if it is a rigid transform, else a DataError naming ``path`` and ``what``."""
    R = T[:3, :3]
    if not np.allclose(T[3], [0, 0, 0, 1], atol=1e-6) or not np.allclose(R @ R.T, np.eye(3), atol=1e-3) or np.linalg.det(R) < 0:
        raise DataError(path, f"'{what}' is not a rigid transform (a rotation and a translation over the row 0 0 0 1)")
    return T


def _euroc_model(path, info: dict) -> tuple[str, list[float]]:
    """The distortion model and its coefficients of ``sensor.yaml`` (``camera_model`` must be pinhole)."""
    kind = info.get("camera_model", "pinhole")
    if kind != "pinhole":
        raise DataError(path, f"camera_model {kind!r} is not supported (pinhole, with a distortion_model of {', '.join(EUROC_MODELS)})")
    coeffs = _yaml_numbers(path, info, "distortion_coefficients") if "distortion_coefficients" in info else []
    name = info.get("distortion_model", "none" if not any(coeffs) else None)
    if name is None:
        raise DataError(path, "'distortion_coefficients' without a 'distortion_model' (e.g. radial-tangential or equidistant)")
    if not isinstance(name, str) or name.lower() not in EUROC_MODELS:
        raise DataError(path, f"distortion_model {name!r} is not supported (one of {', '.join(EUROC_MODELS)})")
    model = EUROC_MODELS[name.lower()]
    if model == "pinhole" and any(coeffs):
        raise DataError(path, f"distortion_model {name!r} with non-zero distortion_coefficients {coeffs}")
    return model, ([] if model == "pinhole" else coeffs)


def read_euroc_yaml(path, what: str) -> dict:
    """A EuRoC ``sensor.yaml`` (its ``%YAML:1.0`` line dropped) as a mapping; DataError otherwise."""
    text = re.sub(r"^%YAML.*$", "", read_text(path, what), flags=re.M)
    try:
        info = yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise DataError(path, f"not valid YAML ({str(exc).splitlines()[0]})") from None
    if not isinstance(info, dict):
        raise DataError(path, f"{what} must be a mapping of keys to values")
    return info


def read_euroc_sensor(path) -> tuple[CameraModel, np.ndarray]:
    """EuRoC's ``cam0/sensor.yaml``: (the lens: ``intrinsics`` fu fv cu cv, ``resolution``,
    ``distortion_model`` and ``distortion_coefficients``; T_BS (4, 4), the camera in the body frame)."""
    path = pathlib.Path(path)
    info = read_euroc_yaml(path, "EuRoC sensor.yaml")
    missing = [k for k in ("intrinsics", "resolution") if k not in info]
    if missing:
        raise DataError(path, f"missing key(s): {', '.join(missing)}")
    intrinsics = _yaml_numbers(path, info, "intrinsics", 4)
    w, h = _euroc_size(path, info)
    model, coeffs = _euroc_model(path, info)
    return camera_model(path, model, intrinsics, w, h, coeffs), euroc_T_BS(path, info)


def _dso_numbers(path, parts: list[str], line: int, what: str) -> list[float]:
    """``parts`` as finite floats, else a DataError saying the line must be ``what``."""
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise DataError(path, f"expected {what}, found '{' '.join(parts)[:60]}'", line) from None
    if not np.all(np.isfinite(vals)):
        raise DataError(path, "non-finite value", line)
    return vals


def _dso_model(path, first: str, line: int) -> tuple[str, list[float]]:
    """(model, numbers) of camera.txt's first line ``[Model] fx fy cx cy [coefficients]``; without a
    name (DSO's older files) 4 numbers are pinhole, 5 FOV (pinhole when ω is 0), 8 RadTan."""
    parts = first.split()
    name = None
    if parts and not re.match(r"^[-+]?[0-9.]", parts[0]):
        name, parts = parts[0], parts[1:]
    vals = _dso_numbers(path, parts, line, "'[Model] fx fy cx cy [coefficients]'")
    if name is None:
        unnamed = {4: "pinhole", 5: "fov" if len(vals) == 5 and vals[4] != 0 else "pinhole", 8: "radtan"}
        if len(vals) not in unnamed:
            raise DataError(path, f"expected 4, 5 or 8 numbers (pinhole, FOV, RadTan), found {len(vals)}", line)
        model = unnamed[len(vals)]
    else:
        if name.lower() not in DSO_MODELS:
            raise DataError(path, f"camera model '{name}' is not supported (Pinhole, RadTan, EquiDistant, KannalaBrandt, FOV)", line)
        model = DSO_MODELS[name.lower()]
        if len(vals) not in DSO_COUNTS[model]:
            counts = " or ".join(str(n) for n in DSO_COUNTS[model])
            raise DataError(path, f"the {name} model takes {counts} numbers (fx fy cx cy and its coefficients), found {len(vals)}", line)
    if model == "pinhole" and len(vals) == 5 and vals[4] != 0:
        raise DataError(path, f"a Pinhole line's fifth number must be 0, got {vals[4]:g} (a lens with omega is 'FOV ...')", line)
    return model, vals


def _dso_size(path, entry: tuple[int, str] | None, image_path) -> tuple[int, int]:
    """``width height`` of a camera.txt line, or the first image's size when there is none."""
    if entry is None:
        img = read_image_gray(image_path)
        return img.shape[1], img.shape[0]
    line, text = entry
    vals = _dso_numbers(path, text.split(), line, "'width height'")
    if len(vals) != 2 or any(v != int(v) or v <= 0 for v in vals):
        raise DataError(path, f"expected 'width height' (two whole numbers > 0), found '{text[:60]}'", line)
    return int(vals[0]), int(vals[1])


def _relative(vals: list[float], width: int, height: int) -> list[float]:
    """fx fy cx cy in pixels: DSO's relative intrinsics (fractions of the image size, pixel corner
    origin) when cx and cy are both below 1, else as written."""
    fx, fy, cx, cy = vals[:4]
    if cx < 1 and cy < 1:
        return [fx * width, fy * height, cx * width - 0.5, cy * height - 0.5]
    return [fx, fy, cx, cy]


def _dso_output(path, entry: tuple[int, str] | None, width: int, height: int):
    """camera.txt's third line: "crop" (also when absent), "none", or pinhole intrinsics
    ``fx fy cx cy 0`` at the output size; "full" (undefined black borders) is refused."""
    if entry is None:
        return "crop"
    line, text = entry
    if text in ("crop", "none"):
        return text
    if text == "full":
        raise DataError(path, "output 'full' leaves black borders that the tracker would take for edges; use 'crop' or 'fx fy cx cy 0'", line)
    vals = _dso_numbers(path, text.split(), line, "'crop', 'none' or 'fx fy cx cy 0'")
    if len(vals) != 5 or vals[4] != 0:
        raise DataError(path, f"expected 'crop', 'none' or 'fx fy cx cy 0', found '{text[:60]}'", line)
    return _relative(vals, width, height)


def read_dso_camera(path, image_path) -> Undistorter:
    """DSO's ``camera.txt``: line 1 ``[Model] fx fy cx cy [coefficients]`` (Pinhole, RadTan k1 k2 p1
    p2, EquiDistant or KannalaBrandt k1..k4, FOV ω), line 2 ``width height`` (default: the size of
    ``image_path``), line 3 the pinhole camera to undistort to (``crop``, the default; ``none``;
    ``fx fy cx cy 0``), line 4 its ``width height`` (default: the input's). Intrinsics below 1 (cx
    and cy) are relative to the image size, as DSO writes them."""
    path = pathlib.Path(path)
    lines = data_lines(path, "camera.txt")
    if not lines:
        raise DataError(path, "empty camera.txt")
    entry = lambda i: lines[i] if len(lines) > i else None
    model, vals = _dso_model(path, lines[0][1], lines[0][0])
    w, h = _dso_size(path, entry(1), image_path)
    out_w, out_h = _dso_size(path, entry(3), image_path) if entry(3) else (w, h)
    output = _dso_output(path, entry(2), out_w, out_h)
    lens = camera_model(path, model, _relative(vals, w, h), w, h, vals[4:] if model != "pinhole" else (), lines[0][0])
    return undistorter(lens, output, out_w, out_h, where=path, line=(entry(2) or lines[0])[0])
