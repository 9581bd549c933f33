"""Tracking benchmark: ours (n = 1, n = 64 autodiff / analytic, adaptive n) vs Open3D and OpenCV RGB-D
odometry, on the same frame pairs of a generated blurry sequence, in one run.

Each pair: keyframe = the sharp mid-exposure image of frame k with its depth; current = the blurry
frame k+1. The initial guess is constant velocity from the ground-truth mid-exposure poses of frames
k-1 and k (what a perfect constant-velocity model would predict). Accuracy: the median over the
keyframe's points of the reprojection error of the estimated start and end poses ("endpoint") and of
the mid-exposure pose ("mid"); single-pose methods (n = 1, Open3D, OpenCV) use their pose for both.
Times: median wall time per frame of the tracking call, excluding the first pair (compilation).
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
import yaml

from .datasets import open_sequence
from .geometry import ExposureTrajectory, Pose
from .io import read_image_gray
from .odometry import sequence_calibration
from .tracking import Keyframe, TrackerConfig, constant_velocity_guess, track
from .tracking import tracker as tracker_mod

__all__ = ["run_tracking_benchmark", "format_tracking_table"]


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


def _pairs(seq, frames: int):
    _, mids = seq.groundtruth
    _, S, E = seq.exposure_paths
    tau = float(seq.exposures[0]) if seq.exposures is not None else 0.0
    dt = float(np.median(np.diff(seq.timestamps)))
    for k in range(1, min(len(seq) - 1, frames + 1)):
        sharp_path = pathlib.Path(seq[k].path).parent.parent / "sharp" / pathlib.Path(seq[k].path).name
        T_w_ref = _P(mids[k])
        init = constant_velocity_guess(T_w_ref, _P(mids[k - 1]), _P(mids[k]), dt, tau)
        gt = ExposureTrajectory(T_w_ref.inverse().compose(_P(S[k + 1])), T_w_ref.inverse().compose(_P(E[k + 1])))
        yield k, read_image_gray(sharp_path), seq[k].depth, seq[k + 1], init, gt


def _single_pose_traj(T_ref_cur: Pose) -> ExposureTrajectory:
    return ExposureTrajectory(T_ref_cur, T_ref_cur)


def _open3d_method(camera, gamma):
    try:
        import open3d as o3d
    except Exception as exc:  # pragma: no cover - depends on the machine
        return None, f"open3d unavailable ({type(exc).__name__}: {exc})"
    intr = o3d.camera.PinholeCameraIntrinsic(camera.width, camera.height, float(camera.fx), float(camera.fy), float(camera.cx), float(camera.cy))
    option = o3d.pipelines.odometry.OdometryOption()
    jac = o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm()

    def rgbd(img, depth):
        color = o3d.geometry.Image(np.ascontiguousarray((np.clip(img, 0, 1) * 255).astype(np.uint8)))
        d = o3d.geometry.Image(np.ascontiguousarray(np.nan_to_num(depth, nan=0.0).astype(np.float32)))
        return o3d.geometry.RGBDImage.create_from_color_and_depth(color, d, depth_scale=1.0, depth_trunc=50.0, convert_rgb_to_intensity=True)

    def run(sharp, depth, frame, init: ExposureTrajectory):
        src = rgbd(sharp, depth)
        dst = rgbd(frame.image, frame.depth)
        guess = np.asarray(init.middle().inverse().as_matrix(), np.float64)  # T_cur_ref
        ok, T_cur_ref, _ = o3d.pipelines.odometry.compute_rgbd_odometry(src, dst, intr, guess, jac, option)
        T = T_cur_ref if ok else guess
        return _single_pose_traj(Pose.from_matrix(jnp.asarray(np.linalg.inv(T), jnp.float32))), bool(ok)

    return run, f"Open3D {o3d.__version__} compute_rgbd_odometry (hybrid term)"


def _opencv_method(camera):
    import cv2

    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(np.asarray(camera.K(), np.float32))
    odo = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)

    def run(sharp, depth, frame, init: ExposureTrajectory):
        to8 = lambda im: cv2.cvtColor((np.clip(im, 0, 1) * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR)
        d0 = np.nan_to_num(depth, nan=0.0).astype(np.float32)
        d1 = np.nan_to_num(frame.depth, nan=0.0).astype(np.float32)
        ok, Rt = odo.compute(d0, to8(sharp), d1, to8(frame.image))  # Rt · src = dst: T_cur_ref
        if not ok or Rt is None or not np.all(np.isfinite(Rt)):
            return init, False
        return _single_pose_traj(Pose.from_matrix(jnp.asarray(np.linalg.inv(Rt), jnp.float32))), True

    return run, f"OpenCV {cv2.__version__} cv2.Odometry RGB_DEPTH (COMMON)"


def run_tracking_benchmark(data, frames: int = 20, peers: bool = True, progress=sys.stderr) -> dict:
    """Run every method on the same ``frames`` pairs of the sequence in ``data``; returns the results."""
    seq = open_sequence(data)
    if seq.exposure_paths is None or seq.groundtruth is None:
        raise ValueError(f"{data}: the benchmark needs a generated sequence with exposure.txt and groundtruth.txt")
    base = TrackerConfig(**sequence_calibration(seq))
    gamma = base.response_gamma
    ours = {
        "n1": dataclasses.replace(base, blur_aware=False),
        "n64": dataclasses.replace(base, jacobian="autodiff"),
        "n64_analytic": dataclasses.replace(base, jacobian="analytic"),
        "n64_all_levels": dataclasses.replace(base, jacobian="analytic", n_per_level="same"),
        "adaptive": dataclasses.replace(base, jacobian="analytic", n_mode="adaptive"),
    }
    methods: dict[str, tuple] = {}
    peer_notes = {}
    if peers:
        o3d_run, note = _open3d_method(seq.camera, gamma)
        peer_notes["open3d"] = note
        if o3d_run is not None:
            methods["open3d"] = (o3d_run, None)
        cv_run, note = _opencv_method(seq.camera)
        peer_notes["opencv"] = note
        methods["opencv"] = (cv_run, None)
    rows: dict[str, dict] = {name: {"ms": [], "endpoint": [], "mid": [], "ok": 0} for name in [*ours, *methods]}
    recompiles = {name: 0 for name in ours}
    pairs = list(_pairs(seq, frames))
    t_start = time.perf_counter()
    for idx, (k, sharp, depth, frame, init, gt) in enumerate(pairs):
        for name, cfg in ours.items():
            kf = Keyframe.create(sharp, depth, seq.camera, cfg)
            before = tracker_mod._solve_level._cache_size()
            t0 = time.perf_counter()
            traj, status, _ = track(kf, frame.image, init, cfg)
            rows[name]["ms"].append(1000 * (time.perf_counter() - t0))
            if idx > 0:  # programs compiled after the first pair, per method
                recompiles[name] += tracker_mod._solve_level._cache_size() - before
            e, m = _errors(kf, traj, gt)
            rows[name]["endpoint"].append(e)
            rows[name]["mid"].append(m)
            rows[name]["ok"] += int(status.ok)
        kf_eval = Keyframe.create(sharp, depth, seq.camera, base)
        for name, (run, _) in methods.items():
            t0 = time.perf_counter()
            traj, ok = run(sharp, depth, frame, init)
            rows[name]["ms"].append(1000 * (time.perf_counter() - t0))
            e, m = _errors(kf_eval, traj, gt)
            rows[name]["endpoint"].append(e)
            rows[name]["mid"].append(m)
            rows[name]["ok"] += int(ok)
        if progress is not None:
            el = time.perf_counter() - t_start
            progress.write(f"\rbench {idx + 1}/{len(pairs)} pairs  {el:.0f} s")
            progress.flush()
    if progress is not None:
        progress.write("\n")
    summary = {"frames": len(pairs), "sequence": str(data), "resolution": f"{seq.camera.width}x{seq.camera.height}", "peers": peer_notes}
    table = {}
    for name, r in rows.items():
        ms = np.asarray(r["ms"][1:] if len(r["ms"]) > 1 else r["ms"])
        table[name] = {
            "median_ms": float(np.median(ms)),
            "endpoint_px": float(np.median(r["endpoint"])),
            "mid_px": float(np.median(r["mid"])),
            "endpoint_px_p90": float(np.percentile(r["endpoint"], 90)),
            "ok": r["ok"],
        }
    summary["methods"] = table
    for name in ours:
        table[name]["recompiles_after_first_frame"] = int(recompiles[name])
    # fixed-n methods compile once per level on the first frame; adaptive n compiles one program per
    # (level, n) the first time it meets that n, so it may compile later too (reported separately)
    fixed_recompiles = sum(recompiles[k] for k in ours if k != "adaptive")
    n1 = table["n1"]["median_ms"]
    for name in table:
        table[name]["ratio_to_n1"] = table[name]["median_ms"] / n1
    flat = {
        "n1_ms": table["n1"]["median_ms"],
        "n64_ms": table["n64"]["median_ms"],
        "n64_analytic_ms": table["n64_analytic"]["median_ms"],
        "adaptive_ms": table["adaptive"]["median_ms"],
        "open3d_ms": table.get("open3d", {}).get("median_ms"),
        "opencv_ms": table.get("opencv", {}).get("median_ms"),
        "n64_endpoint_px": table["n64"]["endpoint_px"],
        "n64_analytic_endpoint_px": table["n64_analytic"]["endpoint_px"],
        "n1_endpoint_px": table["n1"]["endpoint_px"],
        "adaptive_endpoint_px": table["adaptive"]["endpoint_px"],
        "recompiles_after_first_frame": int(fixed_recompiles),
        "adaptive_recompiles_after_first_frame": int(recompiles["adaptive"]),
    }
    summary.update(flat)
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


def _bench_data(preset: str, args, depth_model: str = "exact") -> pathlib.Path:
    """The generated sequence of a preset (``runs/bench_<preset>_<w>x<h>_seed<s>[_sensor]``), made
    again when missing, too short or older than the depth noise record in camera.yaml."""
    from .synthetic import PRESETS, SynthConfig, generate_sequence

    suffix = "" if depth_model == "exact" else f"_{depth_model}"
    data = pathlib.Path("runs") / f"bench_{preset}_{args.width}x{args.height}_seed{args.seed}{suffix}"
    if (not (data / "exposure.txt").is_file() or len(open_sequence(data)) < args.frames + 2
            or "depth_sigma" not in open_sequence(data).meta):
        cfg = SynthConfig(**{**PRESETS[preset], "frames": args.frames + 2, "width": args.width, "height": args.height, "seed": args.seed,
                             "depth_model": depth_model})
        generate_sequence(cfg, data, progress=None if args.quiet else sys.stderr)
    return data


def main_tracking(args) -> int:
    """``mbavo bench tracking``: one run per preset (default strong, then none), or ``--data DIR``."""
    progress = None if args.quiet else sys.stderr
    if args.data:
        runs = {pathlib.Path(args.data).name: pathlib.Path(args.data)}
    else:
        runs = {p: _bench_data(p, args) for p in args.preset.split(",")}
    results = {name: run_tracking_benchmark(data, args.frames, peers=not args.no_peers, progress=progress) for name, data in runs.items()}
    if args.format == "json":
        print(json.dumps(results if len(results) > 1 else next(iter(results.values())), indent=2))
    else:
        print("\n\n".join(f"[{name}]\n{format_tracking_table(r)}" for name, r in results.items()))
    return 0


# ------------------------------------------------------------------------------ odometry benchmark


def _open3d_step(seq, term: str):
    """Open3D ``compute_rgbd_odometry`` between consecutive frames. ``term="hybrid"`` (Open3D's
    default: photometric + geometric ICP on the current frame's depth) or ``"color"`` (photometric
    only: the like-for-like peer of a direct photometric tracker)."""
    import open3d as o3d

    cam = seq.camera
    intr = o3d.camera.PinholeCameraIntrinsic(cam.width, cam.height, float(cam.fx), float(cam.fy), float(cam.cx), float(cam.cy))
    option = o3d.pipelines.odometry.OdometryOption()
    jac = {"hybrid": o3d.pipelines.odometry.RGBDOdometryJacobianFromHybridTerm,
           "color": o3d.pipelines.odometry.RGBDOdometryJacobianFromColorTerm}[term]()

    def prepare(f):
        color = o3d.geometry.Image(np.ascontiguousarray((np.clip(f.image, 0, 1) * 255).astype(np.uint8)))
        d = o3d.geometry.Image(np.ascontiguousarray(np.nan_to_num(f.depth, nan=0.0).astype(np.float32)))
        return o3d.geometry.RGBDImage.create_from_color_and_depth(color, d, depth_scale=1.0, depth_trunc=50.0, convert_rgb_to_intensity=True)

    def step(prev, cur, guess_prev_cur):
        ok, T_cur_prev, _ = o3d.pipelines.odometry.compute_rgbd_odometry(prev, cur, intr, np.linalg.inv(guess_prev_cur), jac, option)
        return ok, (np.linalg.inv(T_cur_prev) if ok else None)

    return prepare, step


def _opencv_step(seq):
    """OpenCV ``cv2.Odometry`` (RGB_DEPTH, COMMON) between consecutive frames (no initial guess)."""
    import cv2

    settings = cv2.OdometrySettings()
    settings.setCameraMatrix(np.asarray(seq.camera.K(), np.float32))
    odo = cv2.Odometry(cv2.OdometryType_RGB_DEPTH, settings, cv2.OdometryAlgoType_COMMON)

    def prepare(f):
        return (np.nan_to_num(f.depth, nan=0.0).astype(np.float32), cv2.cvtColor((np.clip(f.image, 0, 1) * 255).astype(np.uint8), cv2.COLOR_GRAY2BGR))

    def step(prev, cur, guess_prev_cur):
        ok, Rt = odo.compute(prev[0], prev[1], cur[0], cur[1])  # Rt · src = dst: T_cur_prev
        if not ok or Rt is None or not np.all(np.isfinite(Rt)):
            return False, None
        return True, np.linalg.inv(Rt)

    return prepare, step


def _peer_odometry(seq, out: pathlib.Path, prepare, step) -> dict:
    """Frame-to-frame odometry of a peer method chained into a trajectory; failed frames are dropped
    (no pose) and the chain continues from the last good frame with constant velocity."""
    from .io import TrajectoryWriter

    out.mkdir(parents=True, exist_ok=True)
    writer = TrajectoryWriter(out / "trajectory.txt")
    T_w = np.eye(4)
    prev = prepare(seq[0])
    writer.write(seq.timestamps[0], np.asarray(Pose.from_matrix(jnp.asarray(T_w)).to_vector()))
    vel = np.eye(4)  # T_prev_cur of the last step
    drops, ms = 0, []
    for i in range(1, len(seq)):
        cur = prepare(seq[i])
        t0 = time.perf_counter()
        ok, T_prev_cur = step(prev, cur, vel)
        ms.append(1000 * (time.perf_counter() - t0))
        if ok:
            vel = T_prev_cur
            T_w = T_w @ vel
            writer.write(seq.timestamps[i], np.asarray(Pose.from_matrix(jnp.asarray(T_w, jnp.float32)).to_vector()))
            prev = cur
        else:
            drops += 1
    writer.close()
    return {"frames": len(seq), "dropped": drops, "median_ms": float(np.median(ms)) if ms else 0.0}


def _deblur_quality(seq, run: pathlib.Path) -> dict:
    """PSNR/SSIM of the keyframe images (deblurred where blurred more than ``deblur_min_blur_px``,
    the first one too) against the generated sharp frames, and of the blurry input against the same."""
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


def _ate(t_gt, p_gt, run: pathlib.Path) -> float:
    """SE3-aligned ATE RMSE of ``run/trajectory.txt``; NaN when fewer than 3 poses match (lost run)."""
    from . import evaluation as ev
    from .errors import MbavoError
    from .io import read_tum_trajectory

    t_est, p_est = read_tum_trajectory(run / "trajectory.txt")
    try:
        return float(ev.ape(t_gt, p_gt, t_est, p_est, align="se3", max_diff=0.02)["rmse"])
    except MbavoError:
        return float("nan")


ODOMETRY_METHODS = ("ours_n64", "ours_n1", "ours_adaptive", "ours_n64_depth", "ours_n1_depth", "open3d", "open3d_color", "opencv")


def _check_methods(methods):
    from .errors import MbavoError

    unknown = sorted(set(methods) - set(ODOMETRY_METHODS))
    if unknown or not methods:
        raise MbavoError(f"unknown benchmark method(s) {', '.join(unknown) or '(none left)'}; choose from {', '.join(ODOMETRY_METHODS)}")


def run_odometry_benchmark(sequences: dict, out_root, progress=sys.stderr, tracker_overrides: dict | None = None,
                           depth_weight: float = 0.03, methods=ODOMETRY_METHODS) -> dict:
    """ATE (SE3) and frame drops for ours n=64, n=1, adaptive n (images only, as MBA-VO), ours n=64
    and n=1 with the current frame's depth (``depth_weight``, noise model from camera.yaml), Open3D
    (hybrid and colour terms) and OpenCV RGB-D odometry on each sequence. Our seconds per frame is
    the whole loop's wall time (compilation, keyframe selection and deblurring included); the
    peers' is their median odometry call. ``tracker_overrides``: TrackerConfig fields for our runs
    (e.g. small images). ``methods``: the subset of :data:`ODOMETRY_METHODS` to run."""
    from .odometry import OdometryConfig, run_odometry

    _check_methods(methods)

    out_root = pathlib.Path(out_root)
    results = {}
    for name, path in sequences.items():
        seq = open_sequence(path)
        base = TrackerConfig(**{**(tracker_overrides or {}), **sequence_calibration(seq), "depth_weight": 0.0})
        configs = {
            "ours_n64": base,
            "ours_n1": dataclasses.replace(base, blur_aware=False),
            "ours_adaptive": dataclasses.replace(base, n_mode="adaptive"),
            "ours_n64_depth": dataclasses.replace(base, depth_weight=depth_weight),
            "ours_n1_depth": dataclasses.replace(base, blur_aware=False, depth_weight=depth_weight),
        }
        configs = {m: c for m, c in configs.items() if m in methods}
        row = {}
        t_gt, p_gt = seq.groundtruth
        for method, cfg in configs.items():
            run = out_root / name / method
            if progress is not None:
                progress.write(f"{name}: {method}\n")
            t0 = time.perf_counter()
            summ = run_odometry(seq, run, cfg, OdometryConfig(), progress=progress)
            el = time.perf_counter() - t0
            with open(run / "frames.csv") as fh:
                track_ms = [float(r["ms"]) for r in csv.DictReader(fh) if r["status"] != "keyframe"]
            row[method] = {"ate_rmse_m": _ate(t_gt, p_gt, run), "frame_drop_rate": summ["frame_drop_rate"], "keyframes": summ["keyframes"],
                           "seconds_per_frame": el / max(summ["frames"], 1), "median_track_ms": float(np.median(track_ms)) if track_ms else 0.0}
            if method == "ours_n64":
                row[method]["deblur"] = _deblur_quality(seq, run)
        peers = {"open3d": lambda: _open3d_step(seq, "hybrid"), "open3d_color": lambda: _open3d_step(seq, "color"), "opencv": lambda: _opencv_step(seq)}
        for method, make in ((m, mk) for m, mk in peers.items() if m in methods):
            try:
                prepare, step = make()
            except ImportError as exc:
                row[method] = {"error": f"unavailable: {exc}"}
                continue
            if progress is not None:
                progress.write(f"{name}: {method}\n")
            p_sum = _peer_odometry(seq, out_root / name / method, prepare, step)
            row[method] = {"ate_rmse_m": _ate(t_gt, p_gt, out_root / name / method), "frame_drop_rate": p_sum["dropped"] / p_sum["frames"],
                           "seconds_per_frame": p_sum["median_ms"] / 1000}
        blur = yaml.safe_load((pathlib.Path(path) / "synth.yaml").read_text()).get("mean_blur_px") if (pathlib.Path(path) / "synth.yaml").is_file() else None
        results[name] = {"mean_blur_px": blur, "frames": len(seq), "depth_sigma": list(base.depth_sigma), "depth_weight": depth_weight, "methods": row}
    return results


def format_odometry_table(res: dict) -> str:
    """Three tables, one row per method and one column per sequence: ATE (mm), frame-drop rate,
    seconds per frame; then the deblurred keyframes' PSNR/SSIM."""
    names = list(res)
    head = f"{'method':<16}" + "".join(f"{n:>16}" for n in names)
    methods = [m for m in ODOMETRY_METHODS if any(m in r["methods"] for r in res.values())]

    def table(title, cell):
        lines = [title, head]
        for m in methods:
            lines.append(f"{m:<16}" + "".join(f"{cell(res[n]['methods'].get(m, {})):>16}" for n in names))
        return lines

    def ms(x):
        if "seconds_per_frame" not in x:
            return "-"
        t = f"{x['seconds_per_frame']:.3f}"
        return t + (f" [{x['median_track_ms']:.0f}]" if "median_track_ms" in x else "")

    lines = [f"{'':<16}" + "".join(f"{(f'{b:.1f} px' if b is not None else 'blur ?'):>16}" for b in (r["mean_blur_px"] for r in res.values())), ""]
    lines += table("ATE, SE3-aligned RMSE (mm)", lambda x: f"{1000 * x['ate_rmse_m']:.2f}" if "ate_rmse_m" in x else x.get("error", "-")[:15])
    lines += ["", *table("frame-drop rate", lambda x: f"{x['frame_drop_rate']:.2f}" if "frame_drop_rate" in x else "-")]
    lines += ["", *table("seconds per frame: ours = whole loop incl. compilation, keyframes, deblurring [median tracking ms]; peers = median call", ms)]
    lines += ["", "deblurred keyframes (ours_n64): PSNR dB (blurry input) / SSIM (blurry input)"]
    for n, r in res.items():
        d = r["methods"].get("ours_n64", {}).get("deblur") or {}
        lines.append(f"{n:<16}" + (f"{d['psnr_deblurred']:.2f} ({d['psnr_blurry']:.2f}) / {d['ssim_deblurred']:.3f} ({d['ssim_blurry']:.3f}), {d['keyframes']} keyframes" if d else "-"))
    lines += ["", "ours_n64/n1/adaptive: images only (MBA-VO); *_depth: plus the current frame's depth (tracking.geometric);",
              "open3d: hybrid term (photometric + ICP on the current frame's depth); open3d_color: photometric only;",
              "opencv: cv2.Odometry RGB_DEPTH (uses the current frame's depth); *_sensor sequences: Kinect-class depth (mbavo synth --depth-model sensor)"]
    return "\n".join(lines)


