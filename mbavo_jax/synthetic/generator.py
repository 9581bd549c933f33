"""Blurry sequences with ground-truth exposure paths, in TUM RGB-D layout.

Two sources:

* ``generate_sequence``: a ray-cast scene of :mod:`.scene` (``SynthConfig.scene``) along a smooth
  camera path. Each blurry frame is the mean of ``subframes`` renders along the *true* (curved)
  path during the exposure, in linear radiance; the camera response ``I = r^(1/γ)`` is applied
  after, then noise and 8-bit quantisation.
* ``blur_real_sequence``: a real RGB-D clip blurred with the core blur model along a known exposure
  path (symmetric about each frame's own pose, so the clip's ground truth stays the mid-exposure
  pose).

Depth is the mid-exposure z-depth, either exact (``depth_model="exact"``, 16-bit quantised) or as a
structured-light sensor would write it (``"sensor"``, :func:`sensor_depth`). camera.yaml records the
depth noise model (``depth_sigma``) the way it records the response γ, so trackers can weigh depth.

Output folder: ``rgb.txt rgb/ depth.txt depth/ (16-bit, /depth_scale: 5000 unless the scene is
deeper than 13 m) groundtruth.txt`` (mid-exposure, camera-to-world), ``exposure.txt`` (start and end
pose), ``times.txt`` (``id timestamp exposure_ms``), ``sharp/`` (mid-exposure sharp image),
``camera.yaml`` and ``synth.yaml`` (settings, blur stats, the path bend per frame). Without exposure information
(``exposure_info=False``, as :func:`.metadata.hide_exposure_info` leaves a folder) there is no
times.txt nor ``exposure_ms``, and the exposure paths are in ``groundtruth_exposure.txt``.

Rolling shutter (``readout_ms`` R > 0; the time model of :mod:`mbavo_jax.geometry.trajectory`): row
v is exposed over [t0 + v/(H-1)·R, ... + τ] and rendered at its own times; a frame's exposure path
(exposure.txt) runs from t0 to t0 + R + τ, its timestamp and groundtruth.txt pose are at the middle
of that span; camera.yaml records ``readout_ms`` and ``exposure_rows.txt`` the true start and end
poses of sampled rows (:func:`sampled_rows`). ``shake_deg`` > 0 adds a handheld shake, so that
exposures span curved paths (``bend_px`` in synth.yaml, :func:`path_bend`).
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import time

import cv2
import jax
import jax.numpy as jnp
import numpy as np
import yaml

from ..blur import plane_depths_from_keyframe, render_blurry
from ..config import AT_LEAST_1, DEPTH_SIGMA, FINITE, NONNEG, PRESETS, SynthConfig
from ..datasets.imu import IMU_FILE, imu_block
from ..errors import ConfigError, MbavoError
from ..geometry import quaternion as quat
from ..geometry.camera import PinholeCamera
from ..geometry.pose import Pose
from ..geometry.trajectory import ExposureTrajectory, interpolate, readout_fraction
from ..image import delinearize
from ..io import (ExposureRows, prepare_out_dir, sampled_rows, write_camera_yaml, write_exposure_file, write_exposure_rows,
                  write_tum_trajectory)
from ..progress import bar
from .imu import IMU_GROUNDTRUTH, write_imu
from .metadata import EXPOSURE_ROWS, GROUNDTRUTH_EXPOSURE
from .path import camera_path
from .scene import CAMERA_CENTRE, Scene, make_scene, render_exposure, render_rolling_exposure, scene_arrays

__all__ = ["SynthConfig", "PRESETS", "generate_sequence", "fit_exposure", "probe_blur", "blur_real_sequence", "camera_path", "mean_blur_length", "path_bend",
           "sampled_rows", "sub_frame_times", "sensor_depth", "depth_scale", "DEPTH_SIGMA", "synth_memory_bytes"]


IMU_MARGIN_S = 0.5  # IMU samples before the first frame's exposure and after the last one's (s)


def _path_poses(times, cfg: SynthConfig) -> Pose:
    """The true poses at ``times`` (any shape): a Pose batched like ``times``."""
    times = jnp.asarray(times)
    one = lambda t: camera_path(t, cfg.speed, cfg.rotation_rate, cfg.seed, cfg.shake_deg, cfg.shake_hz)
    if times.ndim == 1:
        return jax.vmap(one)(times)
    flat = jax.vmap(one)(times.ravel())
    return jax.tree_util.tree_map(lambda a: a.reshape(*times.shape, *a.shape[1:]), flat)


def sub_frame_times(n: int) -> np.ndarray:
    """Fractions of the exposure at which the generator renders n sub-frames: i/(n-1), ½ for n = 1."""
    return np.linspace(0.0, 1.0, n) if n > 1 else np.full(1, 0.5)


def mean_blur_length(depth: np.ndarray, camera: PinholeCamera, poses: Pose, mid: Pose, step: int = 16) -> float:
    """Mean image-path length (px) over a pixel grid of points seen at ``mid`` (with ``depth``)
    moving through the sub-frame ``poses`` (T_world_cam)."""
    px = _grid_projections(depth, camera, poses, mid, step)
    return float(np.mean(np.sum(np.linalg.norm(np.diff(px, axis=0), axis=-1), axis=0))) if len(px) > 1 else 0.0


def path_bend(depth: np.ndarray, camera: PinholeCamera, poses: Pose, mid: Pose, step: int = 16) -> float:
    """How curved a path is, in pixels: for ``poses`` (T_world_cam) sampled evenly in time, the
    largest over samples of the mean distance (over the grid of points seen at ``mid``) between
    where the true pose and the straight interpolation (Eqs. 43-44) of the first and last pose
    project them. 0 for a path the linear exposure model follows exactly."""
    k = poses.t.shape[0]
    first, last = (jax.tree_util.tree_map(lambda a, i=i: a[i], poses) for i in (0, -1))
    straight = jax.vmap(lambda s: interpolate(first, last, s))(jnp.linspace(0.0, 1.0, k, dtype=poses.t.dtype))
    both = _grid_projections(depth, camera, jax.tree_util.tree_map(lambda a, b: jnp.concatenate([a, b]), poses, straight), mid, step)
    return float(np.max(np.mean(np.linalg.norm(both[:k] - both[k:], axis=-1), axis=1))) if k > 1 else 0.0


def _grid_projections(depth: np.ndarray, camera: PinholeCamera, poses: Pose, mid: Pose, step: int) -> np.ndarray:
    """(len(poses), P, 2) image positions (less the principal point) of a pixel grid of points seen
    at ``mid`` with ``depth``, seen from each of ``poses`` (T_world_cam)."""
    h, w = depth.shape
    v, u = np.mgrid[step // 2 : h : step, step // 2 : w : step]
    z = depth[v, u]
    ok = np.isfinite(z) & (z > 0)
    pts_cam = np.stack([(u - float(camera.cx)) / float(camera.fx) * z, (v - float(camera.cy)) / float(camera.fy) * z, z], -1)[ok]
    T_w_mid = np.asarray(mid.as_matrix())
    pts_w = pts_cam @ T_w_mid[:3, :3].T + T_w_mid[:3, 3]
    mats = np.asarray(jax.vmap(lambda p: p.inverse().as_matrix())(poses))  # T_cam_world per sub-frame
    pc = np.einsum("nij,pj->npi", mats[:, :3, :3], pts_w) + mats[:, None, :3, 3]
    return np.stack([float(camera.fx) * pc[..., 0] / pc[..., 2], float(camera.fy) * pc[..., 1] / pc[..., 2]], -1)


def sensor_depth(depth: np.ndarray, rng: np.random.Generator, sigma=DEPTH_SIGMA["sensor"], correlation_px: float = 2.0,
                 edge_rel: float = 0.05, dropout: float = 0.01) -> np.ndarray:
    """Exact z-depth (0 = none) as a structured-light sensor writes it: axial noise with
    σ(z) = a + b·(z − 0.4)² (Nguyen et al. 2012), spatially correlated over ``correlation_px``
    (the sensor matches 9x9 windows, so neighbouring pixels share their error); holes along depth
    edges (the 3x3 neighbourhood spans more than ``edge_rel`` of the depth: occlusion shadows and
    mixed pixels) and a fraction ``dropout`` of random missing pixels. Missing = 0."""
    d = np.asarray(depth, np.float32)
    valid = d > 0
    field = rng.normal(size=d.shape).astype(np.float32)
    if correlation_px > 0:
        field = cv2.GaussianBlur(field, (0, 0), correlation_px)
        field /= max(float(field.std()), 1e-12)
    noisy = d + field * (sigma[0] + sigma[1] * (d - 0.4) ** 2)
    big = np.where(valid, d, np.float32(1e6))
    kernel = np.ones((3, 3), np.uint8)
    lo = cv2.erode(big, kernel)
    hi = cv2.dilate(np.where(valid, d, np.float32(0.0)), kernel)
    edge = (hi - lo) > edge_rel * np.where(valid, d, 1.0)
    keep = valid & ~edge & (rng.random(d.shape) >= dropout) & (noisy > 0)
    return np.where(keep, noisy, 0.0).astype(np.float32)


def _write_gray(path, img01):
    cv2.imwrite(str(path), np.clip(np.round(np.asarray(img01) * 255.0), 0, 255).astype(np.uint8))


def _write_depth(path, depth_m, scale: float = 5000.0):
    d = np.nan_to_num(np.asarray(depth_m), nan=0.0)
    cv2.imwrite(str(path), np.clip(np.round(d * scale), 0, 65535).astype(np.uint16))


def depth_scale(scene: Scene, margin: float = 1.5) -> float:
    """16-bit depth units per metre: TUM's 5000 when the farthest box corner (plus ``margin`` for
    the camera's motion) fits in 65535 units, else the largest multiple of 100 that fits."""
    boxes = np.asarray(scene.boxes, np.float64)  # (K, 2, 3)
    pick = np.array(np.meshgrid([0, 1], [0, 1], [0, 1], indexing="ij")).reshape(3, -1).T  # min/max per axis
    corners = boxes[:, pick, np.arange(3)]  # (K, 8, 3)
    far = float(np.linalg.norm(corners - CAMERA_CENTRE, axis=-1).max()) + margin
    return 5000.0 if far * 5000.0 <= 65535 else float(np.floor(65535.0 / far / 100.0) * 100.0)


