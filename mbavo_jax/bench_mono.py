"""``mbavo bench mono``: the monocular system on generated presets and real clips, against itself
blind to blur (n = 1, the DSO-like baseline) and the RGB-D loop, all in one run.

Per sequence and method: ATE after Sim(3) alignment (m and % of the path length), relative drift
over ``delta`` frames (translation % and scale %), frames without a pose (dropped, initialising),
keyframes, and seconds per frame split into tracking, the back-end (candidates, bundle adjustment,
marginalisation) and the rest (deblurring, I/O), and the seconds of that spent compiling or loading
programs (a run at an image size the process has not seen yet pays it). With ``--seeds``, each
preset again at more seeds, and a second table of each method's mean ATE over the seeds (also in
``seed_means.json`` beside ``results.json``).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import pathlib
import sys
import time

import numpy as np

from .config import BenchConfig, EvalConfig, RunConfig, TrackerConfig, calibration_of
from .datasets import open_sequence
from .errors import MbavoError
from .io import read_tum_trajectory

__all__ = ["MONO_METHODS", "mono_configs", "run_mono_benchmark", "format_mono_table", "format_seed_table", "main_mono", "seed_groups",
           "seed_means", "trajectory_scores"]

MONO_METHODS = ("mono_n64", "mono_adaptive", "mono_n1", "rgbd_n64")


def mono_configs(base: TrackerConfig, methods=MONO_METHODS) -> dict[str, RunConfig]:
    """The run settings of each method (``rgbd_*``: the RGB-D loop, for reference)."""
    mono = lambda t: RunConfig(tracker=t).replace(odometry=dict(mode="mono"))
    configs = {"mono_n64": mono(base), "mono_adaptive": mono(dataclasses.replace(base, n_mode="adaptive")),
               "mono_n1": mono(dataclasses.replace(base, blur_aware=False)),
               "rgbd_n64": RunConfig(tracker=base).replace(odometry=dict(mode="rgbd"))}
    return {m: c for m, c in configs.items() if m in methods}


def trajectory_scores(seq, run: pathlib.Path, config: EvalConfig, delta: int = 10) -> dict:
    """ATE after Sim(3) alignment (m, % of the matched ground-truth path length) and the drift over
    ``delta`` matched frames: translation error and segment-length (scale) error, % of the segment."""
    from .evaluation.metrics import ape, relative_drift

    if seq.groundtruth is None or not (run / "trajectory.txt").is_file():
        return {}
    try:
        t_est, p_est = read_tum_trajectory(run / "trajectory.txt")
        if len(t_est) < 3:
            return {}
        t_gt, p_gt = seq.groundtruth
        res = ape(t_gt, p_gt, t_est, p_est, align="sim3", max_diff=config.t_max_diff)
        drift = relative_drift(t_gt, p_gt, t_est, p_est, delta, config.t_max_diff)
    except MbavoError:
        return {}
    return {"ate_rmse_m": res["rmse"], "ate_pct": 100 * res["rmse"] / max(drift["path_length_m"], 1e-12), **drift}


def _frame_rows(run: pathlib.Path) -> list[dict]:
    with open(run / "frames.csv") as fh:
        return list(csv.DictReader(fh))


def _timing(rows: list[dict], seconds: float) -> dict:
    """Seconds per frame: tracking, back-end and the rest; the median back-end seconds per keyframe
    (the first one compiles the bundle adjustment)."""
    n = max(len(rows), 1)
    track = sum(float(r["ms"] or 0) for r in rows) / 1000
    backend = [float(r["backend_ms"]) / 1000 for r in rows if r.get("backend_ms")]
    return {"seconds_per_frame": seconds / n, "track_s_per_frame": track / n, "backend_s_per_frame": sum(backend) / n,
            "other_s_per_frame": max(seconds - track - sum(backend), 0.0) / n,
            "backend_s_per_keyframe": float(np.median(backend)) if backend else 0.0}


def run_method(seq, run: pathlib.Path, config: RunConfig, progress: bool) -> dict:
    """One method over a sequence: scores, frames without a pose, keyframes, timing (with the
    seconds spent compiling or loading programs, which the timing includes)."""
    from .odometry import run_odometry
    from .runtime import compile_counts

    t0, before = time.perf_counter(), compile_counts()
    summ = run_odometry(seq, run, config, progress=progress)
    seconds, after = time.perf_counter() - t0, compile_counts()
    rows = _frame_rows(run)
    waiting = sum(r["status"] == "initialising" for r in rows)
    return {**trajectory_scores(seq, run, config.evaluation), "frames": summ["frames"], "dropped": summ["dropped"],
            "initialising": waiting, "keyframes": summ["keyframes"], **_timing(rows, seconds),
            "compile_s": after["compile_seconds"] - before["compile_seconds"], "compiled": after["compiled"] - before["compiled"]}


def run_mono_benchmark(sequences: dict, out_root, methods=MONO_METHODS, progress: bool = True,
                       tracker_overrides: dict | None = None) -> dict:
    """Each of ``methods`` on each sequence (name -> folder); ``rgbd_*`` only where there is depth.
    ``out_root/results.json`` holds every finished run's scores as soon as it finishes."""
    unknown = [m for m in methods if m not in MONO_METHODS]
    if unknown:
        raise MbavoError(f"unknown method {', '.join(unknown)} (choose from {', '.join(MONO_METHODS)})")
    results, root = {}, pathlib.Path(out_root)
    root.mkdir(parents=True, exist_ok=True)
    for name, path in sequences.items():
        seq = open_sequence(path)
        base = TrackerConfig(**{**(tracker_overrides or {}), **calibration_of(seq.meta)})
        row = results[name] = {}
        for method, config in mono_configs(base, methods).items():
            if method.startswith("rgbd") and not seq.has_depth:
                continue
            if progress:
                print(f"{name}: {method}", file=sys.stderr)
            try:
                row[method] = run_method(seq, root / name / method, config, progress)
            except MbavoError as exc:
                row[method] = {"error": str(exc)}
            (root / "results.json").write_text(json.dumps(results, indent=2))
    return results


