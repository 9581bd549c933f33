"""The rerun view of a run (``mbavo track --viewer / --rrd``, ``mbavo view``).

Per frame: the mid-exposure trajectory and the ground truth, the frame's exposure start and end
camera frusta, keyframe frusta with their points (RGB-D: from the keyframe's depth; monocular: the
window's points), the blurry input, its synthesis from the keyframe along the estimated exposure
path (reblurred), the residual, the current keyframe image, and time series of the fit. What one
frame shows is a :class:`ViewFrame`, built live from the loop (:func:`live_frame`) or rebuilt from a
finished run folder (:func:`folder_frames`); :class:`RunViewer` logs it. rerun-sdk is an optional
extra (``pip install -e ".[viewer]"``) imported only here.
"""

from __future__ import annotations

import bisect
import dataclasses
import datetime
import os
import pathlib
import sys
import uuid

import jax.numpy as jnp
import numpy as np
import yaml
from jaxtyping import Float

from .blur import plane_depths_from_keyframe, render_blurry
from .errors import DataError, MbavoError
from .evaluation import interpolate_poses
from .evaluation.poses import pose_matrices
from .geometry import ExposureTrajectory, PinholeCamera, Pose, readout_fraction
from .image import delinearize, downsample, linearize
from .io import read_exposure_file, read_ply, read_tum_trajectory
from .tracking import Status
from .tracking.points import downsample_depth

__all__ = ["INSTALL_HINT", "require_rerun", "check_display", "check_rrd", "ViewKeyframe", "ViewFrame", "RunViewer", "live_frame", "folder_frames",
           "view_run", "view_level"]

INSTALL_HINT = 'the viewer needs rerun-sdk: pip install -e ".[viewer]"'
VIEW_WIDTH = 320  # images are shown at the first pyramid level at most this wide
JPEG_QUALITY = 80
RESIDUAL_GAIN = 2.0  # the residual image shows 0.5 + gain x (input - reblurred)
FRUSTUM_M = 0.1  # image-plane distance of the drawn camera frusta (m)
FLUSH_S = 2.0  # what is logged goes out at least this often, in one chunk per entity (small chunks cost ~1.5 KB each)
POINT_STRIDE = 6  # RGB-D keyframe points: every 6th pixel of the shown level in each direction
OK_STATUSES = {"keyframe"} | {s.name.lower() for s in Status if s.ok}  # a frame with a pose


def require_rerun():
    """The ``rerun`` module, or a one-line error saying how to install it (usage analytics off)."""
    os.environ.setdefault("RERUN_ANALYTICS", "0")
    try:
        import rerun
    except ImportError:
        raise MbavoError(INSTALL_HINT) from None
    return rerun


def check_display() -> None:
    """A viewer window needs a display: on Linux, an X11 or Wayland one."""
    if sys.platform.startswith("linux") and not any(os.environ.get(v) for v in ("DISPLAY", "WAYLAND_DISPLAY", "WAYLAND_SOCKET")):
        raise MbavoError("the rerun viewer needs a display (DISPLAY and WAYLAND_DISPLAY are not set): write the recording "
                         "with --rrd FILE and open it where there is one (rerun FILE)")


def check_rrd(path) -> pathlib.Path:
    """The recording file ``path`` (``--rrd``), checked before a run by ``--out``'s rules
    (``io.prepare_out_dir``): its folder is made when missing; a one-line MbavoError when ``path``
    is a folder, a parent is not a folder, or the file cannot be written there. A file that is
    already there is kept until the recording replaces it; a probe file made here is removed."""
    if not str(path).strip():
        raise MbavoError("--rrd is empty: give a file name (e.g. run.rrd)")
    path = pathlib.Path(path)
    if path.is_dir():
        raise MbavoError(f"{path}: --rrd is a folder; give a file name (e.g. {path / 'run.rrd'})")
    existing = next((p for p in path.parents if p.exists()), None)
    if existing is not None and not existing.is_dir():
        raise MbavoError(f"{path}: --rrd cannot be created: {existing} is not a folder (choose another --rrd)")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        made = not path.exists()
        with open(path, "ab"):
            pass
        if made:
            path.unlink()
    except OSError as exc:
        raise MbavoError(f"{path}: --rrd cannot be written: {exc.strerror or exc} (choose another --rrd)") from None
    return path


