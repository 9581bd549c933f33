"""``mbavo bench``: the tracking benchmark (frame pairs) and the odometry benchmark (whole sequences),
ours against Open3D and OpenCV RGB-D odometry on the same data.

Tracking: each pair is the sharp mid-exposure image of frame k with its depth (keyframe) and the
blurry frame k+1, from a constant-velocity guess of the true mid-exposure poses of frames k-1 and k.
Accuracy: median reprojection error over the keyframe's points of the estimated start and end poses
("endpoint") and of the mid-exposure pose ("mid"); single-pose methods use their pose for both.
Times: median wall time of the tracking call, first pair (compilation) excluded.

Odometry: a sweep (``mbavo_jax.sweep``) of the sequences x the methods of ``ODOMETRY_METHODS``
(ours: overrides in ``OURS_ODOMETRY``; peers: ``run_peer``), its rows gathered per sequence.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import pathlib
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

from . import tracking
from .config import PRESETS, BenchConfig, EvalConfig, OdometryConfig, RunConfig, SweepConfig, SynthConfig, TrackerConfig, calibration_of
from .datasets import open_sequence
from .errors import DataError, MbavoError
from .evaluation import evaluate_run
from .geometry import ExposureTrajectory, Pose
from .io import read_image_gray
from .methods import ODOMETRY_METHODS, check_methods, parse_methods
from .progress import bar
from .tracking import Keyframe, constant_velocity_guess, track

__all__ = ["run_tracking_benchmark", "format_tracking_table", "run_odometry_benchmark", "format_odometry_table",
           "main_tracking", "main_odometry", "Open3DPeer", "OpenCVPeer", "ODOMETRY_METHODS", "OURS_ODOMETRY",
           "odometry_sweep", "nested_results", "run_ours", "run_peer", "make_peer", "deblur_quality", "tum_blurred",
           "bench_data", "with_hidden_exposure", "tracking_pairs"]

# ---------------------------------------------------------------------------------------- peers


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


# ---------------------------------------------------------------------------- tracking benchmark

# our tracker settings in the tracking benchmark, on top of the sequence's calibration
OURS_TRACKING = {
    "n1": dict(blur_aware=False),
    "n64": dict(jacobian="autodiff"),
    "n64_analytic": dict(jacobian="analytic"),
    "n64_tangent": dict(jacobian="tangent"),  # the default
    "n64_all_levels": dict(jacobian="tangent", n_per_level="same"),
    "adaptive": dict(jacobian="tangent", n_mode="adaptive"),
}


def _P(v):
    return Pose.from_vector(jnp.asarray(v, jnp.float32))


@jax.jit
def _reproj(cam, pixels, depths, valid, est: Pose, gt: Pose):
    X = jax.vmap(cam.backproject)(pixels, depths)
    pa = jax.vmap(lambda p: cam.project(est.inverse().apply(p)))(X)
    pb = jax.vmap(lambda p: cam.project(gt.inverse().apply(p)))(X)
    return jnp.where(valid, jnp.linalg.norm(pa - pb, axis=1), jnp.nan)


def _errors(kf: Keyframe, est: ExposureTrajectory, gt: ExposureTrajectory):
    pts, cam = kf.points[0], kf.cameras[0]
    args = (cam, *pts.on_device)
    ends = np.concatenate([np.asarray(_reproj(*args, est.start, gt.start)), np.asarray(_reproj(*args, est.end, gt.end))])
    mid = np.asarray(_reproj(*args, est.middle(), gt.middle()))
    return float(np.nanmedian(ends)), float(np.nanmedian(mid))


def tracking_pairs(seq, frames: int):
    """(index, sharp keyframe, its depth, next frame, constant-velocity guess, true path) per pair; the
    guess's exposure is the recorded one, or without metadata ``odometry.exposure_guess`` of the interval."""
    _, mids = seq.groundtruth
    _, S, E = seq.exposure_paths
    dt = float(np.median(np.diff(seq.timestamps)))
    tau = float(seq.exposures[0]) if seq.exposures is not None else OdometryConfig().exposure_guess * dt
    for k in range(1, min(len(seq) - 1, frames + 1)):
        sharp_path = pathlib.Path(seq[k].path).parent.parent / "sharp" / pathlib.Path(seq[k].path).name
        T_w_ref = _P(mids[k])
        init = constant_velocity_guess(T_w_ref, _P(mids[k - 1]), _P(mids[k]), dt, tau)
        gt = ExposureTrajectory(T_w_ref.inverse().compose(_P(S[k + 1])), T_w_ref.inverse().compose(_P(E[k + 1])))
        yield k, read_image_gray(sharp_path), seq[k].depth, seq[k + 1], init, gt