def _cell(r: dict) -> str:
    if "error" in r:
        return f"error: {r['error']}"
    if "ate_rmse_m" not in r:
        return f"lost ({r.get('dropped', '?')} dropped, {r.get('initialising', '?')} initialising)"
    return (f"{r['ate_rmse_m']:.4f} m ({r['ate_pct']:.2f} %) | drift {r['drift_trans_pct']:.1f} % / scale {r['drift_scale_pct']:.1f} % | "
            f"drop {r['dropped']} init {r['initialising']} kf {r['keyframes']} | {r['seconds_per_frame']:.2f} s/f "
            f"(track {r['track_s_per_frame']:.2f}, BA {r['backend_s_per_frame']:.2f}, other {r['other_s_per_frame']:.2f}; "
            f"back-end/kf {r['backend_s_per_keyframe']:.2f}; compiling {r['compile_s']:.0f} s)")


def format_mono_table(results: dict) -> str:
    """A markdown table: one row per sequence and method."""
    lines = ["| sequence | method | ATE Sim(3) (% of path) | drift per 10 frames (trans / scale) | frames without pose | "
             "s per frame (track, BA, other; BA per keyframe; compiling in all) |", "|---|---|---|---|---|---|"]
    for name, row in results.items():
        for method, r in row.items():
            parts = _cell(r).split(" | ")
            lines.append(f"| {name} | {method} | " + " | ".join(parts + [""] * (4 - len(parts))) + " |")
    return "\n".join(lines)


