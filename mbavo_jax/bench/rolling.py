"""``mbavo bench rolling-shutter``: the rolling-shutter model and the cubic exposure path against the
global-shutter blur model and n = 1, on generated sequences with readout times and curved paths.

Sequences: every blur preset at every readout (``mbavo synth --readout-ms``), and, with
``shake_deg`` > 0, the same again with a handheld shake (``--shake-deg``: exposures span curved
paths). They are generated once into OUT/data and reused while their settings match. Methods, all
through the RGB-D loop (``odometry.run_odometry``) with the generated depth and the images-only
default (``tracker.depth_weight`` 0, as ``mbavo bench odometry``'s ours_n64):

* ``rs``: blur + rolling-shutter model (defaults; the readout from camera.yaml),
* ``blur``: the global-shutter blur model (``tracker.readout_s=0``),
* ``n1``: classic direct alignment (``tracker.blur_aware=false``, readout 0),
* ``rs_cubic``: ``rs`` with the cubic-spline exposure path (``tracker.trajectory=cubic``),
* ``rs_cubic_prior``: ``rs_cubic`` with a curvature prior on its control poses (σ = 0.01 rad).

Scores: ATE of the mid-exposure poses (SE3-aligned RMSE), the per-row endpoint reprojection error of
the estimated exposure paths (``evaluation.row_path_error``: each row's part of the estimated path,
with the readout fraction the method's model assumed, against exposure_rows.txt), seconds per
frame (whole loop, compilation included: the first method run on a sequence compiles the most) and
the median tracking call (frames.csv ``ms``, the first tracked frame left out).
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import sys
import time

import numpy as np

from ..config import PRESETS, BenchConfig, RunConfig, SynthConfig, as_dict, calibration_of, load_config
from ..errors import ConfigError, MbavoError

__all__ = ["ROLLING_METHODS", "ROLLING_DEFAULTS", "RollingSequence", "parse_rolling_methods", "rolling_sequences", "method_config",
           "run_rolling_benchmark", "format_rolling_table", "main_rolling"]

# each method's --set overrides on top of the defaults and the sequence's camera.yaml calibration
ROLLING_METHODS: dict[str, tuple[str, ...]] = {
    "rs": (),
    "blur": ("tracker.readout_s=0",),
    "n1": ("tracker.blur_aware=false", "tracker.readout_s=0"),
    "rs_cubic": ("tracker.trajectory=cubic",),
    "rs_cubic_prior": ("tracker.trajectory=cubic", "tracker.curvature_prior_rad=0.01"),
}
ROLLING_DEFAULTS = {"presets": "strong,extreme", "out": "runs/bench_rolling"}  # BenchConfig values this benchmark changes


def _split(text: str) -> list[str]:
    return [x.strip() for x in text.split(",") if x.strip()]


def parse_rolling_methods(text: str) -> list[str]:
    """The methods of a comma-separated list ('' = all of ``ROLLING_METHODS``); MbavoError on an unknown one."""
    methods = _split(text) or list(ROLLING_METHODS)
    unknown = [m for m in methods if m not in ROLLING_METHODS]
    if unknown:
        raise MbavoError(f"unknown rolling-shutter method(s) {', '.join(unknown)}; choose from {', '.join(ROLLING_METHODS)}")
    return methods


@dataclasses.dataclass(frozen=True)
class RollingSequence:
    """One generated sequence of the benchmark: its table name, blur preset and generator settings."""

    name: str
    preset: str
    synth: SynthConfig


def _readouts(text: str) -> list[float]:
    try:
        values = [float(x) for x in _split(text)]
    except ValueError:
        raise ConfigError(f"readouts: expected comma-separated numbers (ms), got {text!r}") from None
    if not values or any(not np.isfinite(v) or v < 0 for v in values):
        raise ConfigError(f"readouts: expected readout times >= 0 (ms), got {text!r}")
    return values


def rolling_sequences(cfg: BenchConfig) -> list[RollingSequence]:
    """The sequences of ``cfg``: each preset at each readout, then (``shake_deg`` > 0) all again shaken."""
    unknown = [p for p in _split(cfg.presets) if p not in PRESETS]
    if unknown or not _split(cfg.presets):
        raise ConfigError(f"presets: unknown blur preset(s) {', '.join(unknown) or '(none)'} (choose from {', '.join(PRESETS)})")
    out = []
    for shake in (0.0, cfg.shake_deg) if cfg.shake_deg > 0 else (0.0,):
        for preset in _split(cfg.presets):
            for readout in _readouts(cfg.readouts):
                synth = SynthConfig(**{**PRESETS[preset], "frames": cfg.frames, "width": cfg.width, "height": cfg.height,
                                       "seed": cfg.seed, "readout_ms": readout, "shake_deg": shake})
                out.append(RollingSequence(f"{preset}_ro{readout:g}" + ("_shake" if shake else ""), preset, synth))
    return out


def _generated(seq: RollingSequence, root: pathlib.Path, quiet: bool) -> pathlib.Path:
    """The folder of ``seq`` under ``root``: generated unless a previous call left one with the same settings."""
    import yaml

    from ..synthetic import generate_sequence

    path = root / seq.name
    synth_yaml = path / "synth.yaml"
    if not (synth_yaml.is_file() and (yaml.safe_load(synth_yaml.read_text()) or {}).get("config") == dataclasses.asdict(seq.synth)):
        if not quiet:
            print(f"generating {seq.name} -> {path}", file=sys.stderr)
        generate_sequence(seq.synth, path, progress=not quiet)
    return path


def method_config(method: str, meta: dict) -> RunConfig:
    """The settings of ``method`` on a sequence whose camera.yaml values are ``meta``: defaults, the
    sequence's calibration (readout included), images only (depth_weight 0), the method's overrides."""
    return load_config(None, ["tracker.depth_weight=0", *ROLLING_METHODS[method]], calibration_of(meta))


def _track_ms(run: pathlib.Path) -> float:
    """Median tracking call (frames.csv ``ms``) of a run's tracked frames, the first (compilation)
    left out when there are others; NaN when none."""
    from ..odometry.folder import committed_rows

    ms = [float(r["ms"]) for r in committed_rows(run) if r["status"] != "keyframe" and r.get("ms")]
    return float(np.median(ms[1:] if len(ms) > 1 else ms)) if ms else float("nan")


def _row_error(seq, run: pathlib.Path, config: RunConfig) -> dict:
    """Per-row endpoint error of the exposure paths of the run's tracked frames (global-shutter
    ground truth: every row the frame's path); {} when the run wrote none."""
    from ..evaluation import global_shutter_rows, row_path_error
    from ..geometry.trajectory import readout_fraction
    from ..io import read_exposure_file, read_exposure_spline_file

    if not (run / "exposure.txt").is_file() or seq.exposure_paths is None or seq.exposures is None:
        return {}
    try:
        spline = run / "exposure_spline.txt"  # a cubic run's paths: its control poses
        est = read_exposure_spline_file(spline) if spline.is_file() else read_exposure_file(run / "exposure.txt")
    except MbavoError:  # a run that wrote no path
        return {}
    est = _tracked_only(est, run)
    if len(est[0]) == 0:
        return {}
    truth = seq.exposure_rows or global_shutter_rows(seq.exposure_paths, seq.camera.height)
    rho = readout_fraction(config.tracker.readout_s, float(seq.exposures[0]))
    res = row_path_error(truth, est, seq.camera.as_dict(), readout=rho, max_diff=config.evaluation.t_max_diff)
    return {"row_endpoint_px": res["reprojection_px"]["mean"], "row_endpoint_px_median": res["reprojection_px"]["median"],
            "per_row_px": res["per_row_px"], "model_readout_fraction": rho}