def _tracking_peers(camera, peers: bool, depth_max: float) -> tuple[dict, dict]:
    """(adapters, notes): the peers that load, and a line on each."""
    adapters, notes = {}, {}
    if not peers:
        return adapters, notes
    try:
        adapters["open3d"] = Open3DPeer(camera, depth_max=depth_max)
        notes["open3d"] = adapters["open3d"].note
    except Exception as exc:  # pragma: no cover - depends on the machine
        notes["open3d"] = f"open3d unavailable ({type(exc).__name__}: {exc})"
    adapters["opencv"] = OpenCVPeer(camera, depth_max)
    notes["opencv"] = adapters["opencv"].note
    return adapters, notes


def _record(row: dict, ms: float, kf: Keyframe, traj: ExposureTrajectory, gt: ExposureTrajectory, ok: bool) -> None:
    e, m = _errors(kf, traj, gt)
    row["ms"].append(ms)
    row["endpoint"].append(e)
    row["mid"].append(m)
    row["ok"] += int(ok)


def _track_pair(rows: dict, recompiles: dict, ours: dict, peers: dict, camera, base: TrackerConfig, first: bool, pair) -> None:
    """Every method on one pair; our programs compiled after the first pair counted in ``recompiles``."""
    _, sharp, depth, frame, init, gt = pair
    for name, cfg in ours.items():
        kf = Keyframe.create(sharp, depth, camera, cfg)
        before = tracking.compiled_programs()
        t0 = time.perf_counter()
        traj, status, _ = track(kf, frame.image, init, cfg)
        ms = 1000 * (time.perf_counter() - t0)
        if not first:
            recompiles[name] += tracking.compiled_programs() - before
        _record(rows[name], ms, kf, traj, gt, status.ok)
    kf_eval = Keyframe.create(sharp, depth, camera, base)
    guess = np.asarray(init.middle().inverse().as_matrix(), np.float64)  # T_cur_ref
    for name, peer in peers.items():
        t0 = time.perf_counter()
        ok, T_ref_cur = peer.relative_pose(peer.prepare(sharp, depth), peer.prepare(frame.image, frame.depth), guess)
        ms = 1000 * (time.perf_counter() - t0)
        if T_ref_cur is None:
            traj = init
        else:
            pose = Pose.from_matrix(jnp.asarray(T_ref_cur, jnp.float32))
            traj = ExposureTrajectory(pose, pose)
        _record(rows[name], ms, kf_eval, traj, gt, ok)


def _tracking_summary(rows: dict, recompiles: dict) -> dict:
    """Per-method medians and the flat numbers (``n64_ms``, ...) of the tracking benchmark."""
    table = {}
    for name, r in rows.items():
        ms = np.asarray(r["ms"][1:] if len(r["ms"]) > 1 else r["ms"])
        table[name] = {"median_ms": float(np.median(ms)), "endpoint_px": float(np.median(r["endpoint"])),
                       "mid_px": float(np.median(r["mid"])), "endpoint_px_p90": float(np.percentile(r["endpoint"], 90)), "ok": r["ok"]}
    for name, n in recompiles.items():
        table[name]["recompiles_after_first_frame"] = int(n)
    for name in table:
        table[name]["ratio_to_n1"] = table[name]["median_ms"] / table["n1"]["median_ms"]
    # fixed n compiles once per level on the first pair; adaptive n once per new (level, n), so later too
    return {
        "methods": table,
        **{f"{m}_ms": table[m]["median_ms"] for m in ("n1", "n64", "n64_analytic", "n64_tangent", "adaptive")},
        "open3d_ms": table.get("open3d", {}).get("median_ms"),
        "opencv_ms": table.get("opencv", {}).get("median_ms"),
        **{f"{m}_endpoint_px": table[m]["endpoint_px"] for m in ("n64", "n64_analytic", "n64_tangent", "n1", "adaptive")},
        "recompiles_after_first_frame": int(sum(n for m, n in recompiles.items() if m != "adaptive")),
        "adaptive_recompiles_after_first_frame": int(recompiles["adaptive"]),
    }


