"""Sequence folders that are wrong, or right in a way the loaders used to misread.

Bad folders (a malformed EuRoC ``T_BS``, an empty or gapped KITTI ``image_0/``, a ``poses.txt``
of the wrong length, exposures outside 0 .. the frame interval, YAML booleans where numbers
belong, lens models we do not support) must give one line ``mbavo: error: FILE[:LINE]: ...`` and
exit 1. Good folders must be read as they are meant: images in natural order (``frame2`` before
``frame10``), and lenses with distortion (radial-tangential, equidistant, FOV; DSO's camera.txt,
EuRoC's sensor.yaml, TUM fr1/fr2) undistorted at load: a point drawn where OpenCV's projection (or
the FOV model's closed form) puts it lands where the pinhole camera of the sequence puts it.
Every folder is a few tiny files written in ``tmp_path``.
"""

from __future__ import annotations

import pathlib

import cv2
import numpy as np
import pytest

from mbavo_jax.datasets import open_sequence

from .conftest import shared_dataset

W, H = 160, 120


# ------------------------------------------------------------------------------ writing folders


def gray(path: pathlib.Path, image: np.ndarray) -> None:
    """Write ``image`` (values in [0, 1]) as a 16-bit PNG."""
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), np.round(np.clip(image, 0, 1) * 65535).astype(np.uint16))


def flat(value: float = 0.5, shape=(H, W)) -> np.ndarray:
    return np.full(shape, value, np.float32)


def kitti(root: pathlib.Path, n: int = 5, times: int | None = None, poses: int | None = None) -> pathlib.Path:
    """A KITTI layout: ``image_0/`` with n frames, ``times.txt`` (``times`` rows, default n),
    ``calib.txt``, and ``poses.txt`` with ``poses`` rows when given."""
    for i in range(n):
        gray(root / "image_0" / f"{i:06d}.png", flat(0.1 + 0.05 * i))
    (root / "times.txt").write_text("".join(f"{0.1 * i:.6e}\n" for i in range(times or n)))
    (root / "calib.txt").write_text("P0: 100 0 79.5 0 0 100 59.5 0 0 0 1 0\n")
    if poses is not None:
        (root / "poses.txt").write_text("".join(f"1 0 0 0 0 1 0 0 0 0 1 {0.5 * i}\n" for i in range(poses)))
    return root


def euroc(root: pathlib.Path, sensor: str, image: np.ndarray | None = None) -> pathlib.Path:
    """An EuRoC layout of one frame (``image``, default flat) with ``sensor.yaml`` holding ``sensor``."""
    cam = root / "mav0" / "cam0"
    gray(cam / "data" / "1403636579763555584.png", flat() if image is None else image)
    (cam / "data.csv").write_text("#timestamp [ns],filename\n1403636579763555584,1403636579763555584.png\n")
    (cam / "sensor.yaml").write_text("%YAML:1.0\nsensor_type: camera\n" + sensor)
    return root


EUROC_SENSOR = f"resolution: [{W}, {H}]\nintrinsics: [100.0, 101.0, 79.5, 59.5]\n"
T_BS_OK = "T_BS:\n  cols: 4\n  rows: 4\n  data: [1,0,0,0.1, 0,1,0,0, 0,0,1,0, 0,0,0,1]\n"


def dso(root: pathlib.Path, camera_txt: str, images: list[np.ndarray] | None = None, times: str | None = None,
        depth: list[np.ndarray] | None = None) -> pathlib.Path:
    """A DSO layout: ``images/`` (default: one flat frame), ``times.txt`` (default: ``i t``),
    ``camera.txt`` holding ``camera_txt``, ``depth/`` (16-bit, 5000 per metre) when given."""
    images = images if images is not None else [flat()]
    for i, img in enumerate(images):
        gray(root / "images" / f"{i:05d}.png", img)
    if depth is not None:
        (root / "depth").mkdir()
        for i, d in enumerate(depth):
            cv2.imwrite(str(root / "depth" / f"{i:05d}.png"), np.round(np.nan_to_num(d) * 5000).astype(np.uint16))
    (root / "times.txt").write_text(times if times is not None else "".join(f"{i} {1.0 + i / 30:.6f}\n" for i in range(len(images))))
    (root / "camera.txt").write_text(camera_txt)
    return root


