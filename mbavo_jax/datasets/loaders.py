"""TUM RGB-D, KITTI odometry, EuRoC, DSO-style and plain-folder loaders."""

from __future__ import annotations

import dataclasses
import pathlib
import re
from typing import Callable

import jax.numpy as jnp
import numpy as np

from ..errors import DataError
from ..evaluation.associate import associate
from ..geometry.camera import PinholeCamera
from ..io import (
    check_exposures,
    check_size,
    check_stamps,
    checked_camera,
    data_lines,
    format_stamp,
    read_camera,
    read_depth_png,
    read_exposure_file,
    read_exposure_rows,
    read_file_list,
    read_image_gray,
    read_table,
    read_text,
    read_tum_trajectory,
)
from .base import Frame, Sequence
from .calibration import read_dso_camera, read_euroc_sensor
from .distortion import Undistorter, camera_model, undistorter
from .imu import open_euroc_imu, open_imu

__all__ = ["open_sequence", "open_tum", "open_kitti", "open_euroc", "open_dso", "open_image_folder", "image_files", "natural_key"]

# Intrinsics published by the TUM RGB-D benchmark (ROS default for fr3, calibrated fr1/fr2).
TUM_CAMERAS = {
    "freiburg1": (517.3, 516.5, 318.6, 255.3),
    "freiburg2": (520.9, 521.0, 325.1, 249.7),
    "freiburg3": (535.4, 539.2, 320.1, 247.6),
}
# Their radial-tangential distortion k1 k2 p1 p2 k3 (fr3's images are undistorted already).
TUM_DISTORTION = {
    "freiburg1": (0.2624, -0.9531, -0.0054, 0.0026, 1.1633),
    "freiburg2": (0.2312, -0.7849, -0.0033, -0.0001, 0.9172),
    "freiburg3": (0.0, 0.0, 0.0, 0.0, 0.0),
}
IMAGE_EXT = (".png", ".jpg", ".jpeg", ".pgm", ".bmp", ".tif", ".tiff")


def _first_image_size(path) -> tuple[int, int]:
    img = read_image_gray(path)
    return img.shape[1], img.shape[0]


def natural_key(name: str) -> tuple:
    """Sort key of a file name with its digit runs compared as numbers (``frame2`` before ``frame10``)."""
    parts = re.split(r"(\d+)", name)
    return tuple(int(p) if i % 2 else p for i, p in enumerate(parts)), name


def image_files(folder) -> list[pathlib.Path]:
    """The image files of ``folder`` (by extension), in natural order (:func:`natural_key`)."""
    return sorted((p for p in pathlib.Path(folder).iterdir() if p.suffix.lower() in IMAGE_EXT), key=lambda p: natural_key(p.name))


def _undistorting(load: Callable[[int], Frame], und: Undistorter | None) -> Callable[[int], Frame]:
    """``load`` with each frame's image (bilinear) and depth (nearest) undistorted by ``und`` into its
    pinhole camera, the raw image's size checked against the lens first; ``load`` itself when there
    is nothing to undistort."""
    if und is None or und.maps is None:
        return load

    def undistorted(i: int) -> Frame:
        f = load(i)
        check_size(f.path, f.image, und.input_shape)
        depth = None if f.depth is None else und.depth(f.depth)
        return dataclasses.replace(f, image=und.image(f.image), depth=depth, camera=und.camera)

    return undistorted


def _tum_camera(root: pathlib.Path, rgb_text: str, first_image: pathlib.Path) -> Undistorter:
    """The TUM calibration (intrinsics and distortion) of the ``freiburgN`` camera that rgb.txt's
    header or the folder name names, undistorted to the pinhole camera of the image's size."""
    header = rgb_text[:400] + " " + root.name
    key = next((k for k in TUM_CAMERAS if k in header or k.replace("freiburg", "fr") in header), None)
    if key is None:
        raise DataError(root, "no camera.yaml and no TUM 'freiburgN' camera named in rgb.txt or the folder name")
    w, h = _first_image_size(first_image)
    lens = camera_model(first_image, "radtan", TUM_CAMERAS[key], w, h, TUM_DISTORTION[key])  # the calibration must fit the image
    return undistorter(lens, "crop", where=first_image)