def run_tracking_benchmark(data, frames: int = 20, peers: bool = True, progress: bool = True,
                           peer_depth_max: float = BenchConfig().peer_depth_max) -> dict:
    """Every method on the same ``frames`` pairs of the generated sequence in ``data``; the results."""
    seq = open_sequence(data)
    if seq.exposure_paths is None or seq.groundtruth is None:
        raise DataError(data, "the tracking benchmark needs a generated sequence with exposure.txt and groundtruth.txt")
    base = TrackerConfig(**calibration_of(seq.meta))
    ours = {name: dataclasses.replace(base, **changes) for name, changes in OURS_TRACKING.items()}
    adapters, notes = _tracking_peers(seq.camera, peers, peer_depth_max)
    rows = {name: {"ms": [], "endpoint": [], "mid": [], "ok": 0} for name in [*ours, *adapters]}
    recompiles = dict.fromkeys(ours, 0)
    pairs = list(tracking_pairs(seq, frames))
    with bar(len(pairs), "bench", progress, unit="pair") as pbar:
        for idx, pair in enumerate(pairs):
            _track_pair(rows, recompiles, ours, adapters, seq.camera, base, idx == 0, pair)
            pbar.update()
    summary = {"frames": len(pairs), "sequence": str(data), "resolution": f"{seq.camera.width}x{seq.camera.height}", "peers": notes}
    summary.update(_tracking_summary(rows, recompiles))
    return summary


def format_tracking_table(s: dict) -> str:
    lines = [
        f"tracking benchmark: {s['frames']} frame pairs, {s['resolution']}, sequence {s['sequence']}",
        f"{'method':<16} {'median ms':>10} {'x n=1':>7} {'endpoint px':>12} {'p90':>7} {'mid px':>8} {'ok':>5}",
    ]
    for name, r in s["methods"].items():
        lines.append(
            f"{name:<16} {r['median_ms']:>10.1f} {r['ratio_to_n1']:>7.2f} {r['endpoint_px']:>12.3f} {r['endpoint_px_p90']:>7.2f} {r['mid_px']:>8.3f} {r['ok']:>3}/{s['frames']}"
        )
    lines.append(
        f"recompilations after the first frame: {s['recompiles_after_first_frame']} (fixed n), "
        f"{s['adaptive_recompiles_after_first_frame']} (adaptive n: one per new (level, n) bucket)"
    )
    for k, v in s["peers"].items():
        lines.append(f"{k}: {v}")
    return "\n".join(lines)


def bench_data(preset: str, cfg: BenchConfig, frames: int, quiet: bool = False, depth_model: str = "exact",
                scene: str = "room", exact: bool = False) -> pathlib.Path:
    """The generated sequence of a preset (``runs/bench_<preset>[_<scene>]_<w>x<h>_seed<s>[_sensor]``),
    made again when missing, shorter than ``frames`` (``exact``: of another length, for benchmarks that
    run the whole folder) or older than the depth noise record in camera.yaml."""
    from .synthetic import generate_sequence

    if preset not in PRESETS:
        raise MbavoError(f"unknown blur preset '{preset}' (choose from {', '.join(PRESETS)})")
    suffix = "" if depth_model == "exact" else f"_{depth_model}"
    label = preset if scene == "room" else f"{preset}_{scene}"
    data = pathlib.Path("runs") / f"bench_{label}_{cfg.width}x{cfg.height}_seed{cfg.seed}{suffix}"
    seq = open_sequence(data) if (data / "exposure.txt").is_file() else None
    if seq is None or len(seq) < frames or (exact and len(seq) != frames) or "depth_sigma" not in seq.meta:
        synth = SynthConfig(**{**PRESETS[preset], "frames": frames, "width": cfg.width, "height": cfg.height, "seed": cfg.seed,
                               "depth_model": depth_model, "scene": scene})
        generate_sequence(synth, data, progress=not quiet)
    return data