def main_odometry(args) -> int:
    """``mbavo bench odometry``: generated sequences at each blur preset plus the blurred TUM clip."""
    from .synthetic import blur_real_sequence

    progress = None if args.quiet else sys.stderr
    methods = [m.strip() for m in args.methods.split(",") if m.strip()] if args.methods else list(ODOMETRY_METHODS)
    if args.no_peers:
        methods = [m for m in methods if m.startswith("ours_")]
    _check_methods(methods)
    root = pathlib.Path(args.out)
    seqs = {}
    a = argparse_ns(frames=args.frames - 2, width=args.width, height=args.height, seed=args.seed, quiet=args.quiet)
    for preset in filter(None, args.presets.split(",")):
        seqs[preset] = _bench_data(preset, a)
    for preset in filter(None, args.sensor_presets.split(",")):
        seqs[f"{preset}_sensor"] = _bench_data(preset, a, depth_model="sensor")
    if args.tum:
        tum_src = pathlib.Path(args.tum)
        tum_out = pathlib.Path("runs") / "bench_tum_blurred"
        if not (tum_out / "exposure.txt").is_file():
            blur_real_sequence(open_sequence(tum_src), tum_out, blur_px=20.0, progress=progress)
        seqs["tum_blurred"] = tum_out
    res = run_odometry_benchmark(seqs, root, progress=progress, depth_weight=args.depth_weight, methods=methods)
    print(json.dumps(res, indent=2) if args.format == "json" else format_odometry_table(res))
    (root / "results.json").write_text(json.dumps(res, indent=2))
    return 0


def argparse_ns(**kw):
    import argparse

    return argparse.Namespace(**kw)