@dataclasses.dataclass(frozen=True)
class ViewKeyframe:
    """A keyframe as shown: its stamp, T_world_kf [t, q], image (display values, deblurred where it
    was) and depth in metres (None or NaN where unknown)."""

    stamp: float
    pose: Float[np.ndarray, "7"]
    image: Float[np.ndarray, "H W"]
    depth: Float[np.ndarray, "H W"] | None = None


@dataclasses.dataclass(frozen=True)
class ViewFrame:
    """What one frame shows: its status, poses [t, q] (camera-to-world; None when not tracked), fit
    (RMS, blur px, virtual frames n, seconds of tracking and back-end), the blurry input, the keyframe
    it was tracked against, keyframes made or replaced at it, and world points (N, 3) with their
    intensity (monocular window) when they changed."""

    index: int
    stamp: float
    status: str
    note: str = ""
    mid: np.ndarray | None = None
    start: np.ndarray | None = None
    end: np.ndarray | None = None
    rms: float | None = None
    blur_px: float | None = None
    n: int = 0
    readout: float = 0.0  # rolling-shutter readout fraction of the frame's exposure path
    seconds: float = 0.0
    image: np.ndarray | None = None
    reference: ViewKeyframe | None = None
    keyframes: tuple[ViewKeyframe, ...] = ()
    points: tuple[np.ndarray, np.ndarray] | None = None

    @property
    def tracked(self) -> bool:
        return self.mid is not None


# ---------------------------------------------------------------------------------- image maths


def view_level(width: int) -> int:
    """The pyramid level shown: the first at most ``VIEW_WIDTH`` pixels wide."""
    level = 0
    while (width >> level) > VIEW_WIDTH:
        level += 1
    return level


def at_level(image: Float[np.ndarray, "H W"], level: int, depth: bool = False) -> np.ndarray:
    """An image (2x2 box averages) or a depth map (mean of valid depths) at pyramid ``level``."""
    out = np.asarray(image, np.float32)
    for _ in range(level):
        out = downsample_depth(out) if depth else downsample(out)
    return out


def _pose(v) -> Pose:
    return Pose.from_vector(jnp.asarray(np.asarray(v, np.float32)))


def _has_depth(depth) -> bool:
    return depth is not None and bool(np.any(np.isfinite(depth) & (np.asarray(depth) > 0)))


def reblurred(f: ViewFrame, camera: PinholeCamera, gamma: float, level: int) -> tuple[np.ndarray, np.ndarray] | None:
    """The frame's blurry image synthesised from its reference keyframe along its estimated exposure
    path with n virtual frames (display values at ``level``), and where it is valid; None without
    a path, a reference or its depth."""
    ref = f.reference
    if not f.tracked or ref is None or not _has_depth(ref.depth):
        return None
    cam = camera.scaled(level)
    T_kf_world = _pose(ref.pose).inverse()
    path = ExposureTrajectory(T_kf_world.compose(_pose(f.start)), T_kf_world.compose(_pose(f.end)))
    planes = plane_depths_from_keyframe(jnp.asarray(at_level(ref.depth, level, depth=True)), cam, path.middle())
    sharp = jnp.asarray(linearize(at_level(ref.image, level), gamma), jnp.float32)
    image, ok = render_blurry(sharp, planes, cam, path, max(int(f.n), 1), f.readout)
    return delinearize(np.asarray(image), gamma), np.asarray(ok)


