"""The peers of the benchmarks: Open3D and OpenCV RGB-D odometry between two frames, behind one
adapter (``prepare`` a frame, ``relative_pose`` between two), and a peer's frame-to-frame odometry
chained over a whole sequence (:func:`peer_odometry`)."""

from __future__ import annotations

import pathlib
import time

import jax.numpy as jnp
import numpy as np

from .config import BenchConfig
from .errors import MbavoError
from .geometry import Pose

__all__ = ["import_open3d", "Open3DPeer", "OpenCVPeer", "make_peer", "peer_odometry"]


def import_open3d():
    """Open3D; where the system lacks libusb-1.0 (some builds link it), the copy that the
    libusb-package wheel ships is loaded first."""
    try:
        import open3d
    except (OSError, ImportError) as exc:  # which of the two depends on the Python and Open3D build
        if "libusb" not in str(exc):
            raise
        import ctypes

        import libusb_package

        ctypes.CDLL(str(libusb_package.get_library_path()), mode=ctypes.RTLD_GLOBAL)
        import open3d
    return open3d


class Open3DPeer:
    """Open3D ``compute_rgbd_odometry`` between two RGB-D frames. ``term``: "hybrid" (Open3D's
    default: photometric + geometric ICP on the current frame's depth) or "color" (photometric only)."""

    def __init__(self, camera, term: str = "hybrid", depth_max: float = BenchConfig().peer_depth_max):
        o3d = import_open3d()
        self.o3d = o3d
        self.intrinsic = o3d.camera.PinholeCameraIntrinsic(camera.width, camera.height, float(camera.fx), float(camera.fy),
                                                           float(camera.cx), float(camera.cy))
        self.option = o3d.pipelines.odometry.OdometryOption(depth_max=depth_max)
        self.jacobian = {"hybrid": o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm,
                         "color": o3d.pipelines.odometry.RGBDOdometryJacobianFromColorTerm}[term]()
        self.note = f"Open3D {o3d.__version__} compute_rgbd_odometry ({term} term, depth_max {depth_max:g} m)"

    def prepare(self, image, depth):
        o3d = self.o3d
        color = o3d.geometry.Image(np.ascontiguousarray((np.clip(image, 0, 1) * 255).astype(np.uint8)))
        d = o3d.geometry.Image(np.ascontiguousarray(np.nan_to_num(depth, nan=0.0).astype(np.float32)))
        return o3d.geometry.RGBDImage.create_from_color_and_depth(color, d, depth_scale=1.0, depth_trunc=50.0, convert_rgb_to_intensity=True)

    def relative_pose(self, prev, cur, guess_cur_prev):
        """(ok, T_prev_cur) from ``guess_cur_prev`` (4x4); on failure (or a non-finite result, which
        Open3D can report as a success) the guess's inverse."""
        ok, T_cur_prev, _ = self.o3d.pipelines.odometry.compute_rgbd_odometry(prev, cur, self.intrinsic, guess_cur_prev,
                                                                             self.jacobian, self.option)
        ok = bool(ok) and bool(np.all(np.isfinite(T_cur_prev)))
        return ok, np.linalg.inv(T_cur_prev if ok else guess_cur_prev)


class OpenCVPeer:
    """OpenCV ``cv2.Odometry`` (RGB_DEPTH, COMMON) between two RGB-D frames; it takes no guess."""

    def __init__(self, camera, depth_max: float = BenchConfig().peer_depth_max):
        import cv2

        self.cv2 = cv2
        settings = cv2.OdometrySettings()
        settings.setCameraMatrix(np.asarray(camera.K(), np.float32))
        settings.setMaxDepth(float(depth_max))
        self.odometry = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)
        self.note = f"OpenCV {cv2.__version__} cv2.Odometry RGB_DEPTH (COMMON, max depth {depth_max:g} m)"

    def prepare(self, image, depth):
        gray = (np.clip(image, 0, 1) * 255).astype(np.uint8)
        return np.nan_to_num(depth, nan=0.0).astype(np.float32), self.cv2.cvtColor(gray, self.cv2.COLOR_GRAY2BGR)

    def relative_pose(self, prev, cur, guess_cur_prev):
        """(ok, T_prev_cur); (False, None) on failure."""
        ok, Rt = self.odometry.compute(prev[0], prev[1], cur[0], cur[1])  # Rt · src = dst: T_cur_prev
        if not ok or Rt is None or not np.all(np.isfinite(Rt)):
            return False, None
        return True, np.linalg.inv(Rt)


def make_peer(method: str, camera, depth_max: float):
    """The peer adapter of ``method`` (open3d, open3d_color, opencv); MbavoError when its library is missing."""
    try:
        if method == "opencv":
            return OpenCVPeer(camera, depth_max)
        return Open3DPeer(camera, {"open3d": "hybrid", "open3d_color": "color"}[method], depth_max)
    except (ImportError, OSError) as exc:
        raise MbavoError(f"{method} unavailable: {exc}") from None


def peer_odometry(seq, out: pathlib.Path, peer) -> dict:
    """Frame-to-frame odometry of a peer chained into ``out/trajectory.txt``; a failed frame is
    dropped (no pose) and the chain goes on from the last good frame with constant velocity."""
    from .io import TrajectoryWriter

    out.mkdir(parents=True, exist_ok=True)
    writer = TrajectoryWriter(out / "trajectory.txt")
    T_w = np.eye(4)
    prev = peer.prepare(seq[0].image, seq[0].depth)
    writer.write(seq.timestamps[0], np.asarray(Pose.from_matrix(jnp.asarray(T_w)).to_vector()))
    vel = np.eye(4)  # T_prev_cur of the last step
    drops, ms = 0, []
    for i in range(1, len(seq)):
        frame = seq[i]
        cur = peer.prepare(frame.image, frame.depth)
        guess = np.linalg.inv(vel)
        t0 = time.perf_counter()
        ok, T_prev_cur = peer.relative_pose(prev, cur, guess)
        ms.append(1000 * (time.perf_counter() - t0))
        pose = np.asarray(Pose.from_matrix(jnp.asarray(T_w @ T_prev_cur, jnp.float32)).to_vector()) if ok else None
        if pose is not None and np.all(np.isfinite(pose)):
            vel = T_prev_cur
            T_w = T_w @ vel
            writer.write(seq.timestamps[i], pose)
            prev = cur
        else:
            drops += 1
    writer.close()
    return {"frames": len(seq), "dropped": drops, "median_ms": float(np.median(ms)) if ms else 0.0}