def with_hidden_exposure(seqs: dict, names: str) -> dict:
    """``seqs`` plus, for each of ``names`` (or 'all'), ``<name>_noexp``: the same images with the
    exposure metadata removed (``synthetic.exposure_hidden_copy``, next to the data)."""
    from .synthetic import exposure_hidden_copy

    chosen = list(seqs) if names.strip() == "all" else [n for n in names.split(",") if n]
    unknown = [n for n in chosen if n not in seqs]
    if unknown:
        raise MbavoError(f"bench.hide_exposure: no sequence named {', '.join(unknown)} (have {', '.join(seqs)})")
    out = {}
    for name, path in seqs.items():
        out[name] = path
        if name in chosen:
            path = pathlib.Path(path)
            out[f"{name}_noexp"] = exposure_hidden_copy(path, path.parent / f"{path.name}_noexp")
    return out


def main_tracking(cfg: BenchConfig, data=None, fmt: str = "table", quiet: bool = False) -> int:
    """``mbavo bench tracking``: one run per preset of ``cfg.preset`` (default strong, then none), or on ``data``."""
    if data:
        runs = {pathlib.Path(data).name: pathlib.Path(data)}
    else:
        runs = {p: bench_data(p, cfg, cfg.frames + 2, quiet) for p in cfg.preset.split(",")}
    runs = with_hidden_exposure(runs, cfg.hide_exposure)
    results = {name: run_tracking_benchmark(path, cfg.frames, peers=not cfg.no_peers, progress=not quiet,
                                                 peer_depth_max=cfg.peer_depth_max) for name, path in runs.items()}
    if fmt == "json":
        print(json.dumps(results if len(results) > 1 else next(iter(results.values())), indent=2))
    else:
        print("\n\n".join(f"[{name}]\n{format_tracking_table(r)}" for name, r in results.items()))
    return 0


# ---------------------------------------------------------------------------- odometry benchmark


def _peer_odometry(seq, out: pathlib.Path, peer) -> dict:
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


def deblur_quality(seq, run: pathlib.Path) -> dict:
    """Mean PSNR/SSIM of this run's keyframe images (deblurred where blurred) and of the blurry
    input, both against the generated sharp frames."""
    from .deblur import psnr, ssim
    from .io import read_tum_trajectory

    rows = []
    stamps, _ = read_tum_trajectory(run / "keyframes.txt")  # this run's keyframes, not stale files
    for stamp in stamps:
        p = run / "keyframes" / f"{stamp:.6f}.png"
        k = int(np.argmin(np.abs(seq.timestamps - stamp)))
        sharp_path = pathlib.Path(seq[k].path).parent.parent / "sharp" / pathlib.Path(seq[k].path).name
        if not sharp_path.is_file():
            continue
        ref = read_image_gray(sharp_path)
        deb = read_image_gray(p)  # 16-bit keyframe image
        rows.append((psnr(deb, ref), psnr(seq[k].image, ref), ssim(deb, ref), ssim(seq[k].image, ref)))
    if not rows:
        return {}
    a = np.asarray(rows)
    return {"keyframes": len(rows), "psnr_deblurred": float(a[:, 0].mean()), "psnr_blurry": float(a[:, 1].mean()),
            "ssim_deblurred": float(a[:, 2].mean()), "ssim_blurry": float(a[:, 3].mean())}


def _ate(seq, run: pathlib.Path, config: EvalConfig) -> float:
    """ATE RMSE of a run; NaN when it cannot be scored (fewer than 3 matched poses: a lost run)."""
    return evaluate_run(run, seq.groundtruth, config=config).get("ate_rmse_m", float("nan"))


# our methods of the odometry benchmark: overrides of the defaults (``{depth_weight}``: BenchConfig.depth_weight)
OURS_ODOMETRY = {
    "ours_n64": (),
    "ours_n1": ("tracker.blur_aware=false",),
    "ours_adaptive": ("tracker.n_mode=adaptive",),
    "ours_n64_depth": ("tracker.depth_weight={depth_weight}",),
    "ours_n1_depth": ("tracker.blur_aware=false", "tracker.depth_weight={depth_weight}"),
}