def folder(root: pathlib.Path, names: list[str], camera_yaml: str = "") -> pathlib.Path:
    """A plain image folder: one image per name (image k has grey level k/100), and camera.yaml."""
    for k, name in enumerate(names):
        gray(root / name, flat(k / 100.0))
    (root / "camera.yaml").write_text(f"fx: 100\nfy: 100\ncx: 79.5\ncy: 59.5\nwidth: {W}\nheight: {H}\n" + camera_yaml)
    return root


def tum(root: pathlib.Path, camera_yaml: str | None, n: int = 3, fps: float = 30.0, image: np.ndarray | None = None) -> pathlib.Path:
    """A TUM layout of n frames at ``fps`` (``camera_yaml`` None: no camera.yaml; the folder name
    then says which TUM camera took it)."""
    stamps = [10.0 + k / fps for k in range(n)]
    for t in stamps:
        gray(root / "rgb" / f"{t:.6f}.png", flat() if image is None else image)
    (root / "rgb.txt").write_text("# timestamp filename\n" + "".join(f"{t:.6f} rgb/{t:.6f}.png\n" for t in stamps))
    if camera_yaml is not None:
        (root / "camera.yaml").write_text(camera_yaml)
    return root


def one_line_error(mbavo, root: pathlib.Path, *expect: str, check: bool = False) -> str:
    """Run ``mbavo info ROOT`` and return its error line, asserting exit 1, one line holding each of
    ``expect``, and no traceback."""
    r = mbavo("info", root, *(["--check", "-q"] if check else []))
    lines = r.stderr.splitlines()
    assert r.returncode == 1, (r.returncode, r.stdout, r.stderr)
    assert len(lines) == 1 and lines[0].startswith("mbavo: error: "), r.stderr
    assert "Traceback" not in r.stderr and r.stdout == "", (r.stdout, r.stderr)
    for e in expect:
        assert e in lines[0], (e, lines[0])
    return lines[0]


# ------------------------------------------------------------------------ 6. EuRoC sensor.yaml


@pytest.mark.parametrize("t_bs", [
    "T_BS: [1, 0, 0, 0]\n",
    "T_BS:\n  data: [1, 0, 0]\n",
    "T_BS:\n  data: [a, b, c, d, e, f, g, h, i, j, k, l, m, n, o, p]\n",
    "T_BS:\n  data: 7\n",
    "T_BS:\n  data: [true,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]\n",
    "T_BS:\n  data: [2,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]\n",
    "T_BS:\n  rows: 3\n  data: [1,0,0,0, 0,1,0,0, 0,0,1,0, 0,0,0,1]\n",
], ids=["list", "short", "text", "number", "boolean", "not_rigid", "rows"])
def test_euroc_malformed_T_BS_is_one_line_naming_the_file_and_key(tmp_path, mbavo, t_bs):
    root = euroc(tmp_path / "euroc", EUROC_SENSOR + t_bs)
    one_line_error(mbavo, root, "sensor.yaml", "T_BS")


@pytest.mark.parametrize("sensor, expect", [
    ("resolution: [160, 120]\nintrinsics: [true, 100.0, 79.5, 59.5]\n", "'intrinsics' entry 1 is not a number: True"),
    ("resolution: [160.5, 120]\nintrinsics: [100.0, 100.0, 79.5, 59.5]\n", "'resolution' must be two whole numbers"),
    ("resolution: [160, 120]\nintrinsics: [100.0, 100.0, 79.5]\n", "'intrinsics' must be a list of 4 numbers"),
    ("resolution: [160, 120]\n", "missing key(s): intrinsics"),
    (EUROC_SENSOR + "distortion_model: omni\ndistortion_coefficients: [0.1]\n", "distortion_model 'omni' is not supported"),
    (EUROC_SENSOR + "camera_model: omni\n", "camera_model 'omni' is not supported"),
    (EUROC_SENSOR + "distortion_model: radial-tangential\ndistortion_coefficients: [0.1, 0.2, 0.3]\n",
     "the radtan model takes 4 or 5 distortion coefficients, found 3"),
    (EUROC_SENSOR + "distortion_model: equidistant\ndistortion_coefficients: [0.1, .nan, 0, 0]\n", "is not finite"),
], ids=["bool_intrinsics", "half_pixel", "three_intrinsics", "no_intrinsics", "unknown_distortion", "unknown_camera",
        "radtan_count", "nan_coefficient"])
