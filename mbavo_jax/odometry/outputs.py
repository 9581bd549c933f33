"""The files of a run, owned by one object: trajectory.txt (mid-exposure, camera-to-world),
exposure.txt (start and end poses), exposure_spline.txt (a cubic path's control poses),
keyframes.txt, frames.csv (one row per frame), keyframes/ (keyframe images, 16-bit, for --resume
and the benchmarks) and triptych_*.png. Every frame's records are written and flushed together."""

from __future__ import annotations

import csv
import pathlib

import cv2
import jax.numpy as jnp
import numpy as np

from ..blur import plane_depths_from_keyframe, render_blurry
from ..geometry import PinholeCamera, Pose, SplineTrajectory
from ..image import delinearize, from_uint16, linearize, to_uint16
from ..io import PlyWriter, TrajectoryWriter
from ..runtime import resident_mb
from .state import ExposureReport, FrameOutcome, Triptych

__all__ = ["RunOutputs", "CSV_COLUMNS", "keyframe_image_path", "read_keyframe_image"]

CSV_COLUMNS = ["index", "timestamp", "status", "rms", "n_finest", "blur_px", "hypothesis", "ms", "keyframe",
               "exposure", "exposure_ms", "exposure_fraction", "sample_s", "sample_weight", "sample_dt_s", "speed_px_s",
               "prev_speed_px_s", "jump_px", "note", "backend_ms", "rss_mb"]
EXPOSURE_HEADER = "timestamp start:tx ty tz qx qy qz qw end:tx ty tz qx qy qz qw (camera-to-world)"
SPLINE_HEADER = "timestamp control poses 0..3 (tx ty tz qx qy qz qw each) of the cubic exposure path (camera-to-world)"


def keyframe_image_path(out: pathlib.Path, stamp: float) -> pathlib.Path:
    return pathlib.Path(out) / "keyframes" / f"{stamp:.6f}.png"


def read_keyframe_image(out: pathlib.Path, stamp: float) -> np.ndarray | None:
    """A keyframe image written by a run (float [0, 1]), or None when missing or unreadable."""
    path = keyframe_image_path(out, stamp)
    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED) if path.is_file() else None
    return None if img is None or img.dtype != np.uint16 or img.ndim != 2 else from_uint16(img)


def _vec(p: Pose) -> np.ndarray:
    return np.asarray(p.to_vector(), np.float32)


def _exposure_cells(e: ExposureReport | None) -> list:
    """How the exposure is had, its value (ms, fraction of the frame interval) after this frame, and
    the sample this frame gave the estimate (exposure s, weight, frame interval s) and its point
    speed since the previous tracked frame, and the previous frame's central speed it completes (both
    kept for pairing); blank: none."""
    if e is None:
        return [""] * 8
    sample = [repr(float(v)) for v in e.sample] if e.sample else ["", "", ""]  # exact, for --resume
    return [e.mode, f"{1000 * e.seconds:.4f}", "" if e.fraction is None else f"{e.fraction:.4f}", *sample,
            "" if e.speed is None else repr(e.speed), "" if e.completed_speed is None else repr(e.completed_speed)]


def _csv_row(o: FrameOutcome) -> list:
    """One frames.csv row; the fit (rms, jump_px) is written exactly, for --resume."""
    if o.result is None and o.status == "keyframe":  # the first frame
        return [o.index, f"{o.timestamp:.6f}", "keyframe", 0.0, 0, 0.0, "", 0.0, 1, *_exposure_cells(o.exposure), "", "", "",
                f"{resident_mb():.1f}"]
    diag = o.result.diagnostics if o.result is not None else {}
    levels = diag.get("levels") or [{}]
    rms = repr(o.fit.rms) if o.fit is not None else f"{diag.get('rms', float('nan')):.5f}"
    jump = "" if o.fit is None or o.fit.jump_px is None else repr(o.fit.jump_px)
    return [o.index, f"{o.timestamp:.6f}", o.status, rms, levels[-1].get("n", 0),
            f"{diag.get('blur_px', 0.0):.2f}", diag.get("hypothesis", ""), f"{1000 * o.track_seconds:.1f}", int(o.new_keyframe is not None),
            *_exposure_cells(o.exposure), jump, "; ".join(filter(None, (o.note, diag.get("implausible") or diag.get("confirmed")))),
            f"{1000 * o.backend_seconds:.1f}" if o.backend_seconds else "", f"{resident_mb():.1f}"]


