"""``mbavo bench odometry``: the odometry benchmark on whole sequences, ours against Open3D and
OpenCV RGB-D odometry: a sweep (``mbavo_jax.sweep``) of the sequences x the methods of
``ODOMETRY_METHODS`` (ours: overrides in ``OURS_ODOMETRY``; each run by ``methods.run_ours`` or
``methods.run_peer``), its rows gathered per sequence.
"""

from __future__ import annotations

import json
import pathlib
import sys

from ..config import BenchConfig, SweepConfig
from ..methods import ODOMETRY_METHODS, check_methods, parse_methods
from ..sweep import SequenceSpec, SweepSpec, as_overrides, run_sweep, summary_line
from .goals import format_goals_table, with_goals
from .sequences import generated_sequences, make_generated, tum_blurred, with_hidden_exposure

__all__ = ["OURS_ODOMETRY", "odometry_sweep", "nested_results", "run_odometry_benchmark", "format_odometry_table", "main_odometry"]

# our methods of the odometry benchmark: overrides of the defaults (``{depth_weight}``: BenchConfig.depth_weight)
OURS_ODOMETRY = {
    "ours_n64": (),
    "ours_n1": ("tracker.blur_aware=false",),
    "ours_adaptive": ("tracker.n_mode=adaptive",),
    "ours_n64_depth": ("tracker.depth_weight={depth_weight}",),
    "ours_n1_depth": ("tracker.blur_aware=false", "tracker.depth_weight={depth_weight}"),
}


def odometry_sweep(sequences: dict, tracker_overrides: dict | None = None, depth_weight: float = 0.03,
                   methods=ODOMETRY_METHODS, peer_depth_max: float = BenchConfig().peer_depth_max):
    """The odometry benchmark as a sweep: ``sequences`` (name -> folder) x ``methods``; our methods
    with ``tracker_overrides`` (TrackerConfig fields, e.g. for small images) under their own."""
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
    """Tables with one row per method and one column per sequence: ATE (mm), frame-drop rate,
    seconds per frame, exposure; the deblurred keyframes' PSNR/SSIM; then the goals, one row per
    sequence (``goals.format_goals_table``)."""
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
    return "\n".join([*lines, "", format_goals_table(res)])


def main_odometry(cfg: BenchConfig, fmt: str = "table", quiet: bool = False, settings: SweepConfig = SweepConfig()) -> int:
    """``mbavo bench odometry``: generated sequences at each blur preset (and size and seed,
    ``sequences.generated_sequences``) plus the TUM clip at each blur of ``cfg.tum_blur_px``, run as
    a sweep (``settings``: jobs, engine; finished runs in ``cfg.out`` are kept); the results, each
    sequence with its ``goals`` row, are printed and written to ``results.json``."""
    methods = parse_methods(cfg.methods, cfg.no_peers)
    seqs = {name: make_generated(g, cfg, quiet) for name, g in generated_sequences(cfg).items()}
    if cfg.tum:
        seqs.update({f"tum_blurred{px:g}": tum_blurred(cfg, quiet, px) for px in cfg.tum_blur_list()})
    seqs = with_hidden_exposure(seqs, cfg.hide_exposure)
    root = pathlib.Path(cfg.out)
    res = with_goals(run_odometry_benchmark(seqs, root, progress=not quiet, depth_weight=cfg.depth_weight, methods=methods,
                                            peer_depth_max=cfg.peer_depth_max, settings=settings))
    print(json.dumps(res, indent=2) if fmt == "json" else format_odometry_table(res))
    (root / "results.json").write_text(json.dumps(res, indent=2))
    return 0