def run_ours(seq, run: pathlib.Path, config: RunConfig, progress: bool = False) -> dict:
    """Our loop over a sequence: ATE, frame drops, keyframes, whole-loop seconds per frame, the
    exposure quality and (generated sequences) the deblurred keyframes' PSNR/SSIM."""
    from .odometry import run_odometry

    t0 = time.perf_counter()
    summ = run_odometry(seq, run, config, progress=progress)
    el = time.perf_counter() - t0
    with open(run / "frames.csv") as fh:
        track_ms = [float(r["ms"]) for r in csv.DictReader(fh) if r["status"] != "keyframe"]
    deblur = {("deblur_keyframes" if k == "keyframes" else k): v for k, v in deblur_quality(seq, run).items()}
    return {"ate_rmse_m": _ate(seq, run, config.evaluation), "frame_drop_rate": summ["frame_drop_rate"], "keyframes": summ["keyframes"],
            "seconds_per_frame": el / max(summ["frames"], 1), "median_track_ms": float(np.median(track_ms)) if track_ms else 0.0,
            **_exposure_quality(seq, run, summ), **deblur}


def _exposure_quality(seq, run: pathlib.Path, summ: dict) -> dict:
    """How the run had its exposure time (and the estimate), and the median over frames of its
    exposure paths' length over the true ones (generated sequences)."""
    from .evaluation import exposure_path_error
    from .io import read_exposure_file

    out = {k: summ[k] for k in ("exposure", "exposure_ms", "exposure_fraction", "exposure_samples") if k in summ}
    if seq.exposure_paths is not None:
        cam = seq.camera.as_dict()
        ratio = exposure_path_error(seq.exposure_paths, read_exposure_file(run / "exposure.txt"), cam).get("length_ratio")
        if ratio:
            out["exposure_length_ratio"] = ratio["median"]
    return out


def make_peer(method: str, camera, depth_max: float):
    """The peer adapter of ``method`` (open3d, open3d_color, opencv); MbavoError when its library is missing."""
    try:
        if method == "opencv":
            return OpenCVPeer(camera, depth_max)
        return Open3DPeer(camera, {"open3d": "hybrid", "open3d_color": "color"}[method], depth_max)
    except (ImportError, OSError) as exc:
        raise MbavoError(f"{method} unavailable: {exc}") from None


def run_peer(seq, run: pathlib.Path, method: str, evaluation: EvalConfig, depth_max: float) -> dict:
    """A peer's chained frame-to-frame odometry over a sequence: ATE, frame drops, median seconds per call."""
    p_sum = _peer_odometry(seq, run, make_peer(method, seq.camera, depth_max))
    return {"ate_rmse_m": _ate(seq, run, evaluation), "frame_drop_rate": p_sum["dropped"] / p_sum["frames"],
            "seconds_per_frame": p_sum["median_ms"] / 1000}


def odometry_sweep(sequences: dict, tracker_overrides: dict | None = None, depth_weight: float = 0.03,
                   methods=ODOMETRY_METHODS, peer_depth_max: float = BenchConfig().peer_depth_max):
    """The odometry benchmark as a sweep: ``sequences`` (name -> folder) x ``methods``; our methods
    with ``tracker_overrides`` (TrackerConfig fields, e.g. for small images) under their own."""
    from .sweep import SequenceSpec, SweepSpec, as_overrides

    check_methods(methods)
    base = as_overrides(tracker_overrides or {}, "tracker")
    ours = {m: (*base, *(o.format(depth_weight=repr(float(depth_weight))) for o in OURS_ODOMETRY[m])) for m in OURS_ODOMETRY if m in methods}
    return SweepSpec(sequences=tuple(SequenceSpec(name, path=str(path)) for name, path in sequences.items()), configurations=ours,
                     peers=tuple(m for m in ODOMETRY_METHODS if m in methods and m not in OURS_ODOMETRY), base=base,
                     peer_depth_max=peer_depth_max)


ROW_KEYS = ("sequence", "method", "status", "seconds", "overrides", "frames", "mean_blur_px", "depth_sigma")
DEBLUR_KEYS = {"deblur_keyframes": "keyframes", "psnr_deblurred": "psnr_deblurred", "psnr_blurry": "psnr_blurry",
               "ssim_deblurred": "ssim_deblurred", "ssim_blurry": "ssim_blurry"}