def test_euroc_other_malformed_sensor_yaml_is_one_line(tmp_path, mbavo, sensor, expect):
    root = euroc(tmp_path / "euroc", sensor)
    one_line_error(mbavo, root, "sensor.yaml", expect)


# ------------------------------------------------------------------------------------ 7, 8, 13. KITTI


def test_kitti_empty_image_folder_is_one_line(tmp_path, mbavo):
    root = kitti(tmp_path / "kitti", n=3)
    for p in (root / "image_0").iterdir():
        p.unlink()
    one_line_error(mbavo, root, "image_0", "no images")


@pytest.mark.parametrize("poses", [3, 7])
def test_kitti_poses_of_another_length_than_the_images_are_refused_when_opened(tmp_path, mbavo, poses):
    """poses.txt holds one pose per frame: a shorter or longer file is an error when the sequence is
    opened (it used to surface as an IndexError in the evaluation after the whole run)."""
    root = kitti(tmp_path / "kitti", n=5, poses=poses)
    one_line_error(mbavo, root, "poses.txt", f"{poses} poses", "5 images")


def test_kitti_clip_of_a_longer_sequence_keeps_the_poses_of_its_frames(tmp_path):
    """A clip (its first 5 images) that keeps the whole sequence's times.txt and poses.txt (8 rows):
    the ground truth is the clip's 5 poses at the clip's 5 timestamps."""
    seq = open_sequence(kitti(tmp_path / "kitti", n=5, times=8, poses=8))
    stamps, poses = seq.groundtruth
    assert len(seq) == 5 and stamps.shape == (5,) and poses.shape == (5, 7)
    np.testing.assert_allclose(poses[:, 2], 0.5 * np.arange(5))


def test_kitti_missing_frame_is_an_error_naming_the_first_missing_index(tmp_path, mbavo):
    """KITTI names are frame indices: without 000005.png frame 6 would be read as frame 5 and take its
    timestamp (every later frame shifted)."""
    root = kitti(tmp_path / "kitti", n=10)
    (root / "image_0" / "000005.png").unlink()
    (root / "image_0" / "000007.png").unlink()
    one_line_error(mbavo, root, "image_0", "frame 000005 is missing")


def test_kitti_image_names_must_be_frame_indices(tmp_path, mbavo):
    root = kitti(tmp_path / "kitti", n=3)
    (root / "image_0" / "000001.png").rename(root / "image_0" / "frame1.png")
    one_line_error(mbavo, root, "frame1.png", "not a KITTI frame index name")


# ------------------------------------------------------------------------------ 14. natural order


def test_image_folder_numbers_sort_as_numbers(tmp_path):
    names = [f"frame{k}.png" for k in range(12)]
    seq = open_sequence(folder(tmp_path / "imgs", names[::-1]))
    assert [pathlib.Path(seq[k].path).name for k in range(12)] == names


def test_dso_images_sort_as_numbers(tmp_path):
    root = dso(tmp_path / "dso", f"Pinhole 100 100 79.5 59.5 0\n{W} {H}\n", images=[flat(k / 20) for k in range(11)])
    for k in range(11):
        (root / "images" / f"{k:05d}.png").rename(root / "images" / f"img_{k}.png")
    seq = open_sequence(root)
    assert [pathlib.Path(seq[k].path).name for k in range(11)] == [f"img_{k}.png" for k in range(11)]
    assert [round(float(seq[k].image.mean()) * 20) for k in range(11)] == list(range(11))


# ------------------------------------------------------------------------- 16. exposure times


@pytest.mark.parametrize("exposure, expect", [
    ("5000", "exposure must be at most the frame interval 33.33 ms (the time between frames), got 5000 ms"),
    ("-25", "exposure must be >= 0 ms, got -25"),
])
def test_times_txt_exposure_outside_the_frame_interval_is_one_line_naming_the_line(tmp_path, mbavo, exposure, expect):
    lines = [f"{i} {1.0 + i / 30:.6f} 20.0" for i in range(3)]
    lines[1] = f"1 {1.0 + 1 / 30:.6f} {exposure}"
    root = dso(tmp_path / "dso", f"Pinhole 100 100 79.5 59.5 0\n{W} {H}\n", images=[flat()] * 3, times="\n".join(lines) + "\n")
    one_line_error(mbavo, root, "times.txt:2", expect)


