"""The ``mbavo`` command line: ``mbavo jacobians | synth | eval | track | deblur | bench``.

Known errors (bad input files, bad options) print one line ``mbavo: error: ...`` and exit 1.
"""

from __future__ import annotations

import argparse
import json
import sys

__all__ = ["main"]


from .errors import MbavoError as UserError  # every user-facing error: one line, exit status 1


def _cmd_jacobians(args) -> int:
    from .paper import cross_validate, format_table

    results = cross_validate(seed=args.seed)
    if args.format == "json":
        print(json.dumps([r.as_dict() for r in results], indent=2, ensure_ascii=False))
    else:
        print(format_table(results))
    return 0


def _cmd_synth(args) -> int:
    import dataclasses

    from .synthetic import PRESETS, SynthConfig, blur_real_sequence, generate_sequence

    progress = None if args.quiet else sys.stderr
    if args.source:
        from .datasets import open_sequence

        seq = open_sequence(args.source)
        blur = args.blur_px if args.blur_px is not None else {"none": 0.0, "mild": 5.0, "strong": 20.0, "extreme": 40.0}[args.preset]
        summary = blur_real_sequence(seq, args.out, blur_px=blur, n=args.subframes or 64, seed=args.seed, noise=args.noise or 0.0, progress=progress)
    else:
        values = dict(PRESETS[args.preset])
        for key in ("frames", "width", "height", "fps", "exposure_ms", "speed", "rotation_rate", "subframes", "noise", "seed", "depth_model"):
            v = getattr(args, key)
            if v is not None:
                values[key] = v
        values["real_textures"] = not args.no_real_textures
        cfg = SynthConfig(**{k: v for k, v in values.items() if k in {f.name for f in dataclasses.fields(SynthConfig)}})
        if cfg.frames < 1 or cfg.width < 16 or cfg.height < 16:
            raise UserError("need --frames >= 1 and an image of at least 16x16 pixels")
        summary = generate_sequence(cfg, args.out, progress=progress)
    if not args.quiet:
        print(
            f"wrote {summary['frames']} frames to {args.out}: mean blur {summary['mean_blur_px']:.1f} px "
            f"(median {summary['median_blur_px']:.1f}, max {summary['max_blur_px']:.1f}) in {summary['seconds']:.1f} s"
        )
    return 0


def _cmd_eval(args) -> int:
    import numpy as np

    from . import evaluation as ev
    from .io import read_camera_yaml, read_exposure_file, read_tum_trajectory

    if args.metric == "exposure":
        ref = read_exposure_file(args.reference)
        est = read_exposure_file(args.estimate)
        cam = read_camera_yaml(args.camera)
        res = ev.exposure_path_error(ref, est, cam, depth=args.depth, max_diff=args.t_max_diff)
        _print_result(res, args.format, ["n_matched"], nested=("translation_m", "rotation_deg", "reprojection_px"))
        return 0
    t_ref, p_ref = read_tum_trajectory(args.reference)
    t_est, p_est = read_tum_trajectory(args.estimate)
    if args.metric == "ape":
        res = ev.ape(t_ref, p_ref, t_est, p_est, align=args.align, max_diff=args.t_max_diff)
    else:
        res = ev.rpe(t_ref, p_ref, t_est, p_est, delta=args.delta, align=args.align if args.align == "sim3" else "none", max_diff=args.t_max_diff)
    if args.sequence:
        from .datasets import open_sequence

        seq = open_sequence(args.sequence)
        res["frame_drop_rate"] = ev.frame_drop_rate(seq.timestamps, t_est, args.t_max_diff)
    errors = np.asarray(res.pop("errors"))
    if args.plot:
        import pathlib

        from .evaluation import plots

        out = pathlib.Path(args.plot)
        out.mkdir(parents=True, exist_ok=True)
        i_est, i_ref = ev.associate(t_est, t_ref, args.t_max_diff)
        if args.metric == "ape":
            from .evaluation.metrics import _align, pose_matrices

            T_al = _align(pose_matrices(p_ref[i_ref]), pose_matrices(p_est[i_est]), args.align)[0]
            plots.plot_trajectories(out / "trajectory.png", p_ref[i_ref, :3], T_al[:, :3, 3], f"APE rmse {res['rmse']:.4f} m ({args.align})")
            plots.plot_error_over_time(out / "ape_over_time.png", t_est[i_est], errors, "APE over time")
        else:
            plots.plot_error_over_time(out / "rpe_over_time.png", t_est[i_est][: len(errors)], errors, "RPE over time", "RPE [m]")
    _print_result(res, args.format, ["n_matched", "alignment", "scale", "delta", "frame_drop_rate"])
    return 0


