"""Lens models of the loaders' datasets and their undistortion into a pinhole camera at load.

A :class:`CameraModel` is a camera as its calibration file describes it: ``pinhole``; ``radtan``
(OpenCV's radial-tangential, k1 k2 p1 p2 [k3]: EuRoC ``radial-tangential``, TUM fr1/fr2, DSO
``RadTan``); ``equidistant`` (Kannala-Brandt, OpenCV's fisheye, k1..k4: EuRoC ``equidistant``,
DSO ``EquiDistant``/``KannalaBrandt``); ``fov`` (Devernay-Faugeras, ω: DSO ``FOV``). An
:class:`Undistorter` resamples each image (bilinear) and depth map (nearest) once, with OpenCV's
maps (``cv2.initUndistortRectifyMap``, ``cv2.fisheye.initUndistortRectifyMap``; FOV: its own
formula), into the pinhole camera the rest of the program uses: by default the largest rectangle
of the undistorted view that the image covers entirely (no undefined border), at the image's size.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from ..errors import DataError
from ..geometry.camera import PinholeCamera
from ..io import checked_camera

__all__ = ["CameraModel", "Undistorter", "COEFFICIENTS", "camera_model", "distort_points", "fov_distort_radius",
           "fov_undistort_radius", "crop_intrinsics", "undistortion_maps", "undistorter"]

# The number of coefficients each model takes.
COEFFICIENTS = {"pinhole": (0,), "radtan": (4, 5), "equidistant": (4,), "fov": (1,)}


@dataclasses.dataclass(frozen=True)
class CameraModel:
    """A calibrated camera before undistortion: ``model`` (a key of ``COEFFICIENTS``), intrinsics
    fx fy cx cy (pixels, pixel centres at integer coordinates), image size, and the model's
    coefficients (radtan: k1 k2 p1 p2 [k3]; equidistant: k1 k2 k3 k4; fov: ω in radians)."""

    model: str
    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int
    coeffs: tuple[float, ...] = ()

    def K(self) -> np.ndarray:
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    def describe(self) -> dict:
        """What a run records: the model and, for a lens model, its coefficients and the intrinsics
        and size it was calibrated at (the images are undistorted at load)."""
        if self.model == "pinhole":
            return {"model": "pinhole"}
        return {"model": self.model, "coefficients": [float(c) for c in self.coeffs],
                "intrinsics": [float(v) for v in (self.fx, self.fy, self.cx, self.cy)], "size": [self.width, self.height]}


def camera_model(where, model: str, intrinsics, width, height, coeffs=(), line: int | None = None) -> CameraModel:
    """A checked :class:`CameraModel`: the intrinsics as :func:`~mbavo_jax.io.checked_camera` wants
    them, the model's coefficient count, finite coefficients, 0 < ω < π; a DataError naming ``where``
    and ``line`` otherwise. A radtan or fov model with all coefficients zero is the pinhole model."""
    intrinsics = tuple(float(v) for v in intrinsics)
    checked_camera(where, *intrinsics, width, height, line)
    coeffs = tuple(float(c) for c in coeffs)
    if len(coeffs) not in COEFFICIENTS[model]:
        counts = " or ".join(str(n) for n in COEFFICIENTS[model])
        raise DataError(where, f"the {model} model takes {counts} distortion coefficients, found {len(coeffs)}", line)
    if not np.all(np.isfinite(coeffs)):
        raise DataError(where, f"a {model} distortion coefficient is not finite: {list(coeffs)}", line)
    if model == "fov" and not 0 <= coeffs[0] < np.pi:
        raise DataError(where, f"the FOV model's omega must be in [0, pi) radians, got {coeffs[0]:g}", line)
    if model in ("radtan", "fov") and not any(coeffs):
        model, coeffs = "pinhole", ()
    return CameraModel(model, *intrinsics, int(width), int(height), coeffs)


def fov_distort_radius(r: np.ndarray, omega: float) -> np.ndarray:
    """The FOV model (Devernay and Faugeras 2001): the distorted radius
    r_d = arctan(2 r tan(ω/2)) / ω of undistorted normalised radii ``r``."""
    return np.arctan(2.0 * r * np.tan(omega / 2.0)) / omega


def fov_undistort_radius(rd: np.ndarray, omega: float) -> np.ndarray:
    """The inverse of :func:`fov_distort_radius`: r = tan(r_d ω) / (2 tan(ω/2)), for r_d ω < π/2."""
    return np.tan(rd * omega) / (2.0 * np.tan(omega / 2.0))


def _fov_factor(r: np.ndarray, omega: float) -> np.ndarray:
    """r_d / r of the FOV model, its limit 2 tan(ω/2) / ω at r = 0."""
    safe = np.where(r > 1e-12, r, 1.0)
    return np.where(r > 1e-12, fov_distort_radius(safe, omega) / safe, 2.0 * np.tan(omega / 2.0) / omega)


def distort_points(cam: CameraModel, xy: np.ndarray) -> np.ndarray:
    """Pixels (N, 2) of the input image where ``cam`` sees the normalised pinhole points ``xy`` (N, 2)
    (the rays (x, y, 1)): OpenCV's projection for radtan and equidistant, the closed form for fov."""
    import cv2

    xy = np.asarray(xy, np.float64).reshape(-1, 2)
    if cam.model == "radtan":
        rays = np.concatenate([xy, np.ones((len(xy), 1))], 1).reshape(-1, 1, 3)
        return cv2.projectPoints(rays, np.zeros(3), np.zeros(3), cam.K(), np.array(cam.coeffs))[0].reshape(-1, 2)
    if cam.model == "equidistant":
        return cv2.fisheye.distortPoints(xy.reshape(-1, 1, 2), cam.K(), np.array(cam.coeffs)).reshape(-1, 2)
    if cam.model == "fov":
        xy = xy * _fov_factor(np.linalg.norm(xy, axis=1), cam.coeffs[0])[:, None]
    return xy * [cam.fx, cam.fy] + [cam.cx, cam.cy]


