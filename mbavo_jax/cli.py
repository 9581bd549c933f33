"""The ``mbavo`` command line: ``mbavo jacobians | synth | eval | track | deblur | demo | view | info | bench | sweep | config``.

Known errors (bad input files, bad options) print one line ``mbavo: error: ...`` and exit 1.
Building the parser and rejecting arguments import no JAX; each command imports what it needs.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import signal
import sys

from .config import (AT_LEAST_1, FINITE, NONNEG, POSITIVE, PRESETS, BenchConfig, DeblurConfig, OdometryConfig, SweepConfig, SynthConfig,
                     add_arguments, from_arguments)
from .errors import MbavoError as UserError  # every user-facing error: one line, exit status 1
from .methods import ODOMETRY_METHODS

__all__ = ["main", "build_parser"]

KINDS = ["auto", "tum", "kitti", "euroc", "dso", "folder"]
JAX_HERE = {"jacobians", "synth", "eval", "track", "deblur", "demo", "view", "info"}  # commands that run JAX in this process
JAX_IN_WORKERS = {"bench", "sweep"}  # commands whose runs may use JAX in worker processes
PRESET_BLUR_PX = {"none": 0.0, "mild": 5.0, "strong": 20.0, "extreme": 40.0}  # synth --from: mean blur per preset


class _Parser(argparse.ArgumentParser):
    """argparse with one-line argument errors and exit status 1, like every other error."""

    def error(self, message):
        self.exit(1, f"mbavo: error: {message}\n")


def positive_int(text: str) -> int:
    """argparse type: a whole number >= 1 (the settings' ``AT_LEAST_1``)."""
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a whole number {AT_LEAST_1.text}, got {text!r}") from None
    if not AT_LEAST_1.ok(value):
        raise argparse.ArgumentTypeError(f"must be {AT_LEAST_1.text}, got {value}")
    return value


def _checked_float(text: str, check) -> float:
    """argparse type: a finite number passing ``check`` (a settings ``Check``)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected a number {check.text}, got {text!r}") from None
    if not (FINITE.ok(value) and check.ok(value)):
        raise argparse.ArgumentTypeError(f"must be a {FINITE.text} number {check.text}, got {text}")
    return value


def positive_float(text: str) -> float:
    """argparse type: a finite number > 0 (the settings' ``FINITE`` and ``POSITIVE``)."""
    return _checked_float(text, POSITIVE)


def nonneg_float(text: str) -> float:
    """argparse type: a finite number >= 0 (the settings' ``FINITE`` and ``NONNEG``)."""
    return _checked_float(text, NONNEG)


# ------------------------------------------------------------------------------------- commands


def _cmd_jacobians(args) -> int:
    from .paper import cross_validate, format_table

    results = cross_validate(seed=args.seed)
    if args.format == "json":
        print(json.dumps([r.as_dict() for r in results], indent=2, ensure_ascii=False))
    else:
        print(format_table(results))
    return 0


def _cmd_synth(args) -> int:
    if args.source:
        from .datasets import open_sequence
        from .synthetic import blur_real_sequence

        seq = open_sequence(args.source)
        given = lambda value, default: default if value is None else value
        summary = blur_real_sequence(seq, args.out, blur_px=given(args.blur_px, PRESET_BLUR_PX[args.preset]),
                                     n=given(args.subframes, 64), seed=given(args.seed, 0), noise=given(args.noise, 0.0),
                                     progress=not args.quiet, exposure_info=args.exposure_info is not False,
                                     readout_ms=given(args.readout_ms, 0.0))
    else:
        cfg = from_arguments(SynthConfig, args, PRESETS[args.preset])
        from .synthetic import generate_sequence

        summary = generate_sequence(cfg, args.out, progress=not args.quiet)
    if not args.quiet:
        print(
            f"wrote {summary['frames']} frames to {args.out}: mean blur {summary['mean_blur_px']:.1f} px "
            f"(median {summary['median_blur_px']:.1f}, max {summary['max_blur_px']:.1f}) in {summary['seconds']:.1f} s"
        )
    return 0


def _eval_plots(args, res: dict, errors, t_ref, p_ref, t_est, p_est) -> None:
    from . import evaluation as ev
    from .evaluation import plots
    from .io import prepare_out_dir

    out = prepare_out_dir(args.plot, "--plot")
    if args.metric == "ape":
        i_est, _, ref_xyz, est_xyz = ev.aligned_positions(t_ref, p_ref, t_est, p_est, args.align, args.t_max_diff)
        plots.plot_trajectories(out / "trajectory.png", ref_xyz, est_xyz, f"APE rmse {res['rmse']:.4f} m ({args.align})")
        plots.plot_error_over_time(out / "ape_over_time.png", t_est[i_est], errors, "APE over time")
    else:
        i_est, _ = ev.associate(t_est, t_ref, args.t_max_diff)
        plots.plot_error_over_time(out / "rpe_over_time.png", t_est[i_est][: len(errors)], errors, "RPE over time", "RPE [m]")


def _cmd_eval(args) -> int:
    import numpy as np

    from . import evaluation as ev
    from .io import read_camera_yaml, read_exposure_file, read_tum_trajectory

    if args.metric == "exposure":
        if args.camera is None:
            raise UserError("eval exposure needs --camera CAMERA.yaml (the intrinsics of the reprojection error)")
        ref = read_exposure_file(args.reference)
        est = read_exposure_file(args.estimate)
        cam = read_camera_yaml(args.camera)
        res = ev.exposure_path_error(ref, est, cam, depth=args.depth, max_diff=args.t_max_diff)
        res.update(_row_errors(args, est, cam))
        _print_result(res, args.format, ["n_matched", "rows", "readout_fraction", "per_row_px"],
                      nested=("translation_m", "rotation_deg", "reprojection_px", "length_ratio", "row_reprojection_px"))
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
        _eval_plots(args, res, errors, t_ref, p_ref, t_est, p_est)
    _print_result(res, args.format, ["n_matched", "alignment", "scale", "delta", "frame_drop_rate"])
    return 0


def _row_errors(args, est, cam: dict) -> dict:
    """'eval exposure': the per-row endpoint error against --rows (default: exposure_rows.txt next to
    the reference, when there is one), rows of the estimate taken with its model's readout fraction
    (--readout-ms, exposure --exposure-ms or camera.yaml's); {} without per-row ground truth."""
    import pathlib

    from . import evaluation as ev
    from .geometry.trajectory import readout_fraction
    from .io import read_exposure_rows

    rows = pathlib.Path(args.rows) if args.rows else pathlib.Path(args.reference).parent / "exposure_rows.txt"
    if not args.rows and not rows.is_file():
        return {}
    exposure_ms = args.exposure_ms if args.exposure_ms is not None else cam.get("exposure_ms")
    if args.readout_ms > 0 and exposure_ms is None:
        raise UserError("--readout-ms needs the exposure time: --exposure-ms, or exposure_ms in the --camera file")
    rho = readout_fraction(args.readout_ms / 1000.0, (exposure_ms or 0.0) / 1000.0)
    res = ev.row_path_error(read_exposure_rows(rows), est, cam, rho, depth=args.depth, max_diff=args.t_max_diff)
    return {"rows": res["rows"], "readout_fraction": round(rho, 6), "row_reprojection_px": res["reprojection_px"],
            "per_row_px": [round(x, 4) for x in res["per_row_px"]]}


def _cmd_info(args) -> int:
    from .datasets import open_sequence
    from .progress import bar

    seq = open_sequence(args.sequence, args.kind)
    cam = seq.camera
    info = {
        "name": seq.name,
        "kind": seq.kind,
        "frames": len(seq),
        "duration_s": float(seq.timestamps[-1] - seq.timestamps[0]) if len(seq) > 1 else 0.0,
        "camera": cam.as_dict(),
        "camera_model": seq.camera_model,
        "depth": seq.has_depth,
        "exposure_times": seq.exposures is not None,
        "readout_ms": 1000 * seq.readout_s,
        "groundtruth_poses": 0 if seq.groundtruth is None else int(len(seq.groundtruth[0])),
        "exposure_paths": 0 if seq.exposure_paths is None else int(len(seq.exposure_paths[0])),
    }
    if args.check:
        with bar(len(seq), "check", not args.quiet) as pbar:
            for i in range(len(seq)):
                seq[i]  # raises DataError naming the file on a bad frame
                pbar.update()
        info["checked"] = True
    if args.format == "json":
        print(json.dumps(info, indent=2))
    else:
        for k, v in info.items():
            print(f"{k:>18}: {v}")
    return 0


def _run_config(args, seq):
    """The settings of a run: defaults, ``--config``, the sequence's camera.yaml calibration, ``--set``."""
    from .config import calibration_of, load_config

    return load_config(args.config, args.set, calibration_of(seq.meta))


def _viewer(args, seq, config):
    """The run's rerun recording (``--viewer``: a window, ``--rrd FILE``: a file), or a stand-in
    that records nothing when neither is given."""
    import contextlib

    if not (args.viewer or args.rrd is not None):
        return contextlib.nullcontext(None)
    from .viewer import RunViewer

    return RunViewer(seq.camera, config.tracker.response_gamma, seq.groundtruth, rrd=args.rrd, spawn=args.viewer)


def _check_viewer(args) -> None:
    """With ``--viewer`` or ``--rrd``: rerun-sdk must be installed, a window needs a display and the
    recording file a place it can be written to (one-line errors before anything runs)."""
    if args.viewer or args.rrd is not None:
        from .viewer import check_display, check_rrd, require_rerun

        require_rerun()
        if args.viewer:
            check_display()
        if args.rrd is not None:
            check_rrd(args.rrd)


def _cmd_track(args) -> int:
    import pathlib

    from .datasets import open_sequence
    from .evaluation import evaluate_run

    _check_viewer(args)
    seq = open_sequence(args.sequence, args.kind)
    if args.mode:
        args.set = [*(args.set or []), f"odometry.mode={args.mode}"]
    config = _run_config(args, seq)
    from .odometry import run_odometry

    out = pathlib.Path(args.out)
    with _viewer(args, seq, config) as viewer:
        summary = run_odometry(seq, out, config, resume=args.resume or args.resume_anyway, max_frames=args.max_frames,
                               progress=not args.quiet, resume_anyway=args.resume_anyway, observer=viewer)
    _check_posed(out, summary, len(seq), args.max_frames)
    summary.update(evaluate_run(out, seq.groundtruth, seq.timestamps, config.evaluation, plots=True, monocular=summary.get("mode") == "mono"))
    summary["out"] = str(out)
    if args.format == "json":
        print(json.dumps(summary, indent=2))
    else:
        for k, v in summary.items():
            print(f"{k:>16}: {v:.4f}" if isinstance(v, float) else f"{k:>16}: {v}")
    return 0


def _check_posed(out, summary: dict, frames: int, max_frames: int | None) -> None:
    """A monocular run that went to the sequence's end without posing a frame is an error: one line
    with the initialiser's last note (frames.csv); the run folder keeps its files. A run stopped
    earlier by --max-frames is not (--resume continues it)."""
    import pathlib

    if summary.get("mode") != "mono" or (max_frames is not None and max_frames < frames):
        return
    trajectory = pathlib.Path(out) / "trajectory.txt"
    lines = trajectory.read_text(errors="replace").splitlines() if trajectory.is_file() else []
    if any(line.strip() and not line.startswith("#") for line in lines):
        return
    from .odometry.folder import committed_rows

    noted = [r for r in committed_rows(pathlib.Path(out)) if r.get("note")]
    last = f" (last note, frame {noted[-1]['index']}: {' '.join(noted[-1]['note'].split())})" if noted else ""
    raise UserError(f"{out}: no frame posed: the monocular system did not initialise in the sequence's {frames} frames{last}; "
                    "the run's files are kept")


def _cmd_deblur(args) -> int:
    import pathlib

    cfg = from_arguments(DeblurConfig, args)
    import cv2
    import jax.numpy as jnp
    import numpy as np

    from .config import EvalConfig
    from .datasets import open_sequence
    from .deblur import deblur, psnr, ssim
    from .evaluation import associate
    from .geometry import ExposureTrajectory, Pose
    from .io import format_stamp, prepare_out_dir, read_image_gray

    seq = open_sequence(args.sequence)
    if not 0 <= args.frame < len(seq):
        raise UserError(f"--frame {args.frame} out of range (the sequence has {len(seq)} frames, 0 to {len(seq) - 1})")
    frame = seq[args.frame]
    if frame.depth is None:
        raise UserError(f"{seq.path}: deblurring needs depth")
    source, (stamps, starts, ends) = _exposure_paths(args, seq)
    tol = EvalConfig().t_max_diff
    _, match = associate(np.array([frame.timestamp]), stamps, tol)
    if len(match) == 0:
        raise UserError(f"{source}: no exposure path within {tol} s (evaluation.t_max_diff) of frame {args.frame} ({format_stamp(frame.timestamp)})")
    out = prepare_out_dir(args.out)
    j = int(match[0])
    P = lambda v: Pose.from_vector(jnp.asarray(v, jnp.float32))
    traj = ExposureTrajectory(P(starts[j]), P(ends[j]))
    sharp = np.asarray(deblur(frame.image, frame.depth, seq.camera, traj, cfg, float(seq.meta.get("response_gamma", 1.0))))
    if not np.isfinite(sharp).all():
        raise UserError(f"{frame.path}: deblurring gave non-finite values; nothing written "
                        f"(check the depth and the exposure paths of {source})")
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


def _exposure_paths(args, seq):
    """deblur's exposure paths (stamps, start (N, 7), end (N, 7)) and where they come from: the file
    --exposure, else the sequence (its groundtruth_exposure.txt or exposure.txt, read by its loader)."""
    from .io import read_exposure_file

    if args.exposure:
        return args.exposure, read_exposure_file(args.exposure)
    if seq.exposure_paths is None:
        raise UserError(f"{seq.path}: no groundtruth_exposure.txt or exposure.txt (give --exposure FILE, e.g. a 'mbavo track' exposure.txt)")
    return seq.path, seq.exposure_paths


def _cmd_demo(args) -> int:
    from .io import prepare_out_dir

    _check_viewer(args)
    out = prepare_out_dir(args.out)
    from .datasets import open_sequence
    from .evaluation import evaluate_run
    from .odometry import run_odometry
    from .synthetic import generate_sequence

    data = out / "sequence"
    if not (data / "exposure.txt").is_file():
        cfg = SynthConfig(**{**PRESETS[args.preset], "frames": args.frames, "width": args.width, "height": args.height, "seed": args.seed,
                             "real_textures": False})  # the same sequence on every machine, shared data or not
        print(f"generating a {args.preset}-blur sequence: {args.frames} frames {args.width}x{args.height} -> {data}", flush=True)
        generate_sequence(cfg, data, progress=not args.quiet)
    seq = open_sequence(data)
    config = _run_config(args, seq)
    run = out / "track"
    print(f"tracking with n={config.tracker.n} virtual frames -> {run}", flush=True)
    with _viewer(args, seq, config) as viewer:
        summary = run_odometry(seq, run, config, progress=not args.quiet, observer=viewer)
    summary.update(evaluate_run(run, seq.groundtruth, seq.timestamps, config.evaluation, plots=True, monocular=summary.get("mode") == "mono"))
    print(
        f"tracked {summary['tracked']}/{summary['frames']} frames, {summary['keyframes']} keyframes, "
        f"ATE rmse {summary.get('ate_rmse_m', float('nan')):.4f} m ({summary.get('ate_alignment', config.evaluation.align)}); "
        f"plots: {run / 'trajectory.png'}, {run / 'ape_over_time.png'}"
    )
    return 0


def _cmd_view(args) -> int:
    from .viewer import check_rrd, require_rerun

    require_rerun()
    if args.rrd is not None:
        check_rrd(args.rrd)
    from .viewer import view_run

    res = view_run(args.run, rrd=args.rrd, sequence=args.sequence, progress=not args.quiet)
    if args.rrd:
        print(f"wrote {res['frames']} frames to {args.rrd} (open it with: rerun {args.rrd})")
    return 0


def _cmd_bench(args) -> int:
    from .methods import parse_methods

    if args.what == "rolling-shutter":
        from .bench.rolling import ROLLING_DEFAULTS, main_rolling

        return main_rolling(from_arguments(BenchConfig, args, ROLLING_DEFAULTS), args.format, args.quiet)
    cfg = from_arguments(BenchConfig, args)
    settings = from_arguments(SweepConfig, args)
    if args.what == "odometry":
        parse_methods(cfg.methods, cfg.no_peers)  # reject unknown methods before loading JAX
    from . import bench

    if args.what == "tracking":
        return bench.main_tracking(cfg, args.data, args.format, args.quiet)
    if args.what == "mono":
        from .bench.mono import main_mono

        return main_mono(cfg, args.format, args.quiet)
    if args.what == "speed":
        from .bench.speed import main_speed

        return main_speed(cfg, args.format, args.quiet)
    return bench.main_odometry(cfg, args.format, args.quiet, settings)


def _cmd_sweep(args) -> int:
    from .sweep import main

    return main(args.spec, args.out, from_arguments(SweepConfig, args), args.format, args.quiet)


def _cmd_config(args) -> int:
    from .config import default_yaml, settings_markdown

    print(settings_markdown() if args.markdown else default_yaml(), end="")
    return 0


def _print_result(res: dict, fmt: str, extra_keys, nested=()) -> None:
    if fmt == "json":
        print(json.dumps(res, indent=2))
        return
    if nested:
        for k in (k for k in nested if res.get(k)):
            st = res[k]
            print(f"{k:>16}: " + "  ".join(f"{s} {st[s]:.5g}" for s in ("rmse", "mean", "median", "std", "min", "max")))
    else:
        for s in ("rmse", "mean", "median", "std", "min", "max"):
            print(f"{s:>8}  {res[s]:.6f}")
    for k in extra_keys:
        if k in res:
            print(f"{k:>8}  {res[k]}")


# --------------------------------------------------------------------------------------- parser


def _format_flag(p) -> None:
    p.add_argument("--format", choices=["table", "json"], default="table")


def _quiet_flag(p, help: str = "no progress output") -> None:
    p.add_argument("-q", "--quiet", action="store_true", help=help)


def _config_flags(p) -> None:
    p.add_argument("--config", help="YAML with tracker:, odometry:, deblur:, evaluation: sections (configs/default.yaml; `mbavo config` prints it)")
    p.add_argument("--set", action="append", metavar="SECTION.KEY=VALUE", help="override a setting, e.g. tracker.n=32 (repeatable)")


def _add_jacobians(sub) -> None:
    p = sub.add_parser("jacobians", help="cross-validate the supplement's Jacobians against autodiff (float64)")
    _format_flag(p)
    p.add_argument("--seed", type=int, default=0, help="seed of the random samples (default 0)")
    p.set_defaults(func=_cmd_jacobians)


def _add_synth(sub) -> None:
    p = sub.add_parser("synth", help="generate a blurry sequence with ground-truth exposure paths (TUM layout)",
                       description="Settings not given come from --preset (exposure, speed, rotation rate, sub-frames), "
                                   "then from the defaults shown.")
    p.add_argument("--out", required=True, help="output folder (created; must be empty or a previous synth output)")
    p.add_argument("--preset", choices=list(PRESETS), default="strong",
                   help="blur level: mean blur ~0 / 5 / 20 / 40 px at 640x480 (default strong)")
    p.add_argument("--from", dest="source", metavar="SEQ", help="blur a real RGB-D sequence (with depth) instead of rendering")
    p.add_argument("--blur-px", type=nonneg_float, help="mean blur length in pixels: of the generated images (exposure_ms is "
                   "scaled to reach it, the motion kept; 0: exposure_ms as given), or with --from of the blurred clip (default from --preset)")
    add_arguments(p, SynthConfig, skip=("blur_px",))
    _quiet_flag(p)
    p.set_defaults(func=_cmd_synth)


def _add_bench(sub) -> None:
    p = sub.add_parser("bench", help="benchmarks: 'tracking' (frame pairs, vs Open3D/OpenCV), 'odometry' (whole RGB-D sequences, ATE) and "
                       "'mono' (the monocular system vs n = 1 and RGB-D)",
                       description="odometry methods: " + ", ".join(ODOMETRY_METHODS))
    p.add_argument("what", choices=["tracking", "odometry", "mono", "rolling-shutter", "speed"],
                   help="rolling-shutter: methods rs, blur, n1, rs_cubic on sequences at --presets (default strong,extreme) x "
                        "--readouts, plus a curved-path set (--shake-deg); --out default runs/bench_rolling. speed: per --preset, the whole loop "
                        "profiled (tracking, deblurring, keyframes, I/O, compilation) vs Open3D hybrid, and start-up with and without the "
                        "compilation cache")
    p.add_argument("--data", help="tracking: a generated sequence (default: generate runs/bench_<preset>_<w>x<h>_seed<s>)")
    add_arguments(p, BenchConfig, skip=("no_peers",))
    p.add_argument("--no-peers", dest="no_peers", action="store_true", default=None, help="skip Open3D and OpenCV")
    add_arguments(p.add_argument_group("odometry: how the runs execute (a sweep; finished runs in --out are kept)"), SweepConfig)
    _format_flag(p)
    _quiet_flag(p)
    p.set_defaults(func=_cmd_bench)


def _add_sweep(sub) -> None:
    p = sub.add_parser("sweep", help="many runs at once: sequences x configurations (and peers) from a YAML, on a process pool or Ray; "
                       "one results table (CSV, markdown, ATE plot)",
                       description="SWEEP.yaml: sequences: (path: DIR | preset: strong with seed: [1, 2], frames:, width:, ... | "
                                   "from: RGBD_DIR, blur_px:), configurations: (name: {section.key: value or [values]}), peers: "
                                   "(open3d, open3d_color, opencv), base:, config:, peer_depth_max: (configs/sweeps/*.yaml). "
                                   "Runs finished by an earlier call with --out DIR are kept. On a Ray cluster (--address) every node "
                                   "needs mbavo_jax installed and must see DIR and the sequences at the same paths.")
    p.add_argument("spec", metavar="SWEEP.yaml", help="the sweep file")
    p.add_argument("--out", required=True, help="output folder: data/, runs/<sequence>/<method>/, results.csv, results.md, ate.png")
    add_arguments(p, SweepConfig)
    _format_flag(p)
    _quiet_flag(p)
    p.set_defaults(func=_cmd_sweep)


def _viewer_flags(p) -> None:
    p.add_argument("--viewer", action="store_true", help="open the rerun viewer and stream the run to it (needs the viewer extra)")
    p.add_argument("--rrd", metavar="FILE", help="save the rerun recording of the run to FILE (open later: rerun FILE)")


def _add_track(sub) -> None:
    p = sub.add_parser("track", help="motion-blur-aware visual odometry over a sequence (RGB-D with depth, else monocular)")
    p.add_argument("sequence", help="sequence folder (TUM RGB-D, mbavo synth output, KITTI, EuRoC, DSO, images + camera.yaml)")
    p.add_argument("--out", required=True, help="output folder (trajectory.txt, exposure.txt, keyframes.txt, plots)")
    _config_flags(p)
    p.add_argument("--resume", action="store_true",
                   help="continue after the last frame committed in OUT (same sequence and settings, else an error)")
    p.add_argument("--resume-anyway", action="store_true",
                   help="--resume even with another sequence or other settings (recorded in OUT/run.yaml)")
    p.add_argument("--max-frames", type=positive_int, help="stop after this many frames")
    mode = {f.name: f for f in dataclasses.fields(OdometryConfig)}["mode"]
    p.add_argument("--mode", choices=mode.metadata["choices"], help=f"odometry.mode: {mode.metadata['help']}")
    p.add_argument("--kind", default="auto", choices=KINDS)
    _viewer_flags(p)
    _format_flag(p)
    _quiet_flag(p, "no progress bar")
    p.set_defaults(func=_cmd_track)


def _add_deblur(sub) -> None:
    p = sub.add_parser("deblur", help="deblur one frame with its exposure path and depth; PSNR/SSIM vs sharp/ if present")
    p.add_argument("sequence")
    p.add_argument("--frame", type=int, required=True, help="frame index")
    p.add_argument("--exposure", help="exposure file (default: the sequence's groundtruth_exposure.txt or exposure.txt; or a 'mbavo track' output)")
    p.add_argument("--out", required=True)
    add_arguments(p, DeblurConfig)
    _format_flag(p)
    p.set_defaults(func=_cmd_deblur)


def _add_demo(sub) -> None:
    p = sub.add_parser("demo", help="generate a short blurry sequence, track it, print the ATE and write plots (no downloads)")
    p.add_argument("--out", default="runs/demo")
    p.add_argument("--preset", choices=list(PRESETS), default="strong")
    p.add_argument("--frames", type=int, default=40)
    p.add_argument("--width", type=int, default=320)
    p.add_argument("--height", type=int, default=240)
    p.add_argument("--seed", type=int, default=0)
    _config_flags(p)
    _viewer_flags(p)
    _quiet_flag(p)
    p.set_defaults(func=_cmd_demo)


def _add_view(sub) -> None:
    p = sub.add_parser("view", help="show a finished run folder in the rerun viewer (needs the viewer extra)",
                       description="Rebuilds the recording from the run folder (trajectory, exposure paths, keyframes, frames.csv, "
                                   "points.ply) and the run's sequence (input images, depth, ground truth).")
    p.add_argument("run", help="run folder (mbavo track ... --out RUN)")
    p.add_argument("--sequence", help="the run's sequence folder (default: the one RUN/run.yaml records)")
    p.add_argument("--rrd", metavar="FILE", help="write the recording to FILE instead of opening the viewer")
    _quiet_flag(p)
    p.set_defaults(func=_cmd_view)


def _add_info(sub) -> None:
    p = sub.add_parser("info", help="describe a sequence (layout, camera, depth, ground truth); --check reads every frame")
    p.add_argument("sequence")
    p.add_argument("--kind", default="auto", choices=KINDS)
    p.add_argument("--check", action="store_true", help="read and validate every frame")
    _format_flag(p)
    _quiet_flag(p)
    p.set_defaults(func=_cmd_info)


def _add_eval(sub) -> None:
    p = sub.add_parser("eval", help="evaluate an estimated trajectory (APE, RPE) or exposure paths, as evo does")
    p.add_argument("metric", choices=["ape", "rpe", "exposure"])
    p.add_argument("reference", help="ground truth (TUM file; exposure.txt for 'exposure')")
    p.add_argument("estimate", help="estimate (TUM file; exposure.txt for 'exposure')")
    p.add_argument("--align", "-a", choices=["none", "se3", "sim3"], default="se3", help="Umeyama alignment (default se3)")
    p.add_argument("--t_max_diff", type=positive_float, default=0.01,
                   help="max timestamp difference for association in s (default 0.01, evo's; mbavo track uses evaluation.t_max_diff)")
    p.add_argument("--delta", type=positive_int, default=1, help="RPE frame delta (default 1)")
    p.add_argument("--sequence", help="sequence folder: also report the frame-drop rate")
    p.add_argument("--camera", help="camera.yaml (needed for 'exposure')")
    p.add_argument("--depth", type=positive_float, default=2.0, help="'exposure': depth of the reprojection grid in m (default 2)")
    p.add_argument("--rows", metavar="FILE", help="'exposure': per-row ground truth of a rolling shutter (default: exposure_rows.txt "
                   "next to the reference, when there is one): also the per-row endpoint error")
    p.add_argument("--readout-ms", type=nonneg_float, default=0.0,
                   help="'exposure' with rows: the readout time the estimate's model assumed (default 0: a global-shutter estimate)")
    p.add_argument("--exposure-ms", type=positive_float, help="'exposure' with rows: the exposure time (default: camera.yaml's exposure_ms)")
    p.add_argument("--plot", metavar="DIR", help="write PNG plots to DIR")
    _format_flag(p)
    p.set_defaults(func=_cmd_eval)


def _add_config(sub) -> None:
    p = sub.add_parser("config", help="print every setting with its default and help (configs/default.yaml)")
    p.add_argument("--markdown", action="store_true", help="the settings reference tables of docs/settings.md instead")
    p.set_defaults(func=_cmd_config)


SUBCOMMANDS = (_add_jacobians, _add_synth, _add_bench, _add_sweep, _add_track, _add_deblur, _add_demo, _add_view, _add_info, _add_eval, _add_config)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="mbavo", description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    for add in SUBCOMMANDS:
        add(sub)
    return parser


def _check_jax_environment(command: str) -> None:
    """JAX_PLATFORMS and XLA_FLAGS checked before a command that uses JAX starts its backend (one
    line naming the variable; ``jaxenv``)."""
    if command in JAX_HERE or command in JAX_IN_WORKERS:
        from .jaxenv import check_jax_environment

        check_jax_environment(in_process=command in JAX_HERE)


def _interrupt(signum, frame):
    raise KeyboardInterrupt


def _interrupted_line(args) -> str:
    """What an interrupted command says: a sweep names its file (its workers are ended, its finished
    runs kept); a run keeps every finished frame."""
    if args.command == "sweep":
        return (f"mbavo: interrupted: sweep {args.spec} stopped and its workers ended (finished runs in {args.out} are kept; "
                "the same command continues)")
    return "mbavo: interrupted (every finished frame is kept; 'mbavo track ... --resume' continues)"


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)  # argument errors: one line, exit 1
    previous = signal.signal(signal.SIGTERM, _interrupt)  # SIGTERM stops like Ctrl-C: finished frames are kept
    try:
        _check_jax_environment(args.command)
        return int(args.func(args) or 0)
    except UserError as exc:
        print(f"mbavo: error: {exc}", file=sys.stderr)
        return 1
    except KeyboardInterrupt:
        print(_interrupted_line(args), file=sys.stderr)
        return 130
    finally:
        signal.signal(signal.SIGTERM, previous)


if __name__ == "__main__":
    sys.exit(main())