def _method_cell(row: dict) -> dict:
    """A sweep row as the benchmark's per-method dict (deblurring under ``deblur``)."""
    if row.get("status") != "ok":
        return {"error": row.get("error", "failed")}
    cell = {k: v for k, v in row.items() if k not in ROW_KEYS and k not in DEBLUR_KEYS and k != "error"}
    deblur = {DEBLUR_KEYS[k]: row[k] for k in DEBLUR_KEYS if row.get(k) is not None}
    return {**cell, "deblur": deblur} if deblur else cell


def nested_results(rows: list[dict], depth_weight: float) -> dict:
    """Sweep rows as the odometry benchmark's results: per sequence its blur, frames, depth noise
    and ``methods`` (method -> numbers, or ``{"error": ...}``)."""
    res = {}
    for row in rows:
        entry = res.setdefault(row["sequence"], {"mean_blur_px": None, "frames": None, "depth_sigma": None,
                                                 "depth_weight": depth_weight, "methods": {}})
        for k in ("mean_blur_px", "frames", "depth_sigma"):
            entry[k] = entry[k] if entry[k] is not None else row.get(k)
        entry["methods"][row["method"]] = _method_cell(row)
    return res


def run_odometry_benchmark(sequences: dict, out_root, progress: bool = True, tracker_overrides: dict | None = None,
                           depth_weight: float = 0.03, methods=ODOMETRY_METHODS,
                           peer_depth_max: float = BenchConfig().peer_depth_max, settings: SweepConfig = SweepConfig()) -> dict:
    """ATE (SE3) and frame drops of each of ``methods`` (see ODOMETRY_METHODS) on each sequence,
    run as a sweep into ``out_root`` (``runs/<sequence>/<method>/``, results.csv/.md, ate.png).
    Ours: whole-loop seconds per frame (compilation, keyframes and deblurring included), ``*_depth``
    with ``depth_weight``; peers: their median odometry call. ``tracker_overrides``: TrackerConfig
    fields for our runs (e.g. for small images); ``settings``: jobs, engine."""
    from .sweep import run_sweep, summary_line

    spec = odometry_sweep(sequences, tracker_overrides, depth_weight, methods, peer_depth_max)
    res = run_sweep(spec, out_root, settings, progress)
    if progress:
        print(summary_line(res), file=sys.stderr)
    return nested_results(res.rows, depth_weight)


def _exposure_cell(x: dict) -> str:
    if "exposure" not in x:
        return "-"
    ms = f"{x['exposure_ms']:.1f}" + (f" ({x['exposure_samples']})" if x["exposure"] == "estimate" else "")
    return ms + (f" | {x['exposure_length_ratio']:.2f}" if "exposure_length_ratio" in x else "")