def keyframe_points(kf: ViewKeyframe, camera: PinholeCamera, level: int) -> tuple[np.ndarray, np.ndarray]:
    """Points (N, 3) in the keyframe's camera frame from its depth, every ``POINT_STRIDE``-th pixel
    of ``level``, and their intensity (N,)."""
    if not _has_depth(kf.depth):
        return np.zeros((0, 3), np.float32), np.zeros(0, np.float32)
    cam, s = camera.scaled(level), POINT_STRIDE
    depth = at_level(kf.depth, level, depth=True)[::s, ::s]
    value = at_level(kf.image, level)[::s, ::s]
    v, u = np.mgrid[0:cam.height:s, 0:cam.width:s]
    ok = np.isfinite(depth) & (depth > 0)
    d = depth[ok]
    xyz = np.stack([(u[ok] - float(cam.cx)) / float(cam.fx) * d, (v[ok] - float(cam.cy)) / float(cam.fy) * d, d], -1)
    return xyz.astype(np.float32), value[ok]


def _gray(image) -> np.ndarray:
    return np.clip(np.asarray(image, np.float32) * 255 + 0.5, 0, 255).astype(np.uint8)


def _anchored(groundtruth, stamp: float, T_world_mid: np.ndarray) -> np.ndarray | None:
    """Ground-truth positions (N, 3) moved so that its pose at ``stamp`` is the estimate's
    ``T_world_mid`` (no scale: a monocular run's scale differs); None when ``stamp`` is outside it."""
    stamps, poses = groundtruth
    at = interpolate_poses(stamps, poses, np.array([stamp]))
    if not np.isfinite(at).all():
        return None
    T = pose_matrices(T_world_mid[None])[0] @ np.linalg.inv(pose_matrices(at)[0])
    return np.asarray(poses, np.float64)[:, :3] @ T[:3, :3].T + T[:3, 3]


# ---------------------------------------------------------------------------------- the recording


