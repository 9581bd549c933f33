"""RGB-D motion-blur-aware visual odometry: the per-sequence loop.

For each frame: predict its exposure path by constant velocity, track it against the current sharp
keyframe (``tracking.track``), write its poses (flushed per frame), and decide whether it becomes the
next keyframe (mean point flow and blur length, or too few visible points). A blurry frame that becomes a keyframe is
deblurred with its estimated exposure path first (``deblur.deblur``), so later frames align against
sharp images; a keyframe made without an estimated path (the first frame, or the current frame
after repeated drops) is deblurred once the first frame tracked against it gives the camera's
velocity. Tracking failures never end the run: the frame is dropped (no pose written) and the
next frames are re-initialised from the last good pose with the motion hypotheses; after
``reset_after_drops`` drops in a row the current frame becomes a new keyframe at the last good pose.

Outputs in ``out``: ``trajectory.txt`` (TUM, every tracked frame, mid-exposure, camera-to-world),
``exposure.txt`` (start and end poses), ``keyframes.txt`` (timestamp + pose), ``frames.csv``
(per-frame status, RMS error, n, time), ``keyframes/`` (the sharp/deblurred keyframe images, for
``--resume`` and the triptychs), ``config.yaml`` (the configuration used).
"""

from __future__ import annotations

import csv
import dataclasses
import pathlib
import sys
import time

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import yaml

from .blur import blur_lengths
from .deblur import choose_deblur_n, deblur, exposure_blur_px
from .errors import ConfigError, DataError, MbavoError
from .geometry import ExposureTrajectory, Pose
from .io import TrajectoryWriter, read_exposure_file, read_tum_trajectory
from .tracking import Keyframe, Status, TrackerConfig, constant_velocity_guess, exposure_from_velocity, track

__all__ = ["OdometryConfig", "run_odometry", "load_config", "needs_keyframe", "sequence_calibration"]


@dataclasses.dataclass(frozen=True)
class OdometryConfig:
    """Sequence-level settings. ``keyframe_flow``: new keyframe when the mean flow of the keyframe's
    points exceeds this fraction of the image width, unless the frame is blurred more than
    ``keyframe_max_blur_px`` (mean blur length of the keyframe's points, full-resolution pixels): a
    blurred frame is passed over for a sharper one until the flow exceeds ``keyframe_flow_max``
    (off by default: with deblurred keyframes, waiting for sharper frames raised the ATE on our
    640x480 benchmark, strong blur 3.4 -> 3.9 mm with 8 px, extreme 6.6 -> 13.7 mm);
    ``keyframe_min_visible``: a new keyframe whatever its blur when fewer than this fraction of the
    keyframe's points are still visible; ``deblur_min_blur_px``: deblur a new keyframe whose
    estimated blur exceeds this (pixels at full resolution); ``deblur_n``: the deconvolution's
    virtual frames (0 = one per pixel of the frame's blur, 95th percentile, as a power of two up to
    ``deblur_n_max``: fewer leave gaps in the blur operator and the deconvolution rings, which on
    37-px blur raised the ATE from 6.6 to 9.9 mm); ``deblur_iterations``: its CG iterations; ``deblur_regularization``: weight of its
    gradient penalty (2e-2: +2.6 dB PSNR, +0.01 SSIM on strong-blur 640x480 frames); ``reset_after_drops``: consecutive dropped frames
    after which the current frame becomes a keyframe at the last good pose; ``exposure_s``: exposure
    time when the sequence has none (0: sharp); ``deblur_first_keyframe``: the first frame (and a
    frame made a keyframe after ``reset_after_drops``) has no estimated exposure path when it becomes
    a keyframe, so it is used as it is until the first frame tracked against it gives the camera's
    velocity; then that keyframe is deblurred with the constant-velocity exposure path (if blurred
    more than ``deblur_min_blur_px``) and the frame is tracked again against it."""

    keyframe_flow: float = 0.1
    keyframe_max_blur_px: float = float("inf")
    keyframe_flow_max: float = 0.15
    keyframe_min_visible: float = 0.6
    deblur_min_blur_px: float = 2.0
    deblur_n: int = 0
    deblur_n_max: int = 64
    deblur_iterations: int = 30
    deblur_regularization: float = 2e-2
    reset_after_drops: int = 3
    exposure_s: float = 0.0
    deblur_first_keyframe: bool = True
    triptychs: int = 3