def open_tum(path, camera: PinholeCamera | None = None, max_diff: float = 0.02, depth: bool = True) -> Sequence:
    """TUM RGB-D layout: ``rgb.txt``, optional ``depth.txt`` (associated within ``max_diff`` s; not
    read when ``depth`` is false),
    ``groundtruth.txt``, exposure paths (``groundtruth_exposure.txt``, else ``exposure.txt``; per
    row: ``exposure_rows.txt``) and exposure times (``times.txt``, else camera.yaml's ``exposure_ms``;
    the rolling-shutter readout: camera.yaml's ``readout_ms``, ``Sequence.readout_s``; the IMU: ``imu.txt``
    with camera.yaml's ``imu:`` block, ``Sequence.imu``); camera from ``camera.yaml``
    or the TUM calibration named in ``rgb.txt``'s header / the folder name (freiburg1/2/3; fr1 and fr2
    images and depth undistorted at load with TUM's published coefficients, :func:`_tum_camera`)."""
    root = pathlib.Path(path)
    rgb_text = read_text(root / "rgb.txt", "rgb list")
    rgb = read_file_list(root / "rgb.txt", "rgb list", rgb_text)
    stamps = np.array([s for _, s, _ in rgb])
    names = [n for _, _, n in rgb]
    cam_info: dict = {}
    und = None
    if camera is None:
        if (root / "camera.yaml").is_file():
            camera, cam_info = read_camera(root / "camera.yaml")
        else:
            und = _tum_camera(root, rgb_text, root / names[0])
            camera = und.camera
    raw_shape = und.input_shape if und is not None else (camera.height, camera.width)
    depth_scale = float(cam_info.get("depth_scale", 5000.0))
    depth_names = None
    if depth and (root / "depth.txt").is_file():
        dl = read_file_list(root / "depth.txt", "depth list")
        dstamps = np.array([s for _, s, _ in dl])
        i_rgb, i_depth = associate(stamps, dstamps, max_diff)
        depth_names = [None] * len(stamps)
        for i, j in zip(i_rgb, i_depth):
            depth_names[i] = dl[j][2]
    exposures = None
    if (root / "times.txt").is_file():
        exposures = _dso_times(root / "times.txt", len(stamps))[1]
    elif "exposure_ms" in cam_info:
        exposures = check_exposures(root / "camera.yaml", np.full(len(stamps), cam_info["exposure_ms"]), stamps,
                                    what="camera key 'exposure_ms'") / 1000.0
    gt = read_tum_trajectory(root / "groundtruth.txt") if (root / "groundtruth.txt").is_file() else None
    exp_file = next((root / n for n in ("groundtruth_exposure.txt", "exposure.txt") if (root / n).is_file()), None)
    exp_paths = read_exposure_file(exp_file) if exp_file is not None else None
    exp_rows = read_exposure_rows(root / "exposure_rows.txt") if (root / "exposure_rows.txt").is_file() else None

    def load(i: int) -> Frame:
        img_path = root / names[i]
        img = read_image_gray(img_path)  # its size is checked by Sequence.__getitem__
        depth = None
        if depth_names is not None:
            if depth_names[i] is None:
                raise DataError(root / "depth.txt", f"no depth within {max_diff} s of rgb frame {i} ({format_stamp(stamps[i])})")
            depth = read_depth_png(root / depth_names[i], depth_scale, raw_shape)
        exp = None if exposures is None else float(exposures[i])
        return Frame(i, float(stamps[i]), img, camera, depth, exp, str(img_path))

    return Sequence(root.name, root, camera, stamps, _undistorting(load, und), exposures, gt, exp_paths, depth_names is not None,
                    "tum", cam_info, exposure_rows=exp_rows, lens=None if und is None else und.lens, imu=open_imu(root, cam_info))