def _inside(cam: CameraModel, uv: np.ndarray) -> np.ndarray:
    """Whether each pixel (N, 2) lies in the input image (pixel centres 0 .. size - 1)."""
    ok = np.all(np.isfinite(uv), axis=1)
    u, v = np.nan_to_num(uv[:, 0], nan=-1.0), np.nan_to_num(uv[:, 1], nan=-1.0)
    return ok & (u >= 0) & (u <= cam.width - 1) & (v >= 0) & (v <= cam.height - 1)


def _axis_reach(cam: CameraModel, direction: tuple[float, float], far: float, steps: int = 4000) -> float:
    """How far along ``direction`` from the optical axis (normalised units, up to ``far``) the rays
    stay inside the image: the last sample before the first one outside."""
    t = np.linspace(0.0, far, steps + 1)[1:]
    ok = _inside(cam, distort_points(cam, t[:, None] * np.asarray(direction, np.float64)))
    first_out = int(np.argmin(ok)) if not ok.all() else len(t)
    return float(t[first_out - 1]) if first_out > 0 else 0.0


def _sides_outside(cam: CameraModel, box: np.ndarray, width: int, height: int) -> np.ndarray:
    """For the normalised rectangle ``box`` [x0, x1, y0, y1] sampled at the output's pixels: whether
    its left, right, top and bottom side has a ray outside the input image."""
    ys, xs = np.linspace(box[2], box[3], height), np.linspace(box[0], box[1], width)
    sides = [np.c_[np.full(height, box[0]), ys], np.c_[np.full(height, box[1]), ys],
             np.c_[xs, np.full(width, box[2])], np.c_[xs, np.full(width, box[3])]]
    return np.array([not _inside(cam, distort_points(cam, s)).all() for s in sides])


def _box_intrinsics(box: np.ndarray, width: int, height: int) -> tuple[float, float, float, float]:
    """fx fy cx cy that map the normalised rectangle ``box`` [x0, x1, y0, y1] onto the pixel centres
    0 .. width - 1 and 0 .. height - 1."""
    fx, fy = (width - 1) / (box[1] - box[0]), (height - 1) / (box[3] - box[2])
    return float(fx), float(fy), float(-box[0] * fx), float(-box[2] * fy)


def crop_intrinsics(cam: CameraModel, width: int, height: int, where="camera", shrink: float = 0.995):
    """fx fy cx cy of the pinhole camera of size ``width`` x ``height`` whose every pixel ``cam`` sees
    inside its image, and that sees no wider than ``cam``'s own intrinsics do (the centre keeps its
    resolution): the view of those intrinsics cut where the axes leave the image, its sides then
    drawn in (by ``shrink``) while a ray on them falls outside; the full maps checked last."""
    view = np.array([-cam.cx / cam.fx, (cam.width - 1 - cam.cx) / cam.fx, -cam.cy / cam.fy, (cam.height - 1 - cam.cy) / cam.fy])
    box = np.array([-_axis_reach(cam, (-1, 0), -view[0]), _axis_reach(cam, (1, 0), view[1]),
                    -_axis_reach(cam, (0, -1), -view[2]), _axis_reach(cam, (0, 1), view[3])])
    if np.any(box[[1, 3]] <= 0) or np.any(box[[0, 2]] >= 0):
        raise DataError(where, f"the {cam.model} camera sees no region around its principal point inside the image")
    for _ in range(3000):
        out = _sides_outside(cam, box, width, height)
        if not out.any():
            intrinsics = _box_intrinsics(box, width, height)
            mx, my = undistortion_maps(cam, intrinsics, width, height)
            if _inside(cam, np.c_[mx.ravel(), my.ravel()]).all():
                return intrinsics
            out = np.ones(4, bool)  # a fold inside the rectangle: draw every side in
        box = np.where(out, box * shrink, box)
    raise DataError(where, f"found no pinhole camera that the {cam.model} image covers (check the distortion coefficients)")