def _tracked_only(est: tuple, run: pathlib.Path) -> tuple:
    """The exposure paths of ``est`` (stamps first) whose frames the tracker estimated (frames.csv
    status converged or max_steps): a keyframe started without tracking (the first frame, a reset)
    has a placeholder path (start = end) that no method estimated."""
    from ..evaluation import associate
    from ..odometry.folder import committed_rows

    tracked = [float(r["timestamp"]) for r in committed_rows(run) if r["status"] in ("converged", "max_steps")]
    keep, _ = associate(est[0], np.sort(tracked), max_diff=1e-6)
    return tuple(np.asarray(a)[keep] for a in est)


def _run_method(seq, run: pathlib.Path, method: str, progress: bool) -> dict:
    """One method over one sequence: its scores, or ``error`` when its settings do not exist."""
    from ..evaluation import evaluate_run
    from ..odometry import run_odometry

    try:
        config = method_config(method, seq.meta)
    except ConfigError as exc:
        return {"error": str(exc)}
    t0 = time.perf_counter()
    summ = run_odometry(seq, run, config, progress=progress)
    seconds = time.perf_counter() - t0
    ate = evaluate_run(run, seq.groundtruth, seq.timestamps, config.evaluation)
    return {"ate_rmse_m": ate.get("ate_rmse_m", float("nan")), "frame_drop_rate": summ["frame_drop_rate"],
            "keyframes": summ["keyframes"], "seconds_per_frame": seconds / max(summ["frames"], 1), "median_track_ms": _track_ms(run),
            **_row_error(seq, run, config)}