def _kitti_camera(calib_path, image_path) -> PinholeCamera:
    for k, line in data_lines(calib_path, "calib.txt"):
        if line.startswith("P0:"):
            vals = line.split()[1:]
            if len(vals) != 12:
                raise DataError(calib_path, f"P0 needs 12 numbers, found {len(vals)}", k)
            try:
                P = np.array([float(v) for v in vals]).reshape(3, 4)
            except ValueError:
                raise DataError(calib_path, "P0 has a value that is not a number", k) from None
            w, h = _first_image_size(image_path)
            return checked_camera(calib_path, P[0, 0], P[1, 1], P[0, 2], P[1, 2], w, h, k)
    raise DataError(calib_path, "no 'P0:' line")


def _kitti_poses(path) -> np.ndarray:
    from ..geometry.quaternion import from_matrix

    rows = []
    for k, vals in read_table(path, 12, "poses.txt (3x4 poses)"):
        T = np.array(vals).reshape(3, 4)
        q = np.asarray(from_matrix(jnp.asarray(T[:, :3])))
        rows.append(np.concatenate([T[:, 3], q]))
    return np.array(rows)


def _kitti_images(folder: pathlib.Path) -> list[pathlib.Path]:
    """The images of KITTI's ``image_0/``, named by their frame index (``000000.png``, ...): frames
    0 .. N-1, none missing (a gap would shift every later frame's timestamp), none twice."""
    files = image_files(folder)
    if not files:
        raise DataError(folder, "no images (KITTI names them by frame index: 000000.png, 000001.png, ...)")
    odd = next((p.name for p in files if not p.stem.isdigit()), None)
    if odd is not None:
        raise DataError(folder / odd, "not a KITTI frame index name (000000.png, 000001.png, ...)")
    by_index: dict[int, pathlib.Path] = {}
    for p in files:
        if int(p.stem) in by_index:
            raise DataError(p, f"a second image of frame {int(p.stem)} (the first: {by_index[int(p.stem)].name})")
        by_index[int(p.stem)] = p
    missing = next((i for i in range(len(files)) if i not in by_index), None)
    if missing is not None:
        raise DataError(folder, f"frame {missing:06d} is missing ({len(files)} images up to frame {max(by_index):06d}); "
                        "KITTI image names are frame indices")
    return [by_index[i] for i in range(len(files))]


def _kitti_groundtruth(root: pathlib.Path, stamps: np.ndarray, n_times: int):
    """Ground truth from ``groundtruth.txt`` (TUM) or ``poses.txt`` (a 3x4 pose per frame: one per
    image, or one per times.txt row when times.txt lists a longer sequence than the images)."""
    if (root / "groundtruth.txt").is_file():
        return read_tum_trajectory(root / "groundtruth.txt")
    if not (root / "poses.txt").is_file():
        return None
    poses = _kitti_poses(root / "poses.txt")
    if len(poses) == len(stamps) or (len(poses) == n_times and n_times > len(stamps)):
        return stamps, poses[: len(stamps)]
    times = f" and times.txt {n_times} rows" if n_times != len(stamps) else ""
    raise DataError(root / "poses.txt", f"{len(poses)} poses but the sequence has {len(stamps)} images{times} (one pose per frame)")


def open_kitti(path) -> Sequence:
    """KITTI odometry: ``calib.txt`` (P0), ``times.txt``, images in ``image_0/`` (official layout,
    named by frame index) or listed in ``rgb.txt``; ground truth from ``poses.txt`` (3x4 rows) or
    ``groundtruth.txt`` (TUM)."""
    root = pathlib.Path(path)
    times = root / "times.txt"
    if not times.is_file():
        raise DataError(times, "times.txt not found")
    rows = list(read_table(times, (1,), times.name))
    stamps, lines = np.array([v[0] for _, v in rows]), [k for k, _ in rows]
    if (root / "image_0").is_dir():
        files = _kitti_images(root / "image_0")
    else:
        files = [root / n for _, _, n in read_file_list(root / "rgb.txt", "rgb list")]
    if len(files) > len(stamps):
        raise DataError(times, f"{len(stamps)} timestamps but {len(files)} images")
    stamps = check_stamps(times, stamps[: len(files)], lines)  # a clip may list the full sequence's times
    camera = _kitti_camera(root / "calib.txt", files[0])
    gt = _kitti_groundtruth(root, stamps, len(rows))

    def load(i):
        return Frame(i, float(stamps[i]), read_image_gray(files[i]), camera, None, None, str(files[i]))

    return Sequence(root.name, root, camera, stamps, load, None, gt, None, False, "kitti")