def test_exposure_equal_to_the_frame_interval_and_zero_are_accepted(tmp_path):
    """The bounds themselves: 0 (a sharp, instantaneous exposure) and the whole frame interval."""
    times = "".join(f"{i} {1.0 + i / 30:.6f} {e}\n" for i, e in enumerate(["0", "33.333", "33.4"]))
    seq = open_sequence(dso(tmp_path / "dso", f"Pinhole 100 100 79.5 59.5 0\n{W} {H}\n", images=[flat()] * 3, times=times))
    np.testing.assert_allclose(seq.exposures, [0.0, 0.033333, 0.0334])


@pytest.mark.parametrize("layout", ["folder_fps", "folder_default_fps", "tum_stamps"])
def test_camera_yaml_exposure_longer_than_the_frame_interval_is_refused(tmp_path, mbavo, layout):
    """The same rule for camera.yaml's exposure_ms: against its fps, the default 30 fps of an image
    folder, or the interval of a TUM sequence's timestamps."""
    cam = f"fx: 100\nfy: 100\ncx: 79.5\ncy: 59.5\nwidth: {W}\nheight: {H}\n"
    if layout == "folder_fps":
        root = folder(tmp_path / "imgs", ["a.png", "b.png"], "fps: 30\nexposure_ms: 5000\n")
    elif layout == "folder_default_fps":
        root = folder(tmp_path / "imgs", ["a.png", "b.png"], "exposure_ms: 50\n")
    else:
        root = tum(tmp_path / "tum", cam + "exposure_ms: 50\n", fps=30.0)
    one_line_error(mbavo, root, "camera.yaml", "camera key 'exposure_ms' must be at most the frame interval 33.33 ms")


# ------------------------------------------------------------------- 19. booleans are not numbers


@pytest.mark.parametrize("line, expect", [
    ("fps: true", "camera key 'fps' is not a number: True"),
    ("exposure_ms: false", "camera key 'exposure_ms' is not a number: False"),
    ("fx: true", "camera key 'fx' is not a number: True"),
    ("depth_scale: true", "camera key 'depth_scale' is not a number: True"),
    ("depth_sigma: [true, 0.001]", "depth_sigma must be [a > 0, b >= 0]"),
])
def test_camera_yaml_boolean_is_not_a_number(tmp_path, mbavo, line, expect):
    key = line.split(":")[0]
    base = [ln for ln in f"fx: 100\nfy: 100\ncx: 79.5\ncy: 59.5\nwidth: {W}\nheight: {H}".splitlines() if not ln.startswith(key)]
    root = folder(tmp_path / "imgs", ["a.png", "b.png"])
    (root / "camera.yaml").write_text("\n".join(base + [line]) + "\n")
    one_line_error(mbavo, root, "camera.yaml", expect)



# ----------------------------------------------------------------- 15. lenses undistorted at load


def rays(fx: float, fy: float, cx: float, cy: float, fractions=(0.25, 0.5, 0.75)) -> np.ndarray:
    """Normalised rays (N, 2) through a grid of pixels (``fractions`` of the image) of the camera fx fy cx cy."""
    u, v = np.meshgrid([f * (W - 1) for f in fractions], [f * (H - 1) for f in fractions])
    return np.c_[(u.ravel() - cx) / fx, (v.ravel() - cy) / fy]


def opencv_radtan(K, coeffs, xy: np.ndarray) -> np.ndarray:
    """Pixels where OpenCV's radial-tangential model sees the rays ``xy``."""
    pts = np.c_[xy, np.ones(len(xy))].reshape(-1, 1, 3)
    return cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.array(K, float), np.array(coeffs, float))[0].reshape(-1, 2)


def opencv_equidistant(K, coeffs, xy: np.ndarray) -> np.ndarray:
    """Pixels where OpenCV's fisheye (equidistant, Kannala-Brandt) model sees the rays ``xy``."""
    pts = np.c_[xy, np.ones(len(xy))].reshape(-1, 1, 3)
    return cv2.fisheye.projectPoints(pts, np.zeros(3), np.zeros(3), np.array(K, float), np.array(coeffs, float))[0].reshape(-1, 2)