def call_cost(seq, pairs: int = 6) -> dict:
    """One tracking call of ``rs`` and of ``blur`` on the same frame pairs (sharp keyframe, next
    frame, constant-velocity guess: :func:`~mbavo_jax.bench.sequences.tracking_pairs`), side by side in this process: the
    median ms per call and per LM step of each (the first pair, which compiles, left out) and the
    ratios rs / blur."""
    from ..geometry.trajectory import readout_fraction
    from ..tracking import Keyframe, track
    from .sequences import tracking_pairs

    tau = float(seq.exposures[0])
    configs = {m: method_config(m, seq.meta).tracker for m in ("rs", "blur")}
    ms = {m: [] for m in configs}
    steps = {m: [] for m in configs}
    for _, sharp, depth, frame, init, _ in tracking_pairs(seq, pairs + 1):
        for m, cfg in configs.items():
            kf = Keyframe.create(sharp, depth, seq.camera, cfg)
            t0 = time.perf_counter()
            _, _, diag = track(kf, frame.image, init, cfg, readout=readout_fraction(cfg.readout_s, tau))
            ms[m].append(1000 * (time.perf_counter() - t0))
            steps[m].append(sum(level["steps"] for level in diag["levels"]))
    warm = lambda xs: np.asarray(xs[1:] or xs, float)  # noqa: E731 - the first pair compiles
    out = {m: {"ms_per_call": float(np.median(warm(ms[m]))), "ms_per_lm_step": float(np.median(warm(ms[m]) / np.maximum(warm(steps[m]), 1))),
               "lm_steps": float(np.median(warm(steps[m])))} for m in configs}
    out["call_ratio"] = out["rs"]["ms_per_call"] / out["blur"]["ms_per_call"]
    out["step_ratio"] = out["rs"]["ms_per_lm_step"] / out["blur"]["ms_per_lm_step"]
    return out


def _sequence_info(path: pathlib.Path, spec: RollingSequence) -> dict:
    import yaml

    synth = yaml.safe_load((path / "synth.yaml").read_text())
    return {"preset": spec.preset, "readout_ms": spec.synth.readout_ms,
            "exposure_ms": spec.synth.exposure_ms, "shake_deg": spec.synth.shake_deg, "frames": spec.synth.frames,
            "mean_blur_px": synth.get("mean_blur_px"), "mean_bend_px": synth.get("mean_bend_px"), "path": str(path)}


def _cost(results: dict) -> dict:
    """Median tracking call of ``rs`` over ``blur`` (same n) on each sequence with a readout, and their median."""
    ratios = {}
    for name, r in results.items():
        m = r["methods"]
        if r["readout_ms"] > 0 and "median_track_ms" in m.get("rs", {}) and m.get("blur", {}).get("median_track_ms"):
            ratios[name] = m["rs"]["median_track_ms"] / m["blur"]["median_track_ms"]
    calls = {name: r["call_cost"] for name, r in results.items() if "call_cost" in r}
    return {"rs_over_blur_track_ms": ratios, "median_ratio": float(np.median(list(ratios.values()))) if ratios else None,
            "side_by_side": calls}