def open_euroc(path) -> Sequence:
    """EuRoC MAV: ``mav0/cam0/data.csv`` (ns stamps), ``mav0/cam0/sensor.yaml`` (intrinsics,
    resolution, distortion, T_BS: :func:`~mbavo_jax.datasets.calibration.read_euroc_sensor`; the
    images undistorted at load); ground truth ``mav0/state_groundtruth_estimate0/data.csv`` (body poses,
    converted to the camera with T_BS); the IMU of ``mav0/imu0`` when there (``Sequence.imu``)."""
    from ..geometry.pose import Pose

    root = pathlib.Path(path)
    cam_dir = root / "mav0" / "cam0"
    csv = cam_dir / "data.csv"
    if not csv.is_file():
        raise DataError(csv, "EuRoC cam0/data.csv not found")
    stamps, names, lines = [], [], []
    for k, line in data_lines(csv, "EuRoC cam0/data.csv"):
        parts = [p.strip() for p in line.split(",")]
        if len(parts) != 2 or not parts[0].isdigit():
            raise DataError(csv, "expected 'timestamp_ns,filename'", k)
        stamps.append(int(parts[0]) * 1e-9)
        names.append(parts[1])
        lines.append(k)
    stamps = check_stamps(csv, np.array(stamps), lines)
    lens, T_BS = read_euroc_sensor(cam_dir / "sensor.yaml")
    und = undistorter(lens, "crop", where=cam_dir / "sensor.yaml")
    camera = und.camera
    gt = None
    gt_csv = root / "mav0" / "state_groundtruth_estimate0" / "data.csv"
    if gt_csv.is_file():
        rows = _euroc_groundtruth(gt_csv)
        t_gt = rows[:, 0] * 1e-9
        body = [Pose.from_vector(jnp.asarray(np.r_[r[1:4], r[5:8], r[4]])) for r in rows]  # EuRoC stores qw first
        cam = Pose.from_matrix(jnp.asarray(T_BS))
        poses = np.array([np.asarray(b.compose(cam).to_vector()) for b in body])
        gt = (t_gt, poses)

    def load(i):
        p = cam_dir / "data" / names[i]
        return Frame(i, float(stamps[i]), read_image_gray(p), camera, None, None, str(p))

    return Sequence(root.name, root, camera, stamps, _undistorting(load, und), None, gt, None, False, "euroc", lens=und.lens,
                    imu=open_euroc_imu(root, T_BS))


def _euroc_groundtruth(path) -> np.ndarray:
    """The first 8 columns (t [ns], p xyz, q wxyz) of the rows of EuRoC's ground-truth csv."""
    rows = [vals for _, vals in read_table(path, 8, "EuRoC ground truth", at_least=True)]
    if not rows:
        raise DataError(path, "EuRoC ground truth has no rows")
    return np.array(rows)


def _dso_times(path, n_expected=None):
    """(stamps, exposures in s or None) of ``times.txt`` (``id timestamp [exposure_ms]``), each
    exposure checked against the frame interval (:func:`~mbavo_jax.io.exposure_problem`)."""
    path = pathlib.Path(path)
    lines, stamps, exps = [], [], []
    for k, vals in read_table(path, (2, 3), path.name):
        lines.append(k)
        stamps.append(vals[1])
        exps.append(vals[2] if len(vals) == 3 else np.nan)
    stamps = check_stamps(path, np.array(stamps), lines)
    exps = np.array(exps)
    if n_expected is not None and len(stamps) != n_expected:
        raise DataError(path, f"{len(stamps)} entries but the sequence has {n_expected} frames")
    if np.all(np.isnan(exps)):
        return stamps, None
    if np.any(np.isnan(exps)):
        raise DataError(path, "no exposure time on this line, but other lines have one", lines[int(np.flatnonzero(np.isnan(exps))[0])])
    return stamps, check_exposures(path, exps, stamps, lines) / 1000.0