def load_config(path=None, overrides: list[str] | None = None) -> tuple[TrackerConfig, OdometryConfig]:
    """Read ``tracker:`` and ``odometry:`` sections of a YAML file and ``section.key=value`` overrides.
    Unknown keys raise :class:`ConfigError`."""
    data: dict = {}
    if path is not None:
        p = pathlib.Path(path)
        if not p.is_file():
            raise ConfigError(f"{p}: config file not found")
        try:
            data = yaml.safe_load(p.read_text()) or {}
        except yaml.YAMLError as exc:
            raise ConfigError(f"{p}: not valid YAML ({str(exc).splitlines()[0]})") from None
        if not isinstance(data, dict):
            raise ConfigError(f"{p}: expected sections 'tracker:' and 'odometry:'")
    for item in overrides or []:
        if "=" not in item or "." not in item.split("=", 1)[0]:
            raise ConfigError(f"override '{item}' must look like section.key=value (e.g. tracker.n=32)")
        key, value = item.split("=", 1)
        section, name = key.split(".", 1)
        data.setdefault(section, {})[name] = yaml.safe_load(value)
    unknown = set(data) - {"tracker", "odometry"}
    if unknown:
        raise ConfigError(f"unknown config section(s): {', '.join(sorted(unknown))} (expected tracker, odometry)")
    out = []
    for cls, section in ((TrackerConfig, "tracker"), (OdometryConfig, "odometry")):
        values = dict(data.get(section) or {})
        fields = {f.name: f for f in dataclasses.fields(cls)}
        bad = set(values) - set(fields)
        if bad:
            raise ConfigError(f"unknown {section} key(s): {', '.join(sorted(bad))}")
        for k, v in values.items():
            values[k] = _coerce(f"{section}.{k}", v, fields[k].default)
        try:
            out.append(cls(**values))
        except (TypeError, ValueError) as exc:
            raise ConfigError(f"{section}: {exc}") from None
    return out[0], out[1]


def sequence_calibration(seq) -> dict:
    """The TrackerConfig values a sequence records about its camera (camera.yaml): the response γ
    (``response_gamma``) and the depth noise model (``depth_sigma``). Explicit settings win over them."""
    meta = getattr(seq, "meta", None) or {}
    out = {}
    if "response_gamma" in meta:
        out["response_gamma"] = float(meta["response_gamma"])
    if "depth_sigma" in meta:
        out["depth_sigma"] = tuple(float(x) for x in meta["depth_sigma"])
    return out