class RunViewer:
    """A rerun recording of a run, one :meth:`log` per :class:`ViewFrame` on the ``frame`` timeline
    (and ``time``: the frame's stamp in seconds). ``rrd``: saved to this file; ``spawn``: a viewer
    window is started and streamed to. Also the loop's observer (:meth:`__call__`). Close it (or use
    it as a context manager) to finish the file."""

    def __init__(self, camera: PinholeCamera, gamma: float = 1.0, groundtruth=None, rrd=None, spawn: bool = False):
        if rrd is None and not spawn:
            raise ValueError("RunViewer needs a file (rrd) or a viewer (spawn)")
        rr = self.rr = require_rerun()
        self.camera, self.gamma, self.level, self.groundtruth = camera, gamma, view_level(camera.width), groundtruth
        batching = rr.ChunkBatcherConfig(flush_tick=datetime.timedelta(seconds=FLUSH_S), flush_num_bytes=1 << 20, flush_num_rows=1 << 20)
        self.rec = rr.RecordingStream("mbavo", recording_id=str(uuid.uuid4()), batcher_config=batching)
        if spawn:
            check_display()
            self.rec.spawn(connect=False)
        if rrd is not None:
            check_rrd(rrd)
        try:
            self.rec.set_sinks(*([rr.GrpcSink()] if spawn else []), *([rr.FileSink(str(rrd))] if rrd is not None else []))
        except RuntimeError as exc:  # the file's folder changed since the check, or no viewer to stream to
            where = f"{rrd}: --rrd cannot be written" if rrd is not None else "the rerun viewer cannot be reached"
            raise MbavoError(f"{where} ({exc})") from None
        self.mids: list[np.ndarray] = []
        self.keyframe_ids: dict[str, int] = {}
        self.drops = 0
        self.frames = 0
        self._setup()

    def _setup(self) -> None:
        """The world in camera axes (x right, y down, z forward: the first camera's frame)."""
        self.rec.log("world", self.rr.ViewCoordinates.RDF, static=True)

    def __call__(self, frame, before, outcome, after) -> None:
        """The loop's observer: ``frame``'s step took the state ``before`` to ``after`` with ``outcome``."""
        self.log(live_frame(frame, before, outcome, after, self.camera, self.gamma))

    def log(self, f: ViewFrame) -> None:
        """Everything one frame shows."""
        self.rec.set_time("frame", sequence=f.index)
        self.rec.set_time("time", duration=float(f.stamp))
        self._series(f)
        if f.tracked:
            self._poses(f)
        for kf in f.keyframes:
            self._keyframe(kf)
        if f.points is not None:
            xyz, value = f.points
            self.rec.log("world/points", self.rr.Points3D(xyz, colors=np.repeat(_gray(value)[:, None], 3, 1), radii=0.004))
        self._images(f)
        self.frames += 1

    def _series(self, f: ViewFrame) -> None:
        """Time series (status: 1 tracked, 0 not; drops: the count so far) and a text line per frame."""
        rr, ok = self.rr, f.status in OK_STATUSES
        self.drops += not ok and f.status != "initialising"
        values = {"status": float(ok), "drops": float(self.drops), "seconds": f.seconds}
        if f.rms is not None:
            values.update(rms=f.rms, blur_px=f.blur_px or 0.0, n=float(f.n))
        for name, value in values.items():
            self.rec.log(f"series/{name}", rr.Scalars(value))
        text = f"frame {f.index}: {f.status}" + (f" ({f.note})" if f.note else "")
        self.rec.log("log", rr.TextLog(text, level=rr.TextLogLevel.INFO if ok else rr.TextLogLevel.WARN))

    def _camera(self, path: str, pose: np.ndarray, color) -> None:
        """A camera at T_world_cam ``pose`` [t, q]: its transform at ``path`` (3D children are in its
        frame) and its frustum (the shown level's intrinsics) at ``path/frustum``."""
        cam, rr = self.camera.scaled(self.level), self.rr
        pose = np.asarray(pose, np.float32)
        self.rec.log(path, rr.Transform3D(translation=pose[:3], quaternion=rr.Quaternion(xyzw=pose[3:])))
        self.rec.log(f"{path}/frustum", rr.Pinhole(focal_length=[float(cam.fx), float(cam.fy)], principal_point=[float(cam.cx), float(cam.cy)],
                                width=cam.width, height=cam.height, image_plane_distance=FRUSTUM_M, color=color))

    def _poses(self, f: ViewFrame) -> None:
        """The exposure start and end frusta, the mid-exposure trajectory so far and (once, static)
        the ground truth anchored at the first tracked frame."""
        self._camera("world/camera/start", f.start, [80, 200, 80])
        self._camera("world/camera/end", f.end, [220, 60, 60])
        if not self.mids and self.groundtruth is not None:
            xyz = _anchored(self.groundtruth, f.stamp, np.asarray(f.mid, np.float64))
            if xyz is not None:
                self.rec.log("world/groundtruth", self.rr.LineStrips3D([xyz], colors=[[120, 120, 120]]), static=True)
        self.mids.append(np.asarray(f.mid[:3], np.float32))
        self.rec.log("world/trajectory", self.rr.LineStrips3D([np.stack(self.mids)], colors=[[40, 120, 240]]))

    def _keyframe(self, kf: ViewKeyframe) -> None:
        """A keyframe's frustum and points (made or replaced now), and its image as the current one."""
        key = f"{kf.stamp:.6f}"
        j = self.keyframe_ids.setdefault(key, len(self.keyframe_ids))
        self._camera(f"world/keyframes/{j}", kf.pose, [240, 180, 40])
        xyz, value = keyframe_points(kf, self.camera, self.level)
        if len(xyz):  # in the keyframe's camera frame
            self.rec.log(f"world/keyframes/{j}/points", self.rr.Points3D(xyz, colors=np.repeat(_gray(value)[:, None], 3, 1), radii=0.003))
        self._image("images/keyframe", at_level(kf.image, self.level))

    def _image(self, path: str, image) -> None:
        self.rec.log(path, self.rr.Image(_gray(image)).compress(jpeg_quality=JPEG_QUALITY))

    def _images(self, f: ViewFrame) -> None:
        """The blurry input, the reblurred synthesis and the residual (cleared when there is none)."""
        if f.image is None:
            return
        blurry = at_level(f.image, self.level)
        self._image("images/blurry", blurry)
        synth = reblurred(f, self.camera, self.gamma, self.level)
        if synth is None:
            self.rec.log("images/reblurred", self.rr.Clear(recursive=False))
            self.rec.log("images/residual", self.rr.Clear(recursive=False))
            return
        image, ok = synth
        self._image("images/reblurred", np.where(ok, image, blurry))
        self._image("images/residual", 0.5 + RESIDUAL_GAIN * np.where(ok, blurry - image, 0.0))

    def close(self) -> None:
        try:
            self.rec.flush()
        except RuntimeError as exc:  # the viewer went away (or never came up)
            raise MbavoError(f"the rerun viewer stopped taking the recording ({exc}); --rrd FILE saves it instead") from None
        finally:
            self.rec.disconnect()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