class RunOutputs:
    """Writers of one run folder. ``append``: continue the files of an earlier run (``--resume``);
    otherwise they start afresh (``folder.clear_run`` removes what else an earlier run left)."""

    def __init__(self, out, camera: PinholeCamera, response_gamma: float, append: bool = False):
        self.out, self.camera, self.gamma, self.append = pathlib.Path(out), camera, response_gamma, append
        self.out.mkdir(parents=True, exist_ok=True)
        self.spline = None
        self.points = PlyWriter(self.out / "points.ply", append=True) if append and (self.out / "points.ply").is_file() else None
        self.triptychs = len(list(self.out.glob("triptych_*.png")))
        self.trajectory = TrajectoryWriter(self.out / "trajectory.txt", append=append)
        self.exposure = TrajectoryWriter(self.out / "exposure.txt", EXPOSURE_HEADER, append=append)
        self.keyframes = TrajectoryWriter(self.out / "keyframes.txt", append=append)
        fresh = not (append and (self.out / "frames.csv").exists())
        self._csv_fh = open(self.out / "frames.csv", "w" if fresh else "a", newline="")
        self._csv = csv.writer(self._csv_fh)
        if fresh:
            self._csv.writerow(CSV_COLUMNS)
            self._csv_fh.flush()

    def write(self, o: FrameOutcome) -> None:
        """All records of one frame: images first, then the text files, each flushed."""
        for stamp, image in o.replaced_images:
            self.save_keyframe_image(stamp, image)
        if o.earlier_keyframe is not None:
            self.save_keyframe_image(o.earlier_keyframe.stamp, o.earlier_keyframe.image)
            self.keyframes.write(o.earlier_keyframe.stamp, _vec(o.earlier_keyframe.T_world_kf))
        if o.points is not None:
            self.write_points(o.points)
        new = o.new_keyframe
        if new is not None:
            self.save_keyframe_image(new.stamp, new.image)
            if new.triptych is not None:
                self.draw_triptych(new.triptych)
        if o.tracked:
            self.trajectory.write(o.timestamp, _vec(o.T_world_mid))
            self.exposure.write(o.timestamp, _vec(o.T_world_start), _vec(o.T_world_end))
            self.write_spline(o)
        if new is not None:
            self.keyframes.write(new.stamp, _vec(new.T_world_kf))
        self._csv.writerow(_csv_row(o))
        self._csv_fh.flush()

    def write_spline(self, o: FrameOutcome) -> None:
        """A cubic path's control poses (camera-to-world) appended to exposure_spline.txt; nothing
        for a straight path."""
        traj = o.result.trajectory if o.result is not None else None
        if not isinstance(traj, SplineTrajectory):
            return
        if self.spline is None:
            self.spline = TrajectoryWriter(self.out / "exposure_spline.txt", SPLINE_HEADER, append=self.append)
        T_world_ref = o.T_world_start.compose(traj.start.inverse())
        self.spline.write(o.timestamp, *(_vec(T_world_ref.compose(traj.control(j))) for j in range(4)))

    def write_points(self, cloud) -> None:
        """World points (a ``PointCloud``) appended to points.ply."""
        if self.points is None:
            self.points = PlyWriter(self.out / "points.ply", append=self.append)
        self.points.write(cloud.xyz, cloud.intensity)

    @property
    def point_count(self) -> int:
        """Vertices in points.ply so far."""
        return 0 if self.points is None else self.points.count

    def save_keyframe_image(self, stamp: float, image: np.ndarray) -> None:
        path = keyframe_image_path(self.out, stamp)
        path.parent.mkdir(exist_ok=True)
        cv2.imwrite(str(path), to_uint16(image))

    def draw_triptych(self, t: Triptych) -> None:
        """Blurry input | our blur model applied to the deblurred image | deblurred image. Pixels the
        model cannot synthesise (no depth, outside) show the input."""
        planes = plane_depths_from_keyframe(jnp.asarray(t.depth), self.camera, Pose.identity())
        rb, ok = render_blurry(jnp.asarray(linearize(t.sharp, self.gamma)), planes, self.camera, t.path.about_middle(), t.n, t.readout)
        rb = np.where(np.asarray(ok), delinearize(np.asarray(rb), self.gamma), t.blurry)
        row = np.concatenate([t.blurry, rb, t.sharp], axis=1)
        cv2.imwrite(str(self.out / f"triptych_{self.triptychs}.png"), np.clip(row * 255, 0, 255).astype(np.uint8))
        self.triptychs += 1

    def close(self) -> None:
        for w in (self.trajectory, self.exposure, self.keyframes, self.points, self.spline):
            if w is not None:
                w.close()
        self._csv_fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