def _coerce(key: str, value, default):
    """A config value checked against the type of its default (YAML reads ``1e9`` as a string, a
    list as a list): numbers where numbers belong, tuples of them for per-level lists."""
    def number(v, like):
        if isinstance(v, bool) or not isinstance(v, (int, float, str)):
            raise ConfigError(f"{key}: expected a number, got {v!r}")
        try:
            x = float(v)
        except ValueError:
            raise ConfigError(f"{key}: expected a number, got {v!r}") from None
        if isinstance(like, int):
            if x != int(x):
                raise ConfigError(f"{key}: expected an integer, got {v!r}")
            return int(x)
        return x

    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{key}: expected true or false, got {value!r}")
        return value
    if isinstance(default, (int, float)):
        return number(value, default)
    if isinstance(default, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{key}: expected a list like {list(default)}, got {value!r}")
        return tuple(number(v, default[0]) if default else v for v in value)
    if isinstance(default, str) and not isinstance(value, str):
        raise ConfigError(f"{key}: expected a string, got {value!r}")
    return value


def _config_dict(tc: TrackerConfig, oc: OdometryConfig) -> dict:
    conv = lambda d: {k: list(v) if isinstance(v, tuple) else v for k, v in d.items()}
    return {"tracker": conv(dataclasses.asdict(tc)), "odometry": conv(dataclasses.asdict(oc))}


def _pose_vec(p: Pose) -> np.ndarray:
    return np.asarray(p.to_vector(), np.float64)


@jax.jit
def _keyframe_stats(cam, pixels, depths, valid, traj: ExposureTrajectory):
    """For the keyframe's points and a tracked exposure path: mean flow (pixels) into the current
    frame at mid-exposure, the fraction of points that project inside it, and the mean blur length
    (fixed shapes: one program per sequence, one device-to-host copy per frame)."""
    X = jax.vmap(cam.backproject)(pixels, depths)
    T_cur_ref = traj.middle().inverse()
    Xc = jax.vmap(T_cur_ref.apply)(X)
    x = jax.vmap(cam.project)(jnp.where(Xc[:, 2:3] > 1e-6, Xc, jnp.array([0.0, 0.0, 1.0])))
    inside = valid & (Xc[:, 2] > 1e-6) & jax.vmap(cam.in_image)(x)
    flow = jnp.sum(jnp.where(inside, jnp.linalg.norm(x - pixels, axis=1), 0.0)) / jnp.maximum(inside.sum(), 1)
    lengths, ok = blur_lengths(cam, pixels, depths, traj)
    ok = ok & valid
    blur = jnp.sum(jnp.where(ok, lengths, 0.0)) / jnp.maximum(ok.sum(), 1)
    return flow, inside.sum() / jnp.maximum(valid.sum(), 1), blur


def _flow_visible_blur(kf: Keyframe, traj: ExposureTrajectory) -> tuple[float, float, float]:
    pts, cam = kf.points[0], kf.cameras[0]
    if pts.count == 0:
        return float("inf"), 0.0, 0.0
    stats = _keyframe_stats(cam, *pts.on_device, traj)
    return tuple(float(v) for v in jax.device_get(stats))


def needs_keyframe(flow_px: float, visible: float, blur_px: float, width: int, odo: OdometryConfig) -> bool:
    """The keyframe decision: mean point flow beyond ``keyframe_flow`` of the width on a frame
    blurred at most ``keyframe_max_blur_px``, or beyond ``keyframe_flow_max`` whatever its blur, or
    fewer than ``keyframe_min_visible`` of the keyframe's points in view."""
    return bool(visible < odo.keyframe_min_visible or flow_px > odo.keyframe_flow_max * width
                or (flow_px > odo.keyframe_flow * width and blur_px <= odo.keyframe_max_blur_px))


class _Progress:
    def __init__(self, total: int, stream):
        self.total, self.stream, self.t0 = total, stream, time.perf_counter()

    def update(self, i: int, status: str, keyframes: int, drops: int):
        if self.stream is None:
            return
        el = time.perf_counter() - self.t0
        fps = (i + 1) / max(el, 1e-9)
        width = 24
        done = int(width * (i + 1) / max(self.total, 1))
        self.stream.write(
            f"\r[{'#' * done}{'.' * (width - done)}] {i + 1}/{self.total}  {fps:.1f} fps  {status:<14} kf {keyframes}  dropped {drops}  "
        )
        self.stream.flush()

    def close(self):
        if self.stream is not None:
            self.stream.write("\n")
            self.stream.flush()


def _save_keyframe_image(out: pathlib.Path, stamp: float, image: np.ndarray) -> None:
    (out / "keyframes").mkdir(exist_ok=True)
    cv2.imwrite(str(out / "keyframes" / f"{stamp:.6f}.png"), np.clip(np.round(image * 65535), 0, 65535).astype(np.uint16))


def _triptych(path, blurry, reblurred, deblurred):
    row = np.concatenate([blurry, reblurred, deblurred], axis=1)
    cv2.imwrite(str(path), np.clip(row * 255, 0, 255).astype(np.uint8))


def _deblurred(image, depth, camera, path: ExposureTrajectory, tracker: TrackerConfig, odo: OdometryConfig):
    """(sharp image, virtual frames used): ``image`` deconvolved along its exposure ``path`` (in any
    reference frame) with the odometry's deblur settings; the triptych needs the same ``n``."""
    n = choose_deblur_n(depth, camera, path, odo.deblur_n, odo.deblur_n_max)
    return deblur(image, depth, camera, path, n, odo.deblur_iterations, odo.deblur_regularization, tracker.response_gamma), n


def _deblur_pending_keyframe(keyframe: Keyframe, stamp: float, pending, frame, result, camera, tracker: TrackerConfig, odo: OdometryConfig,
                             out: pathlib.Path):
    """A keyframe made without an exposure path (the first frame, or a reset after drops) deblurred
    once the first frame tracked against it gives the camera's velocity (constant velocity from the
    keyframe's mid pose to this frame's), and this frame tracked again against it. Returns
    (keyframe, result); the keyframe unchanged and the first result when the keyframe is sharp
    enough or the second tracking fails."""
    image, depth, exposure = pending
    mid = result.trajectory.middle()  # T_kf_mid of this frame: the motion over frame.timestamp - stamp
    path = exposure_from_velocity(mid, max(frame.timestamp - stamp, 1e-6), exposure)
    if exposure_blur_px(depth, camera, path)[0] <= odo.deblur_min_blur_px:
        return keyframe, result
    sharp, _ = _deblurred(image, depth, camera, path, tracker, odo)
    keyframe = Keyframe.create(sharp, depth, camera, tracker)
    _save_keyframe_image(out, stamp, sharp)
    init = ExposureTrajectory(mid.compose(path.start), mid.compose(path.end))  # same velocity: T_kf_mid ∘ path
    again = track(keyframe, frame.image, init, tracker, depth=frame.depth)
    return keyframe, (again if again.status.ok else result)


def run_odometry(seq, out, tracker: TrackerConfig = TrackerConfig(), odo: OdometryConfig = OdometryConfig(),
                 resume: bool = False, max_frames: int | None = None, progress=sys.stderr) -> dict:
    """Track a whole RGB-D sequence; returns a summary. Writes per frame, so an interrupted run keeps
    every finished pose; ``resume=True`` continues after the last frame in ``out/trajectory.txt``."""
    out = pathlib.Path(out)
    out.mkdir(parents=True, exist_ok=True)
    if not seq.has_depth:
        raise MbavoError(f"{seq.path}: 'mbavo track' needs depth (an RGB-D sequence); the monocular back-end is not built yet")
    n_total = len(seq) if max_frames is None else min(len(seq), max_frames)
    (out / "config.yaml").write_text(yaml.safe_dump(_config_dict(tracker, odo), sort_keys=False))
    start_index = 0
    mids: list[tuple[float, Pose]] = []
    kf_state = None  # (Keyframe, T_world_kf, stamp)
    keyframe_count = 0
    resumed_pending = None  # index of a resumed keyframe that still waits to be deblurred
    if resume and (out / "trajectory.txt").is_file() and (out / "keyframes.txt").is_file():
        t_done, p_done = read_tum_trajectory(out / "trajectory.txt")
        t_kf, p_kf = read_tum_trajectory(out / "keyframes.txt")
        stamps = seq.timestamps
        # frames up to the last keyframe were processed (a keyframe made after drops comes later
        # than the last tracked frame): continue after both
        start_index = int(np.searchsorted(stamps, max(t_done[-1], t_kf[-1]) + 1e-6))
        mids = [(float(t), Pose.from_vector(jnp.asarray(p, jnp.float32))) for t, p in zip(t_done[-2:], p_done[-2:])]
        k = int(np.argmin(np.abs(stamps - t_kf[-1])))
        img_path = out / "keyframes" / f"{t_kf[-1]:.6f}.png"
        if not img_path.is_file():
            raise DataError(img_path, "keyframe image needed for --resume is missing")
        kf_img = cv2.imread(str(img_path), cv2.IMREAD_UNCHANGED).astype(np.float32) / 65535.0
        kf_state = (Keyframe.create(kf_img, seq[k].depth, seq.camera, tracker), Pose.from_vector(jnp.asarray(p_kf[-1], jnp.float32)), float(t_kf[-1]))
        keyframe_count = len(t_kf)
        # a keyframe made without an exposure path that no frame has tracked against yet is still
        # the raw image and waits to be deblurred, as in an uninterrupted run: the first frame with
        # nothing tracked after it, or a reset after drops (later than every tracked frame)
        reset = t_kf[-1] > t_done[-1] + 1e-6
        if reset or (len(t_done) == 1 and abs(t_kf[-1] - t_done[0]) < 1e-6):
            resumed_pending = k
        if reset:  # the drops before it forgot the velocity
            mids = mids[-1:]
    append = resume and start_index > 0
    if not append:  # a fresh run: keyframe images and triptychs of an earlier run in ``out`` would mix in
        for stale in [*(out / "keyframes").glob("*.png"), *out.glob("triptych_*.png")]:
            stale.unlink()
    traj_w = TrajectoryWriter(out / "trajectory.txt", append=append)
    exp_w = TrajectoryWriter(out / "exposure.txt", "timestamp start:tx ty tz qx qy qz qw end:tx ty tz qx qy qz qw (camera-to-world)", append=append)
    kf_w = TrajectoryWriter(out / "keyframes.txt", append=append)
    csv_path = out / "frames.csv"
    csv_fh = open(csv_path, "a" if append else "w", newline="")
    writer = csv.writer(csv_fh)
    if not append:
        writer.writerow(["index", "timestamp", "status", "rms", "n_finest", "blur_px", "hypothesis", "ms", "keyframe"])
    prog = _Progress(n_total - start_index, progress)
    drops, consecutive_drops, tracked, triptychs = 0, 0, 0, 0
    pending = None  # (image, depth, exposure) of the current keyframe while it waits to be deblurred
    deblur_pending = odo.deblur_first_keyframe and tracker.blur_aware

    def exposure_of(frame) -> float:
        return frame.exposure if frame.exposure is not None else odo.exposure_s

    def pending_of(frame):
        """What ``_deblur_pending_keyframe`` needs of a keyframe made from ``frame`` without an
        exposure path, or None when it will not be deblurred."""
        wait = deblur_pending and exposure_of(frame) > 0 and frame.depth is not None
        return (frame.image, frame.depth, exposure_of(frame)) if wait else None

    def keyframe_without_path(frame, T_w_kf: Pose):
        """(kf_state, pending) of a keyframe at ``T_w_kf`` from a frame whose exposure path is not
        known (the first frame, a reset after drops): used as it is, and deblurred once the next
        frame tracked against it gives the velocity (``_deblur_pending_keyframe``)."""
        nonlocal keyframe_count
        keyframe_count += 1
        _save_keyframe_image(out, frame.timestamp, frame.image)
        kf_w.write(frame.timestamp, _pose_vec(T_w_kf))
        state = (Keyframe.create(frame.image, frame.depth, seq.camera, tracker), T_w_kf, frame.timestamp)
        return state, pending_of(frame)

    if resumed_pending is not None:
        pending = pending_of(seq[resumed_pending])

    dt_default = float(np.median(np.diff(seq.timestamps))) if len(seq) > 1 else 1 / 30
    try:
        for idx in range(start_index, n_total):
            frame = seq[idx]
            exposure = exposure_of(frame)
            t0 = time.perf_counter()
            if kf_state is None:  # first frame: the world frame, taken as sharp until its blur is known
                T_w = Pose.identity()
                kf_state, pending = keyframe_without_path(frame, T_w)
                traj_w.write(frame.timestamp, _pose_vec(T_w))
                exp_w.write(frame.timestamp, _pose_vec(T_w), _pose_vec(T_w))
                mids.append((frame.timestamp, T_w))
                writer.writerow([idx, f"{frame.timestamp:.6f}", "keyframe", 0.0, 0, 0.0, "", 0.0, 1])
                csv_fh.flush()
                tracked += 1
                prog.update(idx - start_index, "keyframe", keyframe_count, drops)
                continue
            kf, T_w_kf, _ = kf_state
            if len(mids) >= 2:
                (ta, Ta), (tb, Tb) = mids[-2], mids[-1]
                gap = frame.timestamp - tb
                init = constant_velocity_guess(T_w_kf, Ta, Tb, max(tb - ta, 1e-6), exposure, gap)
            else:
                last = mids[-1][1]
                init = ExposureTrajectory(T_w_kf.inverse().compose(last), T_w_kf.inverse().compose(last))
            if frame.depth is not None and not np.isfinite(frame.depth).any():
                result_status, result = Status.TOO_FEW_POINTS, None
            else:
                result = track(kf, frame.image, init, tracker, depth=frame.depth)
                if pending is not None and result.status.ok:
                    kf, result = _deblur_pending_keyframe(kf, kf_state[2], pending, frame, result, seq.camera, tracker, odo, out)
                    kf_state = (kf, T_w_kf, kf_state[2])
                    pending = None
                result_status = result.status
            ms = 1000 * (time.perf_counter() - t0)
            is_kf = 0
            if result is not None and result_status.ok:
                traj = result.trajectory
                T_w_start, T_w_end = T_w_kf.compose(traj.start), T_w_kf.compose(traj.end)
                T_w_mid = T_w_kf.compose(traj.middle())
                traj_w.write(frame.timestamp, _pose_vec(T_w_mid))
                exp_w.write(frame.timestamp, _pose_vec(T_w_start), _pose_vec(T_w_end))
                mids.append((frame.timestamp, T_w_mid))
                mids = mids[-2:]
                tracked += 1
                consecutive_drops = 0
                flow, visible, blur = _flow_visible_blur(kf, traj)
                need_kf = needs_keyframe(flow, visible, blur, seq.camera.width, odo)
                if need_kf and frame.depth is not None:
                    sharp = frame.image
                    if blur > odo.deblur_min_blur_px and tracker.blur_aware:
                        sharp, n_deblur = _deblurred(frame.image, frame.depth, seq.camera, traj, tracker, odo)
                        if triptychs < odo.triptychs:
                            from .blur import plane_depths_from_keyframe, render_blurry
                            from .deblur import exposure_about_mid

                            lin = jnp.asarray(np.clip(sharp, 0, 1) ** tracker.response_gamma)
                            planes = plane_depths_from_keyframe(jnp.asarray(frame.depth), seq.camera, Pose.identity())
                            rb, rb_ok = render_blurry(lin, planes, seq.camera, exposure_about_mid(traj), n_deblur)
                            # pixels the model cannot synthesise (no depth, outside) show the input
                            rb = np.where(np.asarray(rb_ok), np.asarray(rb) ** (1 / tracker.response_gamma), frame.image)
                            _triptych(out / f"triptych_{triptychs}.png", frame.image, rb, sharp)
                            triptychs += 1
                    kf_state = (Keyframe.create(sharp, frame.depth, seq.camera, tracker), T_w_mid, frame.timestamp)
                    keyframe_count += 1
                    _save_keyframe_image(out, frame.timestamp, sharp)
                    kf_w.write(frame.timestamp, _pose_vec(T_w_mid))
                    is_kf = 1
            else:
                drops += 1
                consecutive_drops += 1
                # re-initialise: no velocity (the motion hypotheses widen the search from the last pose)
                if mids:
                    mids = [mids[-1]]
                if consecutive_drops >= odo.reset_after_drops and frame.depth is not None and np.isfinite(frame.depth).any() and np.std(frame.image) > 1e-3:
                    kf_state, pending = keyframe_without_path(frame, mids[-1][1])
                    consecutive_drops = 0
                    is_kf = 1
            diag = result.diagnostics if result is not None else {}
            levels = diag.get("levels") or [{}]
            writer.writerow([idx, f"{frame.timestamp:.6f}", result_status.name.lower(), f"{diag.get('rms', float('nan')):.5f}",
                             levels[-1].get("n", 0), f"{diag.get('blur_px', 0.0):.2f}", diag.get("hypothesis", ""), f"{ms:.1f}", is_kf])
            csv_fh.flush()
            prog.update(idx - start_index, result_status.name.lower(), keyframe_count, drops)
    finally:
        prog.close()
        for w in (traj_w, exp_w, kf_w):
            w.close()
        csv_fh.close()
    return {"frames": n_total - start_index, "tracked": tracked, "dropped": drops, "keyframes": keyframe_count,
            "frame_drop_rate": drops / max(n_total - start_index, 1)}