def fov_closed_form(K, coeffs, xy: np.ndarray) -> np.ndarray:
    """Pixels where the FOV model (Devernay and Faugeras) sees the rays ``xy``: radius
    r_d = arctan(2 r tan(ω/2)) / ω."""
    w = coeffs[0]
    r = np.maximum(np.linalg.norm(xy, axis=1), 1e-12)  # the optical axis: any r_d / r, times 0
    xd = xy * (np.arctan(2 * r * np.tan(w / 2)) / (w * r))[:, None]
    return np.c_[K[0][0] * xd[:, 0] + K[0][2], K[1][1] * xd[:, 1] + K[1][2]]


def spots(points: np.ndarray, shape=(H, W), sigma: float = 1.5, background: float = 0.25, peak: float = 0.7) -> np.ndarray:
    """A grey ``background`` with a Gaussian spot of height ``peak`` centred at each (sub)pixel point."""
    v, u = np.mgrid[: shape[0], : shape[1]]
    img = np.full(shape, background)
    for pu, pv in points:
        img += peak * np.exp(-((u - pu) ** 2 + (v - pv) ** 2) / (2 * sigma**2))
    return img


def centroid(image: np.ndarray, near: np.ndarray, background: float = 0.25, radius: int = 5) -> np.ndarray:
    """The intensity centroid (above ``background``) of the spot within ``radius`` px of ``near``."""
    u0, v0 = int(round(near[0])), int(round(near[1]))
    win = np.clip(image[v0 - radius : v0 + radius + 1, u0 - radius : u0 + radius + 1] - background, 0, None)
    v, u = np.mgrid[v0 - radius : v0 + radius + 1, u0 - radius : u0 + radius + 1]
    return np.array([(win * u).sum(), (win * v).sum()]) / win.sum()


K_DSO = [[100.0, 0, 79.5], [0, 98.0, 59.5], [0, 0, 1]]
FOV_REL = (0.6, 0.8, 0.5, 0.5)  # DSO's relative intrinsics: fx = 0.6 W, fy = 0.8 H, cx = 0.5 W - 0.5, cy = 0.5 H - 0.5
K_FOV = [[0.6 * W, 0, 0.5 * W - 0.5], [0, 0.8 * H, 0.5 * H - 0.5], [0, 0, 1]]
RADTAN = (-0.3, 0.09, 0.002, -0.003)
RADTAN_PINCUSHION = (0.25, -0.1, 0.001, 0.002, 0.05)
EQUI = (0.06, -0.03, 0.01, -0.004)
K_TUM1 = [[517.3, 0, 318.6], [0, 516.5, 255.3], [0, 0, 1]]
TUM1 = (0.2624, -0.9531, -0.0054, 0.0026, 1.1633)


def _dso_line(name: str, coeffs) -> str:
    k = K_DSO
    return f"{name} {k[0][0]} {k[1][1]} {k[0][2]} {k[1][2]} " + " ".join(str(c) for c in coeffs)


def _euroc_lens(model: str, coeffs) -> str:
    return (f"resolution: [{W}, {H}]\nintrinsics: [{K_DSO[0][0]}, {K_DSO[1][1]}, {K_DSO[0][2]}, {K_DSO[1][2]}]\n"
            f"distortion_model: {model}\ndistortion_coefficients: {list(coeffs)}\n" + T_BS_OK)


# id, layout, its calibration text, the model read, the lens K and coefficients, its projection
LENSES = [
    ("dso_radtan", "dso", _dso_line("RadTan", RADTAN) + f"\n{W} {H}\ncrop\n{W} {H}\n", "radtan", K_DSO, RADTAN, opencv_radtan),
    ("dso_radtan_unnamed", "dso", _dso_line("", RADTAN).strip() + f"\n{W} {H}\n", "radtan", K_DSO, RADTAN, opencv_radtan),
    ("dso_equidistant", "dso", _dso_line("EquiDistant", EQUI) + f"\n{W} {H}\ncrop\n{W} {H}\n", "equidistant", K_DSO, EQUI,
     opencv_equidistant),
    ("dso_kannala_brandt", "dso", _dso_line("KannalaBrandt", EQUI) + f"\n{W} {H}\n", "equidistant", K_DSO, EQUI, opencv_equidistant),
    ("dso_fov_relative", "dso", "FOV " + " ".join(map(str, FOV_REL)) + f" 0.9\n{W} {H}\ncrop\n{W} {H}\n", "fov", K_FOV, (0.9,),
     fov_closed_form),
    ("dso_fov_unnamed", "dso", " ".join(map(str, FOV_REL)) + f" 0.9\n{W} {H}\n", "fov", K_FOV, (0.9,), fov_closed_form),
    ("dso_radtan_to_given_pinhole", "dso", _dso_line("RadTan", RADTAN) + f"\n{W} {H}\n0.9 1.2 0.5 0.5 0\n{W // 2} {H // 2}\n",
     "radtan", K_DSO, RADTAN, opencv_radtan),
    ("euroc_radtan", "euroc", _euroc_lens("radial-tangential", RADTAN), "radtan", K_DSO, RADTAN, opencv_radtan),
    ("euroc_radtan_pincushion", "euroc", _euroc_lens("radtan", RADTAN_PINCUSHION), "radtan", K_DSO, RADTAN_PINCUSHION,
     opencv_radtan),
    ("euroc_equidistant", "euroc", _euroc_lens("equidistant", EQUI), "equidistant", K_DSO, EQUI, opencv_equidistant),
]