def synth_memory_bytes(width: int, height: int, boxes: int) -> int:
    """Peak memory (bytes) of rendering ``width`` x ``height`` frames of a scene of ``boxes`` boxes.

    The ray caster (``scene._render_core``) holds hit distances, face axes and their temporaries per
    pixel and box (~16 bytes each) next to a few float32 images (~50 bytes per pixel); sub-frames are
    scanned one at a time, so their number does not count. Measured on CPU (room, cluttered, deep
    scenes up to 2896x2172) and rounded up, plus 0.5 GiB for the interpreter, JAX and the textures."""
    return 2**29 + width * height * (64 + 20 * boxes)


def _physical_memory() -> int | None:
    """This machine's physical memory in bytes (None where the system does not say)."""
    try:
        return os.sysconf("SC_PHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, ValueError, OSError):
        return None


def _check_memory(cfg: SynthConfig, boxes: int) -> None:
    """ConfigError when rendering ``cfg``'s frames needs more memory than the machine has."""
    need, have = synth_memory_bytes(cfg.width, cfg.height, boxes), _physical_memory()
    if have is not None and need > have:
        raise ConfigError(f"--width {cfg.width} --height {cfg.height}: rendering the {cfg.scene} scene needs about "
                          f"{need / 2**30:,.0f} GiB of memory, this machine has {have / 2**30:,.0f} GiB (lower --width and --height)")


def _prepare_out(out) -> pathlib.Path:
    out = pathlib.Path(out)
    if out.is_dir() and any(out.iterdir()):
        if not (out / "synth.yaml").is_file():
            raise MbavoError(f"{out}: exists and is not a previous 'mbavo synth' output; choose an empty folder")
    prepare_out_dir(out)
    for sub in ("rgb", "depth", "sharp"):
        (out / sub).mkdir(parents=True, exist_ok=True)
    for name in ("times.txt", "exposure.txt", GROUNDTRUTH_EXPOSURE, EXPOSURE_ROWS, IMU_FILE, IMU_GROUNDTRUTH):  # a previous output's
        (out / name).unlink(missing_ok=True)
    return out


@dataclasses.dataclass(frozen=True)
class _FrameTruth:
    """A generated frame's ground truth: the true poses (vectors, T_world_cam) at mid-exposure and
    at the exposure path's start and end, the sampled rows' start and end poses (K, 7) (rolling
    shutter only), its mean blur and path bend (px)."""

    mid: np.ndarray
    start: np.ndarray
    end: np.ndarray
    row_starts: np.ndarray | None
    row_ends: np.ndarray | None
    blur_px: float
    bend_px: float


@dataclasses.dataclass(frozen=True)
class _RenderedFrame:
    """A generated frame's linear radiance (blurry, sharp), mid-exposure depth and ground truth."""

    radiance: jax.Array
    sharp: jax.Array
    depth: np.ndarray
    truth: _FrameTruth


def _vec(poses: Pose, i: int) -> np.ndarray:
    return np.asarray(jax.tree_util.tree_map(lambda a: a[i], poses).to_vector())


def _render_frame(cfg: SynthConfig, arrays, camera: PinholeCamera, t_mid: float) -> _RenderedFrame:
    """Frame at ``t_mid`` (the middle of its exposure span). Global shutter: the mean of
    ``subframes`` renders spread over the exposure τ. Rolling shutter (R = readout_ms > 0): the span
    is [t0, t0 + R + τ] about ``t_mid``; row v is exposed over [t0 + v/(H-1)·R, ... + τ] and is the
    mean of ``subframes`` renders at its own times (``render_rolling_exposure``)."""
    tau, readout = cfg.exposure_ms / 1000.0, cfg.readout_ms / 1000.0
    n_sub = max(1, cfg.subframes if tau > 0 else 1)
    sub_t = t_mid + (np.linspace(-0.5, 0.5, n_sub) if n_sub > 1 else np.zeros(1)) * tau  # the middle row's times
    poses = _path_poses(sub_t, cfg)
    mid = camera_path(t_mid, cfg.speed, cfg.rotation_rate, cfg.seed, cfg.shake_deg, cfg.shake_hz)
    t0, span = t_mid - 0.5 * (readout + tau), readout + tau
    rows, row_starts, row_ends = sampled_rows(cfg.height), None, None
    if readout == 0:
        radiance, sharp_rad, depth = render_exposure(arrays, camera, poses, mid, cfg.response_gamma)
        start, end = _vec(poses, 0), _vec(poses, -1)
    else:
        _, sharp_rad, depth = render_exposure(arrays, camera, jax.tree_util.tree_map(lambda a: a[None], mid), mid, cfg.response_gamma)
        row_t0 = t0 + readout * np.arange(cfg.height) / max(cfg.height - 1, 1)
        radiance = render_rolling_exposure(arrays, camera, _path_poses(row_t0[None, :] + tau * sub_frame_times(n_sub)[:, None], cfg),
                                           cfg.response_gamma)
        ends_ = _path_poses(np.array([t0, t0 + span]), cfg)
        start, end = _vec(ends_, 0), _vec(ends_, 1)
        row_poses = _path_poses(np.stack([row_t0[rows], row_t0[rows] + tau]), cfg)
        row_starts, row_ends = np.asarray(row_poses.to_vector()[0]), np.asarray(row_poses.to_vector()[1])
    depth = np.asarray(depth)
    bend = path_bend(depth, camera, _path_poses(t0 + span * np.linspace(0.0, 1.0, 17), cfg), mid) if span > 0 else 0.0
    truth = _FrameTruth(np.asarray(mid.to_vector()), start, end, row_starts, row_ends, mean_blur_length(depth, camera, poses, mid), bend)
    return _RenderedFrame(radiance, sharp_rad, depth, truth)


def generate_sequence(cfg: SynthConfig, out, progress: bool = True) -> dict:
    """Render a blurry sequence of ``cfg.scene`` into ``out``; returns the summary written to
    ``synth.yaml``. ``progress``: a progress bar on stderr (when it is a terminal)."""
    scene = make_scene(cfg.scene, cfg.seed, use_real_textures=cfg.real_textures, texture=cfg.texture)
    _check_memory(cfg, len(scene.boxes))
    f = 525.0 * cfg.width / 640.0
    camera = PinholeCamera.create(f, f, (cfg.width - 1) / 2, (cfg.height - 1) / 2, cfg.width, cfg.height)
    arrays = scene_arrays(scene)
    cfg = fit_exposure(cfg, arrays, camera) if cfg.blur_px > 0 else cfg
    out = _prepare_out(out)
    scale = depth_scale(scene)
    rng = np.random.default_rng(cfg.seed + 1000)
    stamps, frames = [], []
    t0 = time.perf_counter()
    pbar = bar(cfg.frames, "synth", progress)
    for i in range(cfg.frames):
        t_mid = 1.0 + i / cfg.fps  # start at 1 s to keep stamps positive and distinct
        fr = _render_frame(cfg, arrays, camera, t_mid)
        blurry = delinearize(fr.radiance, cfg.response_gamma)
        sharp = delinearize(fr.sharp, cfg.response_gamma)
        if cfg.noise > 0:
            blurry = blurry + rng.normal(scale=cfg.noise, size=blurry.shape)
        name = f"{t_mid:.6f}.png"
        _write_gray(out / "rgb" / name, blurry)
        _write_gray(out / "sharp" / name, sharp)
        depth_out = fr.depth if cfg.depth_model == "exact" else sensor_depth(fr.depth, rng)
        _write_depth(out / "depth" / name, depth_out, scale)
        stamps.append(t_mid)
        frames.append(fr.truth)
        pbar.update()
    pbar.close()
    exposure_ms = cfg.exposure_ms if cfg.exposure_info else None
    half_span = 0.5 * (cfg.exposure_ms + cfg.readout_ms) / 1000.0 + IMU_MARGIN_S
    imu = write_imu(out, cfg, stamps[0] - half_span, stamps[-1] + half_span) if cfg.imu else None
    summary = _write_layout(out, camera, cfg.fps, exposure_ms, cfg.response_gamma, stamps, stamps, [f.mid for f in frames],
                            [f.start for f in frames], [f.end for f in frames], [f.blur_px for f in frames],
                            DEPTH_SIGMA[cfg.depth_model], scale, cfg.readout_ms, {} if imu is None else {"imu": imu_block(imu)})
    if cfg.readout_ms > 0:
        _write_rows(out, stamps, frames, cfg.height)
    summary.update(_timing_summary(cfg.exposure_ms, cfg.readout_ms, [f.bend_px for f in frames]))
    summary.update(source=f"synthetic {cfg.scene}", config=dataclasses.asdict(cfg), textures=list(scene.texture_names))
    return _finish(out, summary, t0, cfg.exposure_info)


def probe_blur(cfg: SynthConfig, arrays, camera: PinholeCamera, exposure_s: float, probes: int = 8) -> float:
    """Mean blur (px, :func:`mean_blur_length`) of ``probes`` frames spread over ``cfg``'s
    sequence at exposure ``exposure_s`` (16 poses of the middle row's exposure; the sharp depth)."""
    blur = []
    for t_mid in 1.0 + np.linspace(0, cfg.frames - 1, probes) / cfg.fps:
        mid = camera_path(t_mid, cfg.speed, cfg.rotation_rate, cfg.seed, cfg.shake_deg, cfg.shake_hz)
        _, _, depth = render_exposure(arrays, camera, jax.tree_util.tree_map(lambda a: a[None], mid), mid, cfg.response_gamma)
        poses = _path_poses(t_mid + np.linspace(-0.5, 0.5, 16) * exposure_s, cfg)
        blur.append(mean_blur_length(np.asarray(depth), camera, poses, mid))
    return float(np.mean(blur))


def fit_exposure(cfg: SynthConfig, arrays, camera: PinholeCamera) -> SynthConfig:
    """``cfg`` with ``exposure_ms`` such that the mean blur (:func:`probe_blur`) is ``cfg.blur_px``:
    along the same path the blur grows about in proportion to the exposure, so two proportional
    steps from ``exposure_ms`` (half the frame interval when 0). ConfigError when the camera does
    not move or the blur needs an exposure longer than the frame interval (the message gives the
    blur that is within reach)."""
    interval, tau = 1.0 / cfg.fps, (cfg.exposure_ms / 1000.0) or 0.5 / cfg.fps
    for _ in range(2):
        blur = probe_blur(cfg, arrays, camera, tau)
        if blur < 1e-3:
            raise ConfigError(f"blur_px {cfg.blur_px:g}: the camera does not move (speed and rotation_rate 0?), so nothing blurs")
        if tau * cfg.blur_px / blur > interval:
            raise ConfigError(f"blur_px {cfg.blur_px:g}: needs an exposure of about {1000 * tau * cfg.blur_px / blur:.0f} ms, longer than "
                              f"the frame interval ({1000 * interval:.1f} ms); about {blur * interval / tau:.1f} px is within reach at "
                              "this speed, rotation_rate and image size")
        tau = tau * cfg.blur_px / blur
    return dataclasses.replace(cfg, exposure_ms=1000.0 * tau)


def _write_rows(out, stamps, truths: list[_FrameTruth], height: int) -> None:
    """exposure_rows.txt: each frame's sampled rows (:func:`sampled_rows`) with their true start and end poses."""
    rows = np.tile(sampled_rows(height), (len(truths), 1))
    write_exposure_rows(out / EXPOSURE_ROWS, ExposureRows(np.asarray(stamps, np.float64), rows, np.stack([f.row_starts for f in truths]),
                                                          np.stack([f.row_ends for f in truths])))


def _timing_summary(exposure_ms: float, readout_ms: float, bend_px) -> dict:
    """synth.yaml's exposure and readout times and the path bend (:func:`path_bend`) per frame."""
    bend = np.asarray(bend_px, np.float64)
    return {"exposure_ms": float(exposure_ms), "readout_ms": float(readout_ms), "mean_bend_px": round(float(bend.mean()), 3),
            "max_bend_px": round(float(bend.max()), 3), "bend_px": [round(float(b), 3) for b in bend]}


def _finish(out, summary: dict, t0: float, exposure_info: bool) -> dict:
    """Write synth.yaml (with the run time and ``exposure_info``)."""
    summary.update(exposure_info=exposure_info, seconds=round(time.perf_counter() - t0, 2))
    (out / "synth.yaml").write_text(yaml.safe_dump(summary, sort_keys=False))
    return summary


def _write_layout(out, camera, fps, exposure_ms, gamma, stamps, gt_stamps, mids, starts, ends, blur, depth_sigma,
                  scale=5000.0, readout_ms: float = 0.0, extra_camera: dict | None = None) -> dict:
    """Write the lists, trajectories and camera; ``gt_stamps`` are the frames with ground truth;
    depth images hold ``scale`` units per metre. ``exposure_ms`` None: no exposure information (no
    times.txt nor camera.yaml ``exposure_ms``; the exposure paths as ground truth only, in
    groundtruth_exposure.txt). camera.yaml records ``readout_ms`` when it is > 0, and ``extra_camera``'s keys
    (the ``imu:`` block)."""
    names = [f"{t:.6f}.png" for t in stamps]
    with open(out / "rgb.txt", "w") as fh:
        fh.write("# blurry images (mbavo synth)\n# timestamp filename\n")
        fh.writelines(f"{t:.6f} rgb/{n}\n" for t, n in zip(stamps, names))
    with open(out / "depth.txt", "w") as fh:
        fh.write(f"# mid-exposure depth, 16-bit, depth/{scale:g} = metres\n# timestamp filename\n")
        fh.writelines(f"{t:.6f} depth/{n}\n" for t, n in zip(stamps, names))
    if exposure_ms is not None:
        with open(out / "times.txt", "w") as fh:
            fh.write("# id timestamp exposure_ms\n")
            fh.writelines(f"{i} {t:.6f} {exposure_ms:.3f}\n" for i, t in enumerate(stamps))
    write_tum_trajectory(out / "groundtruth.txt", gt_stamps, mids, "timestamp tx ty tz qx qy qz qw (mid-exposure, camera-to-world)")
    write_exposure_file(out / ("exposure.txt" if exposure_ms is not None else GROUNDTRUTH_EXPOSURE), gt_stamps, starts, ends)
    exposure = {} if exposure_ms is None else {"exposure_ms": float(exposure_ms)}
    exposure.update({"readout_ms": float(readout_ms)} if readout_ms > 0 else {})
    write_camera_yaml(out / "camera.yaml", **camera.as_dict(), depth_scale=float(scale), **exposure, fps=float(fps),
                      response_gamma=float(gamma), depth_sigma=[float(x) for x in depth_sigma], **(extra_camera or {}))
    blur = np.asarray(blur)
    return {
        "frames": len(stamps),
        "mean_blur_px": round(float(blur.mean()), 3),
        "median_blur_px": round(float(np.median(blur)), 3),
        "max_blur_px": round(float(blur.max()), 3),
    }


class _symmetric_path:
    """Exposure path exp(−δ/2) → exp(+δ/2) about a frame's own pose; called with k, its k sub-poses."""

    def __init__(self, delta):
        start = Pose.identity().plus(jnp.asarray(-0.5 * delta, jnp.float32))
        end = Pose.identity().plus(jnp.asarray(0.5 * delta, jnp.float32))
        self.trajectory = ExposureTrajectory(start, end)

    def __call__(self, k: int) -> Pose:
        return jax.vmap(self.trajectory.at)(jnp.linspace(0.0, 1.0, k))


def _blur_direction(gt_poses, i: int, rng: np.random.Generator) -> np.ndarray:
    """[rotation, translation] direction of frame i's blur: the ground-truth motion to the next frame
    (from the previous one for the last), or a seeded random direction where there is none."""
    direction = rng.normal(size=6) * np.array([1, 1, 1, 0.3, 0.3, 0.3])
    if gt_poses is not None and np.all(np.isfinite(gt_poses[i])):
        j = min(i + 1, len(gt_poses) - 1) if i + 1 < len(gt_poses) else i - 1
        if np.all(np.isfinite(gt_poses[j])) and j != i:
            Ti, Tj = Pose.from_vector(jnp.asarray(gt_poses[i])), Pose.from_vector(jnp.asarray(gt_poses[j]))
            rel = Ti.inverse().compose(Tj)
            direction = np.concatenate([np.asarray(quat.log(rel.q)), np.asarray(rel.t)])
    return direction


def _blur_path(direction: np.ndarray, depth: np.ndarray, cam, blur_px: float) -> ExposureTrajectory:
    """The symmetric exposure path along ``direction`` whose mean blur over ``depth`` is ``blur_px``."""
    med_depth = float(np.nanmedian(depth)) if np.isfinite(depth).any() else 1.0
    # pixel motion of the unit direction ≈ f (|ω| + |v| / Z); scale it to the requested blur
    px_per_unit = float(cam.fx) * (np.linalg.norm(direction[:3]) + np.linalg.norm(direction[3:]) / med_depth)
    delta = direction * (blur_px / max(px_per_unit, 1e-9))
    # that estimate is an upper bound (e.g. roll blurs less): measure the path and rescale once
    measured = mean_blur_length(depth, cam, _symmetric_path(delta)(16), Pose.identity())
    if measured > 1e-6:
        delta = delta * (blur_px / measured)
    return _symmetric_path(delta).trajectory


REAL_FPS, REAL_EXPOSURE_MS = 30.0, 1000.0 / 30.0 * 0.5  # what blur_real_sequence records for a real clip


def _check_blur_arguments(blur_px: float, n: int, seed: int, noise: float, readout_ms: float) -> None:
    """ConfigError naming the first argument of :func:`blur_real_sequence` out of its (finite) range."""
    for name, value, check in (("blur_px", blur_px, NONNEG), ("subframes", n, AT_LEAST_1), ("seed", seed, NONNEG),
                               ("noise", noise, NONNEG), ("readout_ms", readout_ms, NONNEG)):
        if not (FINITE.ok(value) and check.ok(value)):
            raise ConfigError(f"{name}: must be {check.text}, got {value:g}")
    if readout_ms > 1000.0 / REAL_FPS:
        raise ConfigError(f"readout_ms: must not exceed the frame interval ({1000.0 / REAL_FPS:.3g} ms), got {readout_ms:g}")


def _blur_real_frame(image: np.ndarray, depth: np.ndarray, cam: PinholeCamera, traj: ExposureTrajectory, n: int,
                     rho: float) -> np.ndarray:
    """``image`` blurred along ``traj`` (about its own pose) by the core model, each row at its own
    times for readout fraction ``rho``; pixels the model cannot synthesise (no depth, outside the
    image) keep the sharp value."""
    img = jnp.asarray(image)
    planes = plane_depths_from_keyframe(jnp.asarray(depth), cam, traj.middle())
    blurry, valid = render_blurry(img, planes, cam, traj, n, readout=rho) if rho > 0 else render_blurry(img, planes, cam, traj, n)
    return np.where(np.asarray(valid), np.asarray(blurry), np.asarray(img))


def _real_truth(T_w: Pose, traj: ExposureTrajectory, rho: float, depth: np.ndarray, cam: PinholeCamera) -> _FrameTruth:
    """The ground truth of a frame blurred along ``traj`` about its true pose ``T_w``: the path's
    start and end, the sampled rows' (:meth:`ExposureTrajectory.row_path`; rolling shutter only) and
    the middle row's blur (the path is straight: no bend)."""
    vec = lambda T: np.asarray(T_w.compose(T).to_vector())
    rows = [traj.row_path(v, cam.height, rho) for v in sampled_rows(cam.height)] if rho > 0 else []
    sub = jax.vmap(lambda s: T_w.compose(traj.middle_row_path(rho).at(s)))(jnp.linspace(0.0, 1.0, 16))
    return _FrameTruth(np.asarray(T_w.to_vector()), vec(traj.start), vec(traj.end),
                       np.stack([vec(r.start) for r in rows]) if rows else None, np.stack([vec(r.end) for r in rows]) if rows else None,
                       mean_blur_length(depth, cam, sub, T_w), 0.0)


def blur_real_sequence(seq, out, blur_px: float = 20.0, n: int = 64, seed: int = 0, noise: float = 0.0, progress: bool = True,
                       exposure_info: bool = True, readout_ms: float = 0.0) -> dict:
    """Blur a real RGB-D sequence along known exposure paths with the core blur model.

    For frame k the exposure path is symmetric about the frame's own pose: T_k_start = exp(−δ/2),
    T_k_end = exp(+δ/2) (so its mid-exposure pose is the real pose and the ground truth is the
    clip's). δ follows the real motion direction between neighbouring ground-truth poses (a seeded
    random direction where there is none), scaled so the mean blur is ``blur_px`` pixels.
    ``exposure_info=False``: no exposure time written (the exposure paths in groundtruth_exposure.txt).
    ``readout_ms`` > 0: a rolling shutter; the path spans the frame's readout and exposure, each row
    is blurred along its own part of it (``blur_px`` is a row's blur) and exposure_rows.txt is written.
    """
    from ..evaluation.associate import interpolate_poses

    if not seq.has_depth:
        raise MbavoError(f"{seq.path}: --from needs a sequence with depth")
    _check_blur_arguments(blur_px, n, seed, noise, readout_ms)
    out = _prepare_out(out)
    cam = seq.camera
    rho = readout_fraction(readout_ms / 1000.0, REAL_EXPOSURE_MS / 1000.0)
    rng = np.random.default_rng(seed)
    stamps, truths = [], []
    gt_poses = None
    if seq.groundtruth is not None:
        gt_poses = interpolate_poses(seq.groundtruth[0], seq.groundtruth[1], seq.timestamps)
    t0 = time.perf_counter()
    pbar = bar(len(seq), "blur", progress)
    for i in range(len(seq)):
        fr = seq[i]
        direction = _blur_direction(gt_poses, i, rng)
        depth = np.where(np.isfinite(fr.depth), fr.depth, np.nan).astype(np.float32)
        traj = _blur_path(direction, depth, cam, blur_px / (1.0 - rho))
        blurry = _blur_real_frame(fr.image, depth, cam, traj, n, rho)
        if noise > 0:
            blurry = blurry + rng.normal(scale=noise, size=blurry.shape)
        name = f"{fr.timestamp:.6f}.png"
        _write_gray(out / "rgb" / name, blurry)
        _write_gray(out / "sharp" / name, fr.image)
        _write_depth(out / "depth" / name, depth)
        known = gt_poses is not None and np.all(np.isfinite(gt_poses[i]))
        T_w = Pose.from_vector(jnp.asarray(gt_poses[i], jnp.float32)) if known else Pose.identity()
        stamps.append(fr.timestamp)
        truths.append((fr.timestamp, _real_truth(T_w, traj, rho, depth, cam), known))
        pbar.update()
    pbar.close()
    summary = _write_real_truth(out, cam, stamps, truths, exposure_info, readout_ms, seq.meta)
    summary.update(source=f"blurred real clip {seq.path}", blur_px_requested=blur_px, n=n, seed=seed)
    return _finish(out, summary, t0, exposure_info)


def _write_real_truth(out, cam: PinholeCamera, stamps, truths, exposure_info: bool, readout_ms: float, meta: dict) -> dict:
    """The layout of a blurred real clip: ``truths`` (stamp, _FrameTruth, whether the clip has a
    pose there); frames without one get no ground truth (groundtruth.txt, exposure.txt, rows)."""
    gt = [(t, f) for t, f, known in truths if known]
    exposure_ms = REAL_EXPOSURE_MS if exposure_info else None
    depth_sigma = meta.get("depth_sigma", DEPTH_SIGMA["sensor"])  # real RGB-D: Kinect-class unless the source says
    summary = _write_layout(out, cam, REAL_FPS, exposure_ms, 1.0, stamps, [t for t, _ in gt], [f.mid for _, f in gt],
                            [f.start for _, f in gt], [f.end for _, f in gt], [f.blur_px for _, f, _ in truths], depth_sigma,
                            readout_ms=readout_ms)
    if readout_ms > 0 and gt:
        _write_rows(out, [t for t, _ in gt], [f for _, f in gt], cam.height)
    summary.update(exposure_ms=REAL_EXPOSURE_MS, readout_ms=float(readout_ms))
    return summary