# ---------------------------------------------------------------------------------- live frames


def _vec(pose: Pose | None) -> np.ndarray | None:
    return None if pose is None else np.asarray(pose.to_vector(), np.float32)


def _fit(outcome) -> dict:
    """RMS, blur length and finest-level n of a frame's tracking result, as frames.csv has them."""
    if outcome.result is None:
        return {}
    diag = outcome.result.diagnostics
    rms = outcome.fit.rms if outcome.fit is not None else float(diag.get("rms", float("nan")))
    return {"rms": rms, "blur_px": float(diag.get("blur_px", 0.0)), "n": int((diag.get("levels") or [{}])[-1].get("n", 0)),
            "readout": float(diag.get("readout", 0.0))}


def _window_points(state, camera: PinholeCamera, gamma: float) -> tuple[np.ndarray, np.ndarray] | None:
    """A monocular window's active points in the world (N, 3) and their intensity (display values),
    or None (RGB-D, or not initialised)."""
    mono = state.backend
    if mono is None or getattr(mono, "window", None) is None:
        return None
    from .mono import world_points

    xyz, value = world_points(mono.window, camera)
    return np.asarray(xyz, np.float32), delinearize(np.clip(np.asarray(value, np.float32), 0.0, None), gamma)


def _points_depth(xyz: np.ndarray | None, camera: PinholeCamera, pose: np.ndarray) -> np.ndarray | None:
    """A filled depth map at T_world_cam ``pose`` from world points (a monocular keyframe's depth)."""
    if xyz is None or not len(xyz):
        return None
    from .mono.depthmap import filled_depth, sparse_depth

    return filled_depth(sparse_depth(camera, _pose(pose), np.asarray(xyz, np.float32)))


def _state_keyframe(stamp: float, image, states, points, camera: PinholeCamera) -> ViewKeyframe | None:
    """The keyframe at ``stamp`` as the first of ``states`` holding it has it, shown with ``image``;
    its depth from the sensor, else filled from the window's ``points``."""
    for state in states:
        kf = state.keyframe
        if kf is not None and abs(kf.stamp - stamp) < 1e-6:
            pose = _vec(kf.T_world_kf)
            depth = kf.keyframe.depth if _has_depth(kf.keyframe.depth) else _points_depth(points, camera, pose)
            return ViewKeyframe(stamp, pose, np.asarray(image, np.float32), depth)
    return None