def _lens_folder(tmp_path: pathlib.Path, layout: str, text: str, image: np.ndarray) -> pathlib.Path:
    if layout == "dso":
        return dso(tmp_path / "dso", text, images=[image])
    return euroc(tmp_path / "euroc", text, image)


@pytest.mark.parametrize("case", [pytest.param(c, id=c[0]) for c in LENSES])
def test_a_point_seen_through_the_lens_lands_where_the_pinhole_camera_puts_it(tmp_path, case):
    """Spots drawn where the lens model (OpenCV's projection, or the FOV closed form) sees nine rays
    are, after the loader undistorts the image, where the sequence's pinhole camera projects those
    rays (to 0.1 px); the undistorted view has no undefined border; the run records the model."""
    _, layout, text, model, K, coeffs, project = case
    xy = rays(K[0][0], K[1][1], K[0][2], K[1][2])
    seq = open_sequence(_lens_folder(tmp_path, layout, text, spots(project(K, coeffs, xy))))
    cam, frame = seq.camera, seq[0]
    expected = xy * [float(cam.fx), float(cam.fy)] + [float(cam.cx), float(cam.cy)]
    inside = [(4 < u < cam.width - 5) and (4 < v < cam.height - 5) for u, v in expected]
    assert sum(inside) >= 5, expected
    found = np.array([centroid(frame.image, p) for p, ok in zip(expected, inside) if ok])
    np.testing.assert_allclose(found, expected[inside], atol=0.1)
    assert frame.image.shape == (cam.height, cam.width) and frame.image.min() > 0.24  # no black border
    assert seq.camera_model["model"] == model and seq.camera_model["coefficients"] == pytest.approx(list(coeffs))


def test_tum_fr1_is_undistorted_with_its_published_coefficients(tmp_path):
    """A TUM fr1 folder without camera.yaml: the loader knows the camera from the bag's name and
    undistorts with TUM's published radial-tangential coefficients."""
    w, h = 640, 480
    xy = np.c_[np.meshgrid(np.linspace(-0.45, 0.45, 3), np.linspace(-0.35, 0.35, 3))[0].ravel(),
               np.meshgrid(np.linspace(-0.45, 0.45, 3), np.linspace(-0.35, 0.35, 3))[1].ravel()]
    root = tum(tmp_path / "rgbd_dataset_freiburg1_desk", None, n=1, image=spots(opencv_radtan(K_TUM1, TUM1, xy), (h, w)))
    seq = open_sequence(root)
    cam = seq.camera
    expected = xy * [float(cam.fx), float(cam.fy)] + [float(cam.cx), float(cam.cy)]
    np.testing.assert_allclose([centroid(seq[0].image, p) for p in expected], expected, atol=0.1)
    assert seq.camera_model == {"model": "radtan", "coefficients": list(TUM1), "intrinsics": [517.3, 516.5, 318.6, 255.3],
                                "size": [640, 480]}
    assert seq[0].image.min() > 0.24