def open_dso(path, depth: bool = True) -> Sequence:
    """DSO-style folder: ``images/`` (natural order), ``times.txt`` (``id timestamp [exposure_ms]``),
    ``camera.txt`` (its lens undistorted at load: :func:`~mbavo_jax.datasets.calibration.read_dso_camera`);
    optional ``depth/`` with the same file names (16-bit, /5000; not read when ``depth`` is false)
    and ``groundtruth.txt``."""
    root = pathlib.Path(path)
    img_dir = root / "images"
    if not img_dir.is_dir():
        raise DataError(img_dir, "DSO images/ folder not found")
    files = image_files(img_dir)
    if not files:
        raise DataError(img_dir, "no images")
    stamps, exposures = _dso_times(root / "times.txt", len(files))
    und = read_dso_camera(root / "camera.txt", files[0])
    camera = und.camera
    depth_dir = root / "depth"
    has_depth = depth and depth_dir.is_dir()
    gt = read_tum_trajectory(root / "groundtruth.txt") if (root / "groundtruth.txt").is_file() else None

    def load(i):
        img = read_image_gray(files[i])  # its size is checked by Sequence.__getitem__ (or by _undistorting)
        depth = read_depth_png(depth_dir / files[i].name, 5000.0, und.input_shape) if has_depth else None
        exp = None if exposures is None else float(exposures[i])
        return Frame(i, float(stamps[i]), img, camera, depth, exp, str(files[i]))

    return Sequence(root.name, root, camera, stamps, _undistorting(load, und), exposures, gt, None, has_depth, "dso",
                    lens=und.lens)


def open_image_folder(path) -> Sequence:
    """A folder of images (natural order: ``frame2`` before ``frame10``) plus ``camera.yaml`` (``fx
    fy cx cy width height``, optional ``fps``, default 30; its values in ``Sequence.meta``, e.g.
    ``readout_ms``)."""
    root = pathlib.Path(path)
    camera, info = read_camera(root / "camera.yaml")
    files = image_files(root)
    if not files:
        raise DataError(root, "no images in folder")
    fps = float(info.get("fps", 30.0))
    stamps = np.arange(len(files)) / fps
    if "exposure_ms" in info:  # within the frame interval of the default 30 fps too
        check_exposures(root / "camera.yaml", [info["exposure_ms"]], stamps, what="camera key 'exposure_ms'")

    def load(i):
        return Frame(i, float(stamps[i]), read_image_gray(files[i]), camera, None, None, str(files[i]))

    return Sequence(root.name, root, camera, stamps, load, None, None, None, False, "folder", info)


DEPTH_KINDS = ("tum", "dso")  # the layouts that can hold depth maps


def open_sequence(path, kind: str = "auto", depth: bool = True) -> Sequence:
    """Open a sequence, detecting its layout unless ``kind`` is tum|kitti|euroc|dso|folder;
    ``depth`` false: its depth maps are not read (a monocular run)."""
    root = pathlib.Path(path)
    if not root.exists():
        raise DataError(root, "sequence folder not found")
    if not root.is_dir():
        raise DataError(root, "not a folder")
    openers = {"tum": open_tum, "kitti": open_kitti, "euroc": open_euroc, "dso": open_dso, "folder": open_image_folder}
    if kind != "auto":
        if kind not in openers:
            raise DataError(root, f"unknown dataset kind '{kind}' (choose from {', '.join(openers)})")
        return openers[kind](root, depth=depth) if kind in DEPTH_KINDS else openers[kind](root)
    if (root / "mav0").is_dir():
        return open_euroc(root)
    if (root / "calib.txt").is_file() and (root / "times.txt").is_file():
        return open_kitti(root)
    if (root / "rgb.txt").is_file():
        return open_tum(root, depth=depth)
    if (root / "images").is_dir() and (root / "times.txt").is_file():
        return open_dso(root, depth=depth)
    if (root / "camera.yaml").is_file():
        return open_image_folder(root)
    raise DataError(root, "unknown sequence layout (expected TUM rgb.txt, KITTI calib.txt+times.txt, EuRoC mav0/, DSO images/+times.txt, or images+camera.yaml)")