def live_frame(frame, before, outcome, after, camera: PinholeCamera, gamma: float) -> ViewFrame:
    """The :class:`ViewFrame` of one step of the loop: ``frame`` took the state ``before`` to
    ``after`` with ``outcome`` (odometry.state.FrameOutcome)."""
    replaced = dict(outcome.replaced_images)
    made = {k.stamp: k.image for k in (outcome.earlier_keyframe, outcome.new_keyframe) if k is not None}
    changed = {**replaced, **made}
    points = _window_points(after if changed or outcome.ba is not None else before, camera, gamma)
    xyz = None if points is None else points[0]
    keyframes = tuple(k for s, image in changed.items() if (k := _state_keyframe(s, image, (after, before), xyz, camera)))
    reference = None
    if outcome.result is not None and before.keyframe is not None:
        kf = before.keyframe
        image = replaced.get(kf.stamp)
        image = delinearize(np.asarray(kf.keyframe.images[0]), gamma) if image is None else image
        reference = _state_keyframe(kf.stamp, image, (before,), xyz, camera)
    return ViewFrame(outcome.index, outcome.timestamp, outcome.status, outcome.note, _vec(outcome.T_world_mid),
                     _vec(outcome.T_world_start), _vec(outcome.T_world_end), **_fit(outcome),
                     seconds=outcome.track_seconds + outcome.backend_seconds, image=frame.image, reference=reference,
                     keyframes=keyframes, points=points if changed or outcome.ba is not None else None)


# ---------------------------------------------------------------------------------- a run folder


def _has_rows(path: pathlib.Path) -> bool:
    return path.is_file() and any(line.strip() and not line.startswith("#") for line in path.read_text().splitlines())


def _by_stamp(stamps, *columns) -> dict:
    """``%.6f`` stamp (as the run files write it) -> the rows of ``columns``."""
    return {f"{t:.6f}": tuple(c[i] for c in columns) for i, t in enumerate(stamps)}


class FolderRun:
    """A finished run folder read back for the view: frames.csv rows, trajectory.txt, exposure.txt,
    keyframes.txt with keyframes/ images, points.ply (monocular), and its sequence ``seq`` for the
    input images, the depth of RGB-D keyframes and the camera."""

    def __init__(self, run, seq, gamma: float):
        from .odometry.folder import committed_rows

        self.run, self.seq, self.gamma = pathlib.Path(run), seq, gamma
        self.rows = committed_rows(self.run)
        mids = read_tum_trajectory(self.run / "trajectory.txt") if _has_rows(self.run / "trajectory.txt") else ((), ())
        paths = read_exposure_file(self.run / "exposure.txt") if _has_rows(self.run / "exposure.txt") else ((), (), ())
        self.mids, self.paths = _by_stamp(*mids), _by_stamp(*paths)
        kf = read_tum_trajectory(self.run / "keyframes.txt") if _has_rows(self.run / "keyframes.txt") else (np.zeros(0), np.zeros((0, 7)))
        order = np.argsort(kf[0], kind="stable")
        self.kf_stamps, self.kf_poses = [float(t) for t in kf[0][order]], np.asarray(kf[1])[order]
        self.cloud = read_ply(self.run / "points.ply") if (self.run / "points.ply").is_file() else None
        self.index_of = {f"{float(r['timestamp']):.6f}": int(r["index"]) for r in self.rows}
        self._keyframes: dict[int, ViewKeyframe | None] = {}
        settings = yaml.safe_load((self.run / "config.yaml").read_text()) if (self.run / "config.yaml").is_file() else None
        self.readout_s = float(((settings or {}).get("tracker") or {}).get("readout_s", seq.readout_s))  # the run's own setting

    def keyframe(self, j: int) -> ViewKeyframe | None:
        """Keyframe ``j`` (in time order) with its stored image; None when the image is missing."""
        if j not in self._keyframes:
            from .odometry.outputs import read_keyframe_image

            stamp, pose = self.kf_stamps[j], np.asarray(self.kf_poses[j], np.float32)
            image = read_keyframe_image(self.run, stamp)
            if self.cloud is not None:  # monocular: depth from the run's points
                depth = _points_depth(self.cloud[0], self.seq.camera, pose)
            else:
                index = self.index_of.get(f"{stamp:.6f}")
                depth = None if index is None or not self.seq.has_depth else self.seq[index].depth
            self._keyframes[j] = None if image is None else ViewKeyframe(stamp, pose, image, depth)
        return self._keyframes[j]

    def frame(self, row: dict, last: bool = False) -> ViewFrame:
        """The :class:`ViewFrame` of one frames.csv ``row`` (``last``: the run's points shown with it)."""
        stamp, index, status = float(row["timestamp"]), int(row["index"]), row["status"]
        key = f"{stamp:.6f}"
        mid, (start, end) = self.mids.get(key, (None,))[0], self.paths.get(key, (None, None))
        before = bisect.bisect_left(self.kf_stamps, stamp - 1e-6) - 1  # the keyframe tracked against
        reference = self.keyframe(before) if mid is not None and status != "keyframe" and before >= 0 else None
        made = tuple(k for j, t in enumerate(self.kf_stamps) if abs(t - stamp) < 1e-6 and (k := self.keyframe(j)))
        fit = {} if status in ("keyframe", "initialising") or not row.get("rms") else {
            "rms": float(row["rms"]), "blur_px": float(row["blur_px"] or 0), "n": int(row["n_finest"] or 0),
            "readout": readout_fraction(self.readout_s, float(row.get("exposure_ms") or 0) / 1000)}
        points = None
        if last and self.cloud is not None and len(self.cloud[0]):
            points = (np.asarray(self.cloud[0], np.float32), np.asarray(self.cloud[1], np.float32))
        seconds = (float(row.get("ms") or 0) + float(row.get("backend_ms") or 0)) / 1000
        image = self.seq[index].image if index < len(self.seq) else None
        return ViewFrame(index, stamp, status, row.get("note", ""), mid, start, end, **fit, seconds=seconds, image=image,
                         reference=reference, keyframes=made, points=points)


    def frames(self):
        """The :class:`ViewFrame` of each committed frame, in order."""
        for i, row in enumerate(self.rows):
            yield self.frame(row, last=i == len(self.rows) - 1)