def test_depth_is_undistorted_by_nearest_neighbour(tmp_path):
    """Depth maps take the same map as the image but never blend two depths: each pixel holds the
    input's depth at the nearest pixel to where the lens sees its ray; no ray outside: no NaN."""
    v, u = np.mgrid[:H, :W]
    depth = (1.0 + 0.01 * u + 0.5 * (v // 10)).astype(np.float32)  # one value per pixel column and band of rows
    root = dso(tmp_path / "dso", _dso_line("RadTan", RADTAN) + f"\n{W} {H}\n", images=[flat()], depth=[depth])
    seq = open_sequence(root)
    got = seq[0].depth
    stored = np.round(depth * 5000) / 5000
    cam = seq.camera
    xy = np.c_[((u.ravel() - float(cam.cx)) / float(cam.fx)), ((v.ravel() - float(cam.cy)) / float(cam.fy))]
    src = np.round(opencv_radtan(K_DSO, RADTAN, xy)).astype(int)
    ok = (src[:, 0] >= 0) & (src[:, 0] < W) & (src[:, 1] >= 0) & (src[:, 1] < H)
    assert ok.all() and not np.isnan(got).any()
    want = stored[src[:, 1], src[:, 0]].reshape(H, W)
    assert np.isin(got, stored).all()  # only values the input holds
    assert np.mean(np.isclose(got, want, atol=1e-4)) > 0.99  # the nearest one (ties at half pixels aside)


def test_fov_model_against_its_inverse_and_its_small_radius_limit():
    from mbavo_jax.datasets.distortion import fov_distort_radius, fov_undistort_radius

    for omega in (0.1, 0.9, 2.0):
        r = np.linspace(0.0, 0.99 * np.tan(np.pi / 2 * 0.999) if omega < 1 else 1.5, 200)
        rd = fov_distort_radius(r, omega)
        np.testing.assert_allclose(fov_undistort_radius(rd, omega), r, rtol=1e-9, atol=1e-12)
        assert np.all(np.diff(rd) > 0)  # monotone: one distorted radius per ray
        small = 1e-6
        assert fov_distort_radius(np.array([small]), omega)[0] / small == pytest.approx(2 * np.tan(omega / 2) / omega, rel=1e-9)


@pytest.mark.parametrize("text, expect", [
    ("Omni 100 100 79.5 59.5 0.5\n", "camera model 'Omni' is not supported"),
    ("RadTan 100 100 79.5 59.5 0.1 0.2\n", "the RadTan model takes 8 numbers"),
    ("FOV 100 100 79.5 59.5 0.9 0.1\n", "the FOV model takes 5 numbers"),
    ("Pinhole 100 100 79.5 59.5 0.9\n", "a Pinhole line's fifth number must be 0"),
    ("100 100 79.5 59.5 0.1 0.2\n", "expected 4, 5 or 8 numbers"),
    ("FOV 100 100 79.5 59.5 4.0\n", "omega must be in [0, pi)"),
    (_dso_line("RadTan", RADTAN) + f"\n{W} {H}\nfull\n{W} {H}\n", "output 'full' leaves black borders"),
    (_dso_line("RadTan", RADTAN) + f"\n{W} {H}\nnone\n{W} {H}\n", "output 'none' (no rectification) does not work"),
    (_dso_line("RadTan", RADTAN) + f"\n{W} {H}\nwide\n", "expected 'crop', 'none' or 'fx fy cx cy 0'"),
], ids=["unknown_model", "radtan_count", "fov_count", "pinhole_omega", "unnamed_count", "fov_omega", "full", "none", "output"])
def test_dso_camera_we_cannot_read_is_one_line(tmp_path, mbavo, text, expect):
    one_line_error(mbavo, dso(tmp_path / "dso", text), "camera.txt", expect)


def test_pinhole_sequences_record_the_pinhole_model(tmp_path):
    seq = open_sequence(folder(tmp_path / "imgs", ["a.png"]))
    assert seq.camera_model == {"model": "pinhole"}
    seq = open_sequence(euroc(tmp_path / "euroc", EUROC_SENSOR + "distortion_model: radial-tangential\n"
                              "distortion_coefficients: [0.0, 0.0, 0.0, 0.0]\n"))
    assert seq.camera_model == {"model": "pinhole"} and float(seq.camera.fx) == 100.0


def test_real_tum_clip_reads_as_fr1_radtan():
    seq = open_sequence(shared_dataset("tum_fr1_xyz_head37"))
    assert seq.camera_model["model"] == "radtan" and seq.camera_model["coefficients"] == list(TUM1)
    assert seq[0].image.shape == (480, 640) and seq[0].depth.shape == (480, 640)