def run_rolling_benchmark(cfg: BenchConfig, methods: list[str], progress: bool = True) -> dict:
    """Generate (or reuse) the sequences of ``cfg`` under ``cfg.out``/data and run ``methods`` on
    each into ``cfg.out``/runs; the scores per sequence and method, and the cost of the RS model."""
    from ..datasets import open_sequence

    root = pathlib.Path(cfg.out)
    results = {}
    for spec in rolling_sequences(cfg):
        path = _generated(spec, root / "data", not progress)
        seq = open_sequence(path)
        results[spec.name] = {**_sequence_info(path, spec), "methods": {}}
        for method in methods:
            if progress:
                print(f"{spec.name}: {method}", file=sys.stderr)
            results[spec.name]["methods"][method] = _run_method(seq, root / "runs" / spec.name / method, method, progress)
        if spec.synth.readout_ms > 0 and {"rs", "blur"} <= set(methods):
            results[spec.name]["call_cost"] = call_cost(seq)
    return {"settings": as_dict(cfg), "methods": {m: list(ROLLING_METHODS[m]) for m in methods}, "sequences": results,
            "cost": _cost(results)}


def _cell(x: dict, key: str, fmt: str, scale: float = 1.0) -> str:
    v = x.get(key)
    return "-" if v is None or not np.isfinite(v) else format(scale * v, fmt)


def format_rolling_table(res: dict) -> str:
    """A markdown table, one line per sequence and method, then the cost of the rolling-shutter model."""
    lines = ["| sequence | readout ms | blur px | bend px | method | ATE mm | row endpoint px | drops | s/frame | ms/track |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for name, r in res["sequences"].items():
        for method, x in r["methods"].items():
            if "error" in x:
                lines.append(f"| {name} | {r['readout_ms']:g} | {r['mean_blur_px']} | {r['mean_bend_px']} | {method} | "
                             f"{x['error'][:60]} | | | | |")
                continue
            cells = [_cell(x, "ate_rmse_m", ".2f", 1000), _cell(x, "row_endpoint_px", ".2f"), _cell(x, "frame_drop_rate", ".2f"),
                     _cell(x, "seconds_per_frame", ".2f"), _cell(x, "median_track_ms", ".0f")]
            lines.append(f"| {name} | {r['readout_ms']:g} | {r['mean_blur_px']} | {r['mean_bend_px']} | {method} | " + " | ".join(cells) + " |")
    cost = res["cost"]
    lines += ["", "cost per tracking call, rs / blur (same n; median frames.csv ms): "
              + (", ".join(f"{k} {v:.2f}" for k, v in cost["rs_over_blur_track_ms"].items()) or "-")
              + (f"; median {cost['median_ratio']:.2f}" if cost["median_ratio"] is not None else ""),
              "one tracking call side by side (same pairs, sharp keyframe; ms per call / per LM step, rs vs blur): "
              + (", ".join(f"{k} {c['rs']['ms_per_call']:.0f} vs {c['blur']['ms_per_call']:.0f} ms ({c['call_ratio']:.2f}x), "
                           f"{c['rs']['ms_per_lm_step']:.1f} vs {c['blur']['ms_per_lm_step']:.1f} ms/step ({c['step_ratio']:.2f}x)"
                           for k, c in cost.get("side_by_side", {}).items()) or "-"),
              "methods: " + "; ".join(f"{m}: {' '.join(o) or 'defaults (readout from camera.yaml)'}" for m, o in res["methods"].items())
              + "; all with tracker.depth_weight=0 (images only)",
              "bend px: mean over frames of the true path's largest deviation from the straight start-end path (synth.yaml)"]
    return "\n".join(lines)


def main_rolling(cfg: BenchConfig, fmt: str = "table", quiet: bool = False) -> int:
    """``mbavo bench rolling-shutter``: run, print the table (or JSON), write OUT/results.json and OUT/table.md."""
    from ..io import prepare_out_dir

    methods = parse_rolling_methods(cfg.methods)
    rolling_sequences(cfg)  # reject bad presets and readouts before generating anything
    root = prepare_out_dir(cfg.out)
    res = run_rolling_benchmark(cfg, methods, progress=not quiet)
    table = format_rolling_table(res)
    (root / "results.json").write_text(json.dumps(res, indent=2))
    (root / "table.md").write_text(table + "\n")
    print(json.dumps(res, indent=2) if fmt == "json" else table)
    return 0