def folder_frames(run, seq, gamma: float = 1.0):
    """The :class:`ViewFrame` of each committed frame of the run folder ``run`` (made on ``seq``)."""
    return FolderRun(run, seq, gamma).frames()


def _run_sequence(run: pathlib.Path) -> str:
    """The sequence folder that run.yaml records."""
    path = run / "run.yaml"
    record = yaml.safe_load(path.read_text()) if path.is_file() else None
    where = (record or {}).get("sequence", {}).get("path") if isinstance(record, dict) else None
    if not where:
        raise DataError(path, "missing or names no sequence: give --sequence SEQ")
    if not pathlib.Path(where).exists():
        raise DataError(path, f"its sequence {where} is not there: give --sequence SEQ")
    return where


def view_run(run, rrd=None, sequence=None, progress: bool = True) -> dict:
    """Show the finished run folder ``run`` in a rerun viewer window, or with ``rrd`` write the
    recording to that file instead (no window). ``sequence``: the run's sequence folder (default:
    the one run.yaml records). Returns the frames shown and the file."""
    from .config import load_config
    from .datasets import open_sequence
    from .progress import bar

    run = pathlib.Path(run)
    if not (run / "frames.csv").is_file():
        raise DataError(run / "frames.csv", "missing: not a run folder (mbavo track SEQ --out DIR makes one)")
    require_rerun()
    seq = open_sequence(sequence or _run_sequence(run))
    gamma = load_config(run / "config.yaml").tracker.response_gamma if (run / "config.yaml").is_file() else 1.0
    folder = FolderRun(run, seq, gamma)
    with RunViewer(seq.camera, gamma, seq.groundtruth, rrd=rrd, spawn=rrd is None) as viewer, \
            bar(len(folder.rows), "view", progress) as pbar:
        for f in folder.frames():
            viewer.log(f)
            pbar.update()
    return {"frames": viewer.frames, **({"rrd": str(rrd)} if rrd is not None else {})}