def _cmd_info(args) -> int:
    from .datasets import open_sequence

    seq = open_sequence(args.sequence, args.kind)
    cam = seq.camera
    info = {
        "name": seq.name,
        "kind": seq.kind,
        "frames": len(seq),
        "duration_s": float(seq.timestamps[-1] - seq.timestamps[0]) if len(seq) > 1 else 0.0,
        "camera": {"fx": float(cam.fx), "fy": float(cam.fy), "cx": float(cam.cx), "cy": float(cam.cy), "width": cam.width, "height": cam.height},
        "depth": seq.has_depth,
        "exposure_times": seq.exposures is not None,
        "groundtruth_poses": 0 if seq.groundtruth is None else int(len(seq.groundtruth[0])),
        "exposure_paths": 0 if seq.exposure_paths is None else int(len(seq.exposure_paths[0])),
    }
    if args.check:
        for i in range(len(seq)):
            seq[i]  # raises DataError naming the file on a bad frame
            if not args.quiet and sys.stderr.isatty():
                sys.stderr.write(f"\rchecked {i + 1}/{len(seq)}")
        info["checked"] = True
    if args.format == "json":
        print(json.dumps(info, indent=2))
    else:
        for k, v in info.items():
            print(f"{k:>18}: {v}")
    return 0


def _tracker_setup(args, seq):
    from .odometry import load_config, sequence_calibration

    overrides = list(args.set or [])
    for key, value in sequence_calibration(seq).items():  # camera.yaml's response γ and depth noise
        if not any(o.startswith(f"tracker.{key}=") for o in overrides):
            overrides.insert(0, f"tracker.{key}={json.dumps(list(value) if isinstance(value, tuple) else value)}")
    return load_config(args.config, overrides)


def _evaluate_run(seq, out, quiet=False) -> dict:
    import numpy as np

    from . import evaluation as ev
    from .evaluation import plots
    from .io import read_tum_trajectory

    res = {}
    if seq.groundtruth is None or not (out / "trajectory.txt").is_file():
        return res
    t_est, p_est = read_tum_trajectory(out / "trajectory.txt")
    t_gt, p_gt = seq.groundtruth
    if len(t_est) < 3:
        return res
    try:
        ape = ev.ape(t_gt, p_gt, t_est, p_est, align="se3", max_diff=0.02)
    except UserError:
        return res
    res["ate_rmse_m"] = ape["rmse"]
    res["ate_median_m"] = ape["median"]
    res["frame_drop_rate"] = ev.frame_drop_rate(seq.timestamps, t_est, 0.02)
    i_est, i_ref = ev.associate(t_est, t_gt, 0.02)
    from .evaluation.metrics import _align, pose_matrices

    T_al = _align(pose_matrices(p_gt[i_ref]), pose_matrices(p_est[i_est]), "se3")[0]
    plots.plot_trajectories(out / "trajectory.png", p_gt[i_ref, :3], T_al[:, :3, 3], f"ATE rmse {ape['rmse']:.4f} m (SE3)")
    plots.plot_error_over_time(out / "ape_over_time.png", t_est[i_est], np.asarray(ape["errors"]), "APE over time")
    return res


def _cmd_track(args) -> int:
    import pathlib

    from .datasets import open_sequence
    from .odometry import run_odometry

    seq = open_sequence(args.sequence, args.kind)
    tracker, odo = _tracker_setup(args, seq)
    out = pathlib.Path(args.out)
    summary = run_odometry(seq, out, tracker, odo, resume=args.resume, max_frames=args.max_frames, progress=None if args.quiet else sys.stderr)
    summary.update(_evaluate_run(seq, out))
    summary["out"] = str(out)
    if args.format == "json":
        print(json.dumps(summary, indent=2))
    else:
        for k, v in summary.items():
            print(f"{k:>16}: {v:.4f}" if isinstance(v, float) else f"{k:>16}: {v}")
    return 0