def main_mono(cfg: BenchConfig, fmt: str = "table", quiet: bool = False) -> int:
    """``mbavo bench mono``: the presets of ``cfg.presets`` (exposure hidden, depth not read by the
    mono methods), KITTI 07 and the TUM clip sharp and blurred."""
    from .bench import bench_data, real_clip, with_hidden_exposure, tum_blurred

    groups = seed_groups(cfg)
    seqs = {name: bench_data(p, dataclasses.replace(cfg, seed=s), cfg.frames, quiet, exact=True)
            for p, named in groups.items() for name, s in named.items()}
    seqs = {k: v for k, v in with_hidden_exposure(seqs, "all").items() if k.endswith("_noexp")}
    if cfg.kitti:
        seqs["kitti07"] = real_clip(cfg.kitti)
    if cfg.tum:
        seqs["tum_xyz"] = real_clip(cfg.tum)
        seqs["tum_xyz_blurred"] = tum_blurred(cfg, quiet)
    methods = [m for m in cfg.methods.split(",") if m] or MONO_METHODS
    root = pathlib.Path(cfg.out if cfg.out != BenchConfig().out else "runs/bench_mono")
    results = run_mono_benchmark(seqs, root, methods, progress=not quiet)
    names, several = {p: [f"{n}_noexp" for n in named] for p, named in groups.items()}, len(cfg.seed_list()) > 1
    if several:
        (root / "seed_means.json").write_text(json.dumps({p: seed_means(results, n) for p, n in names.items()}, indent=2))
    if fmt == "json":
        print(json.dumps(results, indent=2))
    else:
        print(format_mono_table(results) + ("\n\n" + format_seed_table(results, names) if several else ""))
    return 0


def seed_groups(cfg: BenchConfig) -> dict[str, dict[str, int]]:
    """Per blur preset, its sequences' table names and seeds: ``<preset>`` at ``cfg.seed``, then
    ``<preset>_s<seed>`` for each of ``cfg.seeds``."""
    seeds = cfg.seed_list()
    return {p: {(p if s == cfg.seed else f"{p}_s{s}"): s for s in seeds} for p in cfg.presets.split(",") if p}


def seed_means(results: dict, names: list[str]) -> dict[str, dict]:
    """Per method, over the sequences ``names`` it ran on: the mean ATE (% of path) of those it
    scored, how many, and against mono_n1 on the sequences both scored: the ratio of their mean ATEs
    and each sequence's ratio."""
    out = {}
    for method in dict.fromkeys(m for n in names for m in results.get(n, {})):
        rows = [(results[n][method], results[n].get("mono_n1", {})) for n in names if method in results.get(n, {})]
        scored = [r["ate_pct"] for r, _ in rows if "ate_pct" in r]
        paired = np.array([(r["ate_pct"], b["ate_pct"]) for r, b in rows if "ate_pct" in r and "ate_pct" in b]).reshape(-1, 2)
        out[method] = {"mean_ate_pct": float(np.mean(scored)) if scored else float("nan"), "scored": len(scored), "runs": len(rows),
                       "ratio": float(paired[:, 0].mean() / paired[:, 1].mean()) if len(paired) else float("nan"),
                       "ratios": [float(a / b) for a, b in paired]}
    return out


def format_seed_table(results: dict, groups: dict[str, list[str]]) -> str:
    """A markdown table: per blur preset and method, the mean ATE over the seeds' sequences and its
    ratio to mono_n1's mean over the sequences both scored (each seed's ratio beside it)."""
    lines = ["| preset | method | seeds scored | mean ATE (% of path) | mean / mono_n1's mean | per seed: ATE / mono_n1's |",
             "|---|---|---|---|---|---|"]
    for preset, names in groups.items():
        for method, m in seed_means(results, names).items():
            ratios = ", ".join(f"{r:.2f}" for r in m["ratios"])
            lines.append(f"| {preset} | {method} | {m['scored']} of {m['runs']} | {m['mean_ate_pct']:.3f} | {m['ratio']:.2f} | {ratios} |")
    return "\n".join(lines)