def format_odometry_table(res: dict) -> str:
    """Three tables, one row per method and one column per sequence: ATE (mm), frame-drop rate,
    seconds per frame; then the deblurred keyframes' PSNR/SSIM."""
    names = list(res)
    w = max([20, *(len(n) + 2 for n in names)])  # a column fits its sequence's name and an exposure cell
    head = f"{'method':<16}" + "".join(f"{n:>{w}}" for n in names)
    methods = [m for m in ODOMETRY_METHODS if any(m in r["methods"] for r in res.values())]

    def table(title, cell):
        lines = [title, head]
        for m in methods:
            lines.append(f"{m:<16}" + "".join(f"{cell(res[n]['methods'].get(m, {})):>{w}}" for n in names))
        return lines

    def ms(x):
        if "seconds_per_frame" not in x:
            return "-"
        t = f"{x['seconds_per_frame']:.3f}"
        return t + (f" [{x['median_track_ms']:.0f}]" if "median_track_ms" in x else "")

    lines = [f"{'':<16}" + "".join(f"{(f'{b:.1f} px' if b is not None else 'blur ?'):>{w}}" for b in (r["mean_blur_px"] for r in res.values())), ""]
    lines += table("ATE, SE3-aligned RMSE (mm)", lambda x: f"{1000 * x['ate_rmse_m']:.2f}" if "ate_rmse_m" in x else x.get("error", "-")[:15])
    lines += ["", *table("frame-drop rate", lambda x: f"{x['frame_drop_rate']:.2f}" if "frame_drop_rate" in x else "-")]
    lines += ["", *table("seconds per frame: ours = whole loop incl. compilation, keyframes, deblurring [median tracking ms]; peers = median call", ms)]
    lines += ["", *table("exposure: ms as known or estimated (samples) | estimated path length / true (median over frames)", _exposure_cell)]
    lines += ["", "deblurred keyframes (ours_n64): PSNR dB (blurry input) / SSIM (blurry input)"]
    for n, r in res.items():
        d = r["methods"].get("ours_n64", {}).get("deblur") or {}
        lines.append(f"{n:<{w}}" + (f"{d['psnr_deblurred']:.2f} ({d['psnr_blurry']:.2f}) / {d['ssim_deblurred']:.3f} ({d['ssim_blurry']:.3f}), {d['keyframes']} keyframes" if d else "-"))
    lines += ["", "ours_n64/n1/adaptive: images only (MBA-VO); *_depth: plus the current frame's depth (tracking.geometric);",
              "open3d: hybrid term (photometric + ICP on the current frame's depth); open3d_color: photometric only;",
              "opencv: cv2.Odometry RGB_DEPTH (uses the current frame's depth); *_sensor sequences: Kinect-class depth (mbavo synth --depth-model sensor)"]
    return "\n".join(lines)


def real_clip(value: str) -> pathlib.Path:
    """The real clip a ``--tum`` / ``--kitti`` value names: the path as given when it exists, else the
    folder of that name in the shared data folder (``synthetic.scene.default_shared_data``), so that
    the defaults (``../shared/data/...``) work from any working folder."""
    from .synthetic.scene import default_shared_data

    path = pathlib.Path(value).expanduser()
    shared = default_shared_data()
    if path.exists() or shared is None or not (shared / path.name).is_dir():
        return path  # missing: the loader says so in one line
    return shared / path.name


def tum_blurred(cfg: BenchConfig, quiet: bool = False) -> pathlib.Path:
    """``runs/bench_tum_blurred``: the TUM clip ``cfg.tum`` blurred by ``mbavo synth --from`` (20 px), made once."""
    from .synthetic import blur_real_sequence

    out = pathlib.Path("runs") / "bench_tum_blurred"
    if not (out / "exposure.txt").is_file():
        blur_real_sequence(open_sequence(real_clip(cfg.tum)), out, blur_px=20.0, progress=not quiet)
    return out


def main_odometry(cfg: BenchConfig, fmt: str = "table", quiet: bool = False, settings: SweepConfig = SweepConfig()) -> int:
    """``mbavo bench odometry``: generated sequences at each blur preset plus the blurred TUM clip,
    run as a sweep (``settings``: jobs, engine; finished runs in ``cfg.out`` are kept)."""
    methods = parse_methods(cfg.methods, cfg.no_peers)
    seqs = {}
    for preset in filter(None, cfg.presets.split(",")):
        seqs[preset] = bench_data(preset, cfg, cfg.frames, quiet, exact=True)
    for preset in filter(None, cfg.sensor_presets.split(",")):
        seqs[f"{preset}_sensor"] = bench_data(preset, cfg, cfg.frames, quiet, depth_model="sensor", exact=True)
    for scene in filter(None, cfg.scenes.split(",")):
        for preset in filter(None, cfg.scene_presets.split(",")):
            seqs[f"{preset}_{scene}"] = bench_data(preset, cfg, cfg.frames, quiet, scene=scene, exact=True)
    if cfg.tum:
        seqs["tum_blurred"] = tum_blurred(cfg, quiet)
    seqs = with_hidden_exposure(seqs, cfg.hide_exposure)
    root = pathlib.Path(cfg.out)
    res = run_odometry_benchmark(seqs, root, progress=not quiet, depth_weight=cfg.depth_weight, methods=methods,
                                 peer_depth_max=cfg.peer_depth_max, settings=settings)
    print(json.dumps(res, indent=2) if fmt == "json" else format_odometry_table(res))
    (root / "results.json").write_text(json.dumps(res, indent=2))
    return 0