def _cmd_deblur(args) -> int:
    import pathlib

    import cv2
    import jax.numpy as jnp
    import numpy as np

    from .datasets import open_sequence
    from .deblur import deblur, psnr, ssim
    from .geometry import ExposureTrajectory, Pose
    from .io import read_exposure_file, read_image_gray

    seq = open_sequence(args.sequence)
    if not 0 <= args.frame < len(seq):
        raise UserError(f"--frame {args.frame} out of range (the sequence has {len(seq)} frames)")
    frame = seq[args.frame]
    if frame.depth is None:
        raise UserError(f"{seq.path}: deblurring needs depth")
    source = pathlib.Path(args.exposure) if args.exposure else pathlib.Path(seq.path) / "exposure.txt"
    stamps, starts, ends = read_exposure_file(source)
    j = int(np.argmin(np.abs(stamps - frame.timestamp)))
    if abs(stamps[j] - frame.timestamp) > 0.01:
        raise UserError(f"{source}: no exposure path within 0.01 s of frame {args.frame} ({frame.timestamp:.6f})")
    P = lambda v: Pose.from_vector(jnp.asarray(v, jnp.float32))
    traj = ExposureTrajectory(P(starts[j]), P(ends[j]))
    gamma = float(seq.meta.get("response_gamma", 1.0))
    sharp = deblur(frame.image, frame.depth, seq.camera, traj, args.n, args.iterations, args.regularization, gamma)
    out = pathlib.Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    name = f"{frame.timestamp:.6f}.png"
    cv2.imwrite(str(out / name), np.clip(sharp * 255, 0, 255).astype(np.uint8))
    res = {"frame": args.frame, "output": str(out / name)}
    ref_path = pathlib.Path(frame.path).parent.parent / "sharp" / pathlib.Path(frame.path).name
    if ref_path.is_file():
        ref = read_image_gray(ref_path)
        res.update(psnr_deblurred=psnr(sharp, ref), psnr_blurry=psnr(frame.image, ref), ssim_deblurred=ssim(sharp, ref), ssim_blurry=ssim(frame.image, ref))
        cv2.imwrite(str(out / f"triptych_{name}"), np.clip(np.concatenate([frame.image, sharp, ref], 1) * 255, 0, 255).astype(np.uint8))
    print(json.dumps(res, indent=2) if args.format == "json" else "\n".join(f"{k:>16}: {v}" for k, v in res.items()))
    return 0


def _cmd_demo(args) -> int:
    import pathlib

    from .datasets import open_sequence
    from .odometry import run_odometry
    from .synthetic import PRESETS, SynthConfig, generate_sequence

    out = pathlib.Path(args.out)
    data = out / "sequence"
    progress = None if args.quiet else sys.stderr
    if not (data / "exposure.txt").is_file():
        cfg = SynthConfig(**{**PRESETS[args.preset], "frames": args.frames, "width": args.width, "height": args.height, "seed": args.seed})
        print(f"generating a {args.preset}-blur sequence: {args.frames} frames {args.width}x{args.height} -> {data}", flush=True)
        generate_sequence(cfg, data, progress=progress)
    seq = open_sequence(data)
    args.set, args.config = args.set or [], args.config
    tracker, odo = _tracker_setup(args, seq)
    run = out / "track"
    print(f"tracking with n={tracker.n} virtual frames -> {run}", flush=True)
    summary = run_odometry(seq, run, tracker, odo, progress=progress)
    summary.update(_evaluate_run(seq, run))
    print(
        f"tracked {summary['tracked']}/{summary['frames']} frames, {summary['keyframes']} keyframes, "
        f"ATE rmse {summary.get('ate_rmse_m', float('nan')):.4f} m; plots: {run / 'trajectory.png'}, {run / 'ape_over_time.png'}"
    )
    return 0