def undistortion_maps(cam: CameraModel, intrinsics, width: int, height: int) -> tuple[np.ndarray, np.ndarray]:
    """(map_x, map_y) float32 (height, width): the input pixel each pixel of the pinhole camera
    ``intrinsics`` (fx fy cx cy) samples, for ``cv2.remap``."""
    import cv2

    fx, fy, cx, cy = intrinsics
    K_out = np.array([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])
    D = np.array(cam.coeffs, np.float64)
    if cam.model == "radtan":
        return cv2.initUndistortRectifyMap(cam.K(), D, None, K_out, (width, height), cv2.CV_32FC1)
    if cam.model == "equidistant":
        return cv2.fisheye.initUndistortRectifyMap(cam.K(), D, np.eye(3), K_out, (width, height), cv2.CV_32FC1)
    u, v = np.meshgrid(np.arange(width, dtype=np.float64), np.arange(height, dtype=np.float64))
    xy = np.c_[((u - cx) / fx).ravel(), ((v - cy) / fy).ravel()]
    uv = distort_points(cam, xy).astype(np.float32)
    return uv[:, 0].reshape(height, width), uv[:, 1].reshape(height, width)


@dataclasses.dataclass(frozen=True)
class Undistorter:
    """Resamples the images of ``lens`` into the pinhole ``camera``; ``maps`` (map_x, map_y) or None
    when the two are the same camera (nothing to do)."""

    lens: CameraModel
    camera: PinholeCamera
    maps: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def input_shape(self) -> tuple[int, int]:
        """(height, width) of the images it takes."""
        return self.lens.height, self.lens.width

    def image(self, image: np.ndarray) -> np.ndarray:
        """``image`` in the pinhole camera (bilinear; 0 where the lens saw nothing)."""
        import cv2

        if self.maps is None:
            return image
        return cv2.remap(image, *self.maps, cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0.0)

    def depth(self, depth: np.ndarray) -> np.ndarray:
        """``depth`` in the pinhole camera (nearest neighbour, never a blend of two surfaces; NaN where
        the lens saw nothing)."""
        import cv2

        if self.maps is None:
            return depth
        return cv2.remap(depth, *self.maps, cv2.INTER_NEAREST, borderMode=cv2.BORDER_CONSTANT, borderValue=float("nan"))


def undistorter(cam: CameraModel, output="crop", width: int | None = None, height: int | None = None,
                where="camera", line: int | None = None) -> Undistorter:
    """The undistortion of ``cam`` into a pinhole camera of ``width`` x ``height`` (default: the
    input's size): ``output`` "crop" (the largest fully covered rectangle, :func:`crop_intrinsics`;
    a pinhole input at its own size is kept as it is), "none" (a pinhole input kept as it is), or
    fx fy cx cy (pixels). DataError naming ``where`` and ``line`` for an output it cannot give."""
    width, height = width or cam.width, height or cam.height
    same_size = (width, height) == (cam.width, cam.height)
    if output == "none" and not (cam.model == "pinhole" and same_size):
        what = "a camera with distortion" if cam.model != "pinhole" else "another output size"
        raise DataError(where, f"output 'none' (no rectification) does not work with {what}; use 'crop' or 'fx fy cx cy 0'", line)
    if output in ("crop", "none") and cam.model == "pinhole" and same_size:
        camera = checked_camera(where, cam.fx, cam.fy, cam.cx, cam.cy, width, height, line)
        return Undistorter(cam, camera, None)
    intrinsics = crop_intrinsics(cam, width, height, where) if output == "crop" else tuple(float(v) for v in output)
    camera = checked_camera(where, *intrinsics, width, height, line)
    return Undistorter(cam, camera, undistortion_maps(cam, intrinsics, width, height))