def _print_result(res: dict, fmt: str, extra_keys, nested=()) -> None:
    if fmt == "json":
        print(json.dumps(res, indent=2))
        return
    if nested:
        for k in nested:
            st = res[k]
            print(f"{k:>16}: " + "  ".join(f"{s} {st[s]:.5g}" for s in ("rmse", "mean", "median", "std", "min", "max")))
    else:
        for s in ("rmse", "mean", "median", "std", "min", "max"):
            print(f"{s:>8}  {res[s]:.6f}")
    for k in extra_keys:
        if k in res:
            print(f"{k:>8}  {res[k]}")


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mbavo", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("jacobians", help="cross-validate the supplement's Jacobians against autodiff (float64)")
    p.add_argument("--format", choices=["table", "json"], default="table")
    p.add_argument("--seed", type=int, default=0, help="seed of the random samples (default 0)")
    p.set_defaults(func=_cmd_jacobians)

    p = sub.add_parser("synth", help="generate a blurry sequence with ground-truth exposure paths (TUM layout)")
    p.add_argument("--out", required=True, help="output folder (created; must be empty or a previous synth output)")
    p.add_argument("--preset", choices=["none", "mild", "strong", "extreme"], default="strong",
                   help="blur level: mean blur ~0 / 5 / 20 / 40 px at 640x480 (default strong)")
    p.add_argument("--from", dest="source", metavar="SEQ", help="blur a real RGB-D sequence (with depth) instead of rendering")
    p.add_argument("--blur-px", type=float, help="with --from: mean blur length in pixels (default from --preset)")
    p.add_argument("--frames", type=int, help="number of frames (default 100)")
    p.add_argument("--width", type=int, help="image width (default 640)")
    p.add_argument("--height", type=int, help="image height (default 480)")
    p.add_argument("--fps", type=float, help="frame rate (default 30)")
    p.add_argument("--exposure-ms", dest="exposure_ms", type=float, help="exposure time τ in ms (preset)")
    p.add_argument("--speed", type=float, help="peak camera speed in m/s (preset)")
    p.add_argument("--rotation-rate", dest="rotation_rate", type=float, help="peak rotation rate in deg/s (preset)")
    p.add_argument("--subframes", type=int, help="sub-frame renders per exposure (default 64)")
    p.add_argument("--noise", type=float, help="Gaussian noise std on [0, 1] intensities (default 0.002)")
    p.add_argument("--depth-model", dest="depth_model", choices=["exact", "sensor"],
                   help="depth written: exact mid-exposure z-depth (default), or as a Kinect-class sensor writes it "
                        "(correlated noise growing with z², holes at depth edges, 1%% dropouts)")
    p.add_argument("--seed", type=int, default=0, help="seed (output is deterministic for a seed)")
    p.add_argument("--no-real-textures", action="store_true", help="procedural textures only (no ../shared/data photos)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress output")
    p.set_defaults(func=_cmd_synth)

    p = sub.add_parser("bench", help="benchmarks: 'tracking' (frame pairs, vs Open3D/OpenCV) and 'odometry' (whole sequences, ATE)")
    p.add_argument("what", choices=["tracking", "odometry"])
    p.add_argument("--data", help="a generated sequence (default: generate runs/bench_<preset>_<w>x<h>)")
    p.add_argument("--frames", type=int, default=20, help="frame pairs to track (default 20)")
    p.add_argument("--preset", default="strong,none", help="comma-separated blur presets to generate and run (default strong,none)")
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--no-peers", action="store_true", help="skip Open3D and OpenCV")
    p.add_argument("--presets", default="none,mild,strong,extreme", help="odometry: blur presets (default all four)")
    p.add_argument("--sensor-presets", dest="sensor_presets", default="strong,extreme",
                   help="odometry: presets generated again with Kinect-class depth (--depth-model sensor; '' to skip)")
    p.add_argument("--tum", default="../shared/data/tum_fr1_xyz_head37", help="odometry: real RGB-D clip to blur ('' to skip)")
    p.add_argument("--out", default="runs/bench_odometry", help="odometry: output folder")
    p.add_argument("--methods", default="", help="odometry: comma-separated subset of " + ", ".join(__import__("mbavo_jax.bench", fromlist=["x"]).ODOMETRY_METHODS) + " (default all)")
    p.add_argument("--depth-weight", dest="depth_weight", type=float, default=0.03,
                   help="odometry: tracker.depth_weight of the *_depth methods (default 0.03)")
    p.add_argument("--format", choices=["table", "json"], default="table")
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=lambda a: getattr(__import__("mbavo_jax.bench", fromlist=["x"]), f"main_{a.what}")(a))

    p = sub.add_parser("track", help="motion-blur-aware RGB-D visual odometry over a sequence")
    p.add_argument("sequence", help="sequence folder (TUM RGB-D, mbavo synth output, DSO with depth/)")
    p.add_argument("--out", required=True, help="output folder (trajectory.txt, exposure.txt, keyframes.txt, plots)")
    p.add_argument("--config", help="YAML with 'tracker:' and 'odometry:' sections (see configs/)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override a config value, e.g. tracker.n=32 (repeatable)")
    p.add_argument("--resume", action="store_true", help="continue after the last frame already in OUT/trajectory.txt")
    p.add_argument("--max-frames", type=int, help="stop after this many frames")
    p.add_argument("--kind", default="auto", choices=["auto", "tum", "kitti", "euroc", "dso", "folder"])
    p.add_argument("--format", choices=["table", "json"], default="table")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_cmd_track)

    p = sub.add_parser("deblur", help="deblur one frame with its exposure path and depth; PSNR/SSIM vs sharp/ if present")
    p.add_argument("sequence")
    p.add_argument("--frame", type=int, required=True, help="frame index")
    p.add_argument("--exposure", help="exposure file (default: the sequence's exposure.txt; or a 'mbavo track' output)")
    p.add_argument("--out", required=True)
    p.add_argument("--n", type=int, default=0, help="virtual frames of the blur operator (default 0: one per pixel of blur, power of two, at most 64)")
    p.add_argument("--iterations", type=int, default=30, help="conjugate-gradient iterations (default 30)")
    p.add_argument("--regularization", type=float, default=2e-2, help="weight of the gradient penalty (default 2e-2)")
    p.add_argument("--format", choices=["table", "json"], default="table")
    p.set_defaults(func=_cmd_deblur)

    p = sub.add_parser("demo", help="generate a short blurry sequence, track it, print the ATE and write plots (no downloads)")
    p.add_argument("--out", default="runs/demo")
    p.add_argument("--preset", choices=["none", "mild", "strong", "extreme"], default="strong")
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--config", help="YAML config (see configs/)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE")
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=_cmd_demo)

    p = sub.add_parser("info", help="describe a sequence (layout, camera, depth, ground truth); --check reads every frame")
    p.add_argument("sequence")
    p.add_argument("--kind", default="auto", choices=["auto", "tum", "kitti", "euroc", "dso", "folder"])
    p.add_argument("--check", action="store_true", help="read and validate every frame")
    p.add_argument("--format", choices=["table", "json"], default="table")
    p.add_argument("-q", "--quiet", action="store_true")
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser("eval", help="evaluate an estimated trajectory (APE, RPE) or exposure paths")
    p.add_argument("metric", choices=["ape", "rpe", "exposure"])
    p.add_argument("reference", help="ground truth (TUM file; exposure.txt for 'exposure')")
    p.add_argument("estimate", help="estimate (TUM file; exposure.txt for 'exposure')")
    p.add_argument("--align", "-a", choices=["none", "se3", "sim3"], default="se3", help="Umeyama alignment (default se3)")
    p.add_argument("--t_max_diff", type=float, default=0.01, help="max timestamp difference for association in s (default 0.01)")
    p.add_argument("--delta", type=int, default=1, help="RPE frame delta (default 1)")
    p.add_argument("--sequence", help="sequence folder: also report the frame-drop rate")
    p.add_argument("--camera", help="camera.yaml (needed for 'exposure')")
    p.add_argument("--depth", type=float, default=2.0, help="'exposure': depth of the reprojection grid in m (default 2)")
    p.add_argument("--plot", metavar="DIR", help="write PNG plots to DIR")
    p.add_argument("--format", choices=["table", "json"], default="table")
    p.set_defaults(func=_cmd_eval)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        return int(args.func(args) or 0)
    except UserError as exc:
        print(f"mbavo: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print("mbavo: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
