"""``mbavo bench mono``: the monocular system on generated presets and real clips, against itself
blind to blur (n = 1, the DSO-like baseline) and the RGB-D loop, all in one run.

Per sequence and method: ATE after Sim(3) alignment (m and % of the path length), relative drift
over ``delta`` frames (translation % and scale %), frames without a pose (dropped, initialising),
keyframes, and seconds per frame split into tracking, the back-end (candidates, bundle adjustment,
marginalisation) and the rest (deblurring, I/O), and the seconds of that spent compiling or loading
programs (a run at an image size the process has not seen yet pays it). With ``--seeds``, each
preset again at more seeds, and a second table of each method's mean ATE over the seeds (also in
``seed_means.json`` beside ``results.json``). With ``--draws K``, each method runs K times on each
sequence, at K Huber thresholds a part in a thousand apart (``config.HUBER_DRAWS``): a monocular run
can keep or lose its scale on a rounding-sized change, and the mean over the draws is what the
second table then compares. With ``--dso PATH``, DSO runs on each sequence too (method ``dso``,
:mod:`.dso`), and each of our rows adds the ATE of it and of DSO over the frames both posed.
Every row says when the method first posed a frame, how many it posed and how often it started
afresh (ours: frames.csv's "initialising again"; DSO: its "RESETTING!").
"""

from __future__ import annotations

import csv
import dataclasses
import json
import pathlib
import sys
import time

import numpy as np

from ..config import HUBER_DRAWS, BenchConfig, EvalConfig, RunConfig, TrackerConfig, calibration_of
from ..datasets import open_sequence
from ..errors import MbavoError
from ..io import read_tum_trajectory
from .dso import check_dso_binary, dso_restarts, run_dso

__all__ = ["MONO_METHODS", "mono_configs", "draw_huber", "run_draws", "run_mono_benchmark", "format_mono_table", "format_seed_table",
           "main_mono", "seed_groups", "seed_means", "trajectory_scores", "posing", "ate_both_posed", "DSO_METHOD"]

MONO_METHODS = ("mono_n64", "mono_adaptive", "mono_n1", "mono_direct_n64", "mono_direct_n1", "rgbd_n64")
DSO_METHOD = "dso"  # the peer, run when --dso names its binary
RESTART_NOTE = "initialising again"  # frames.csv note of a monocular run that lost track and starts afresh (odometry/mono.py)


def mono_configs(base: TrackerConfig, methods=MONO_METHODS) -> dict[str, RunConfig]:
    """The run settings of each method (``mono_direct_*``: started by the direct initialiser,
    ``mono.initialiser = direct``; ``rgbd_*``: the RGB-D loop, for reference)."""
    mono = lambda t, init="corners": RunConfig(tracker=t).replace(odometry=dict(mode="mono"), mono=dict(initialiser=init))
    blind = dataclasses.replace(base, blur_aware=False)
    configs = {"mono_n64": mono(base), "mono_adaptive": mono(dataclasses.replace(base, n_mode="adaptive")),
               "mono_n1": mono(blind), "mono_direct_n64": mono(base, "direct"), "mono_direct_n1": mono(blind, "direct"),
               "rgbd_n64": RunConfig(tracker=base).replace(odometry=dict(mode="rgbd"))}
    return {m: c for m, c in configs.items() if m in methods}


def trajectory_scores(seq, run: pathlib.Path, config: EvalConfig, delta: int = 10) -> dict:
    """ATE after Sim(3) alignment (m, % of the matched ground-truth path length) and the drift over
    ``delta`` matched frames: translation error and segment-length (scale) error, % of the segment."""
    from ..evaluation.metrics import ape, relative_drift

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


def _trajectory(run: pathlib.Path) -> tuple[np.ndarray, np.ndarray]:
    """A run's trajectory.txt (stamps, poses); empty when it has none or no pose."""
    try:
        return read_tum_trajectory(run / "trajectory.txt")
    except MbavoError:  # missing, or a header without poses (never initialised)
        return np.zeros(0), np.zeros((0, 7))


def run_restarts(run: pathlib.Path) -> int:
    """How often a run started afresh: our frames.csv notes "initialising again", DSO's dso.log says "RESETTING!"."""
    if (run / "frames.csv").is_file():
        return sum(RESTART_NOTE in (r.get("note") or "") for r in _frame_rows(run))
    return dso_restarts((run / "dso.log").read_text(errors="replace")) if (run / "dso.log").is_file() else 0


def posing(stamps, run: pathlib.Path, max_diff: float) -> dict:
    """The frames (of the sequence's ``stamps``) a run posed: the first one's index (None: none),
    how many, and how often it started afresh (:func:`run_restarts`)."""
    from ..evaluation.associate import associate

    t, _ = _trajectory(run)
    index = np.unique(associate(t, np.asarray(stamps, np.float64), max_diff)[1]) if len(t) else np.zeros(0, np.int64)
    return {"first_posed": int(index[0]) if len(index) else None, "posed": int(len(index)), "restarts": run_restarts(run)}


def ate_both_posed(seq, run: pathlib.Path, peer: pathlib.Path, config: EvalConfig) -> dict:
    """Two runs scored over the frames both posed: ``both_posed`` (how many) and, with at least 3
    and ground truth, each one's ATE after its own Sim(3) alignment on that subset (m and % of the
    subset's true path length): ``ate_both_m``/``ate_both_pct`` (``run``), ``peer_ate_both_m``/``..._pct``."""
    from ..evaluation.associate import associate
    from ..evaluation.metrics import ape

    (t_a, p_a), (t_b, p_b) = _trajectory(run), _trajectory(peer)
    i_a, i_b = associate(t_a, t_b, config.t_max_diff) if len(t_a) and len(t_b) else (np.zeros(0, int), np.zeros(0, int))
    out = {"both_posed": int(len(i_a))}
    if len(i_a) < 3 or seq.groundtruth is None:
        return out
    t_gt, p_gt = seq.groundtruth
    try:
        a, b = (ape(t_gt, p_gt, t, p, align="sim3", max_diff=config.t_max_diff) for t, p in ((t_a[i_a], p_a[i_a]), (t_b[i_b], p_b[i_b])))
    except MbavoError:  # no ground truth at those stamps
        return out
    _, i_gt = associate(t_a[i_a], t_gt, config.t_max_diff)
    length = max(float(np.linalg.norm(np.diff(p_gt[i_gt, :3], axis=0), axis=1).sum()), 1e-12)
    return {**out, "ate_both_m": a["rmse"], "ate_both_pct": 100 * a["rmse"] / length, "peer_ate_both_m": b["rmse"],
            "peer_ate_both_pct": 100 * b["rmse"] / length}


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
    from ..odometry import run_odometry
    from ..runtime import compile_counts

    t0, before = time.perf_counter(), compile_counts()
    summ = run_odometry(seq, run, config, progress=progress)
    seconds, after = time.perf_counter() - t0, compile_counts()
    rows = _frame_rows(run)
    waiting = sum(r["status"] == "initialising" for r in rows)
    return {**trajectory_scores(seq, run, config.evaluation), **posing(seq.timestamps, run, config.evaluation.t_max_diff),
            "frames": summ["frames"], "dropped": summ["dropped"], "initialising": waiting, "keyframes": summ["keyframes"], **_timing(rows, seconds),
            "compile_s": after["compile_seconds"] - before["compile_seconds"], "compiled": after["compiled"] - before["compiled"]}


def draw_huber(huber: float, d: int) -> float:
    """The Huber threshold of draw ``d``: ``HUBER_DRAWS[d]`` for the default threshold, else
    ``huber`` scaled by ``HUBER_DRAWS[d] / HUBER_DRAWS[0]``."""
    return HUBER_DRAWS[d] if huber == HUBER_DRAWS[0] else huber * HUBER_DRAWS[d] / HUBER_DRAWS[0]


def run_draws(seq, folder: pathlib.Path, config: RunConfig, draws: int = 1, progress: bool = True) -> dict:
    """:func:`run_method` at the first ``draws`` Huber draws (:func:`draw_huber`; draw 0 is
    ``config`` itself, in ``folder``, the others in ``<folder>_huber<h>``). Returns draw 0's row;
    with ``draws`` > 1 it adds ``draws`` (each run's threshold, ATE in % or None, frames dropped)
    and ``ate_pct_mean``, the mean ATE of the draws that scored (None when none did)."""
    rows = []
    for d in range(draws):
        h = draw_huber(config.tracker.huber, d)
        if progress and draws > 1:
            print(f"  draw {d + 1} of {draws}: tracker.huber {h:.7f}", file=sys.stderr)
        cfg = config if d == 0 else config.replace(tracker=dict(huber=h))
        rows.append((h, run_method(seq, folder if d == 0 else folder.with_name(f"{folder.name}_huber{h:.7f}"), cfg, progress)))
    if draws == 1:
        return rows[0][1]
    per = [{"huber": h, "ate_pct": r.get("ate_pct"), "dropped": r["dropped"]} for h, r in rows]
    scored = [p["ate_pct"] for p in per if p["ate_pct"] is not None]
    return {**rows[0][1], "draws": per, "ate_pct_mean": float(np.mean(scored)) if scored else None}


def run_mono_benchmark(sequences: dict, out_root, methods=MONO_METHODS, progress: bool = True,
                       tracker_overrides: dict | None = None, draws: int = 1, dso: str = "", dso_timeout: float = 600.0) -> dict:
    """Each of ``methods`` on each sequence (name -> folder), at ``draws`` Huber draws
    (:func:`run_draws`); ``rgbd_*`` only where there is depth; with ``dso`` (a ``dso_dataset``
    binary) DSO too, once per sequence, and each of our rows adds :func:`ate_both_posed` against it.
    ``out_root/results.json`` holds every finished method's scores as soon as it finishes."""
    unknown = [m for m in methods if m not in (*MONO_METHODS, DSO_METHOD)]
    if unknown:
        raise MbavoError(f"unknown method {', '.join(unknown)} (choose from {', '.join(MONO_METHODS)}, {DSO_METHOD})")
    if DSO_METHOD in methods and not dso:
        raise MbavoError(f"method {DSO_METHOD} needs --dso PATH (a dso_dataset binary)")
    if dso:
        check_dso_binary(dso)
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
                row[method] = run_draws(seq, root / name / method, config, draws, progress)
            except MbavoError as exc:
                row[method] = {"error": str(exc)}
            (root / "results.json").write_text(json.dumps(results, indent=2))
        if dso:
            if progress:
                print(f"{name}: {DSO_METHOD}", file=sys.stderr)
            row[DSO_METHOD] = dso_row(seq, root / name / DSO_METHOD, dso, dso_timeout)
            compare_with_dso(seq, row, root / name)
            (root / "results.json").write_text(json.dumps(results, indent=2))
    return results


def dso_row(seq, run: pathlib.Path, binary: str, timeout_s: float) -> dict:
    """DSO's row: :func:`.dso.run_dso` scored as our runs are (:func:`trajectory_scores`, :func:`posing`)."""
    try:
        facts = run_dso(seq, run, binary, timeout_s)
    except MbavoError as exc:
        return {"error": str(exc)}
    evaluation = EvalConfig()
    return {**facts, **trajectory_scores(seq, run, evaluation), **posing(seq.timestamps, run, evaluation.t_max_diff)}


def compare_with_dso(seq, row: dict, folder: pathlib.Path) -> None:
    """Add :func:`ate_both_posed` against DSO's run (``folder/dso``) to each of our rows of ``row``."""
    if "error" in row.get(DSO_METHOD, {"error": ""}):
        return
    for method, r in row.items():
        if method != DSO_METHOD and "error" not in r:
            r.update(ate_both_posed(seq, folder / method, folder / DSO_METHOD, EvalConfig()))


def _cell(r: dict) -> str:
    """ATE | drift | frames without pose | seconds per frame (DSO: its whole process)."""
    if "error" in r:
        return f"error: {r['error']}"
    if "ate_rmse_m" not in r:
        dropped = r["dropped"] if "dropped" in r else r["frames"] - r.get("posed", 0) if "frames" in r else "?"  # DSO: frames not posed
        return f"lost ({dropped} dropped, {r.get('initialising', '?')} initialising)"
    scores = f"{r['ate_rmse_m']:.4f} m ({r['ate_pct']:.2f} %) | drift {r['drift_trans_pct']:.1f} % / scale {r['drift_scale_pct']:.1f} % | "
    if "track_s_per_frame" not in r:  # DSO
        return scores + f"{r['frames'] - r['posed']} of {r['frames']} | {r['seconds_per_frame']:.2f} s/f (the whole DSO process)"
    return scores + (f"drop {r['dropped']} init {r['initialising']} kf {r['keyframes']} | {r['seconds_per_frame']:.2f} s/f "
                     f"(track {r['track_s_per_frame']:.2f}, BA {r['backend_s_per_frame']:.2f}, other {r['other_s_per_frame']:.2f}; "
                     f"back-end/kf {r['backend_s_per_keyframe']:.2f}; compiling {r['compile_s']:.0f} s)")


def _posing_cell(r: dict) -> str:
    """First posed frame / frames posed of all / restarts (:func:`posing`)."""
    if "posed" not in r:
        return ""
    return f"{'-' if r['first_posed'] is None else r['first_posed']} / {r['posed']} of {r['frames']} / {r['restarts']}"


def _both_cell(r: dict) -> str:
    """Ours / DSO ATE (% of path) over the frames both posed (:func:`ate_both_posed`)."""
    if "both_posed" not in r:
        return ""
    if "ate_both_pct" not in r:
        return f"{r['both_posed']} frames: too few to score"
    return f"{r['ate_both_pct']:.2f} % / {r['peer_ate_both_pct']:.2f} % ({r['both_posed']} frames)"


def _draws_cell(r: dict) -> str:
    """The ATE over a run's draws: the mean, the range, how many scored, the frames they dropped."""
    ates = [p["ate_pct"] for p in r["draws"] if p["ate_pct"] is not None]
    spread = f"{r['ate_pct_mean']:.2f} % ({min(ates):.2f}-{max(ates):.2f}), " if ates else ""
    return f"{spread}{len(ates)} of {len(r['draws'])} scored, {sum(p['dropped'] for p in r['draws'])} dropped"


def format_mono_table(results: dict) -> str:
    """A markdown table: one row per sequence and method; with DSO, a column of ours and DSO's ATE
    over the frames both posed; with draws, a last column: the ATE over them (:func:`_draws_cell`)."""
    several = any("draws" in r for row in results.values() for r in row.values())
    dso = any(DSO_METHOD in row for row in results.values())
    lines = ["| sequence | method | ATE Sim(3) (% of path) | drift per 10 frames (trans / scale) | frames without pose | "
             "s per frame (track, BA, other; BA per keyframe; compiling in all) | first posed / posed / restarts |"
             + (" ATE over the frames both posed: this / DSO |" if dso else "") + (" over the draws: mean ATE (range) |" if several else ""),
             "|---|---|---|---|---|---|---|" + ("---|" if dso else "") + ("---|" if several else "")]
    for name, row in results.items():
        for method, r in row.items():
            parts = _cell(r).split(" | ")
            parts = parts + [""] * (4 - len(parts)) + [_posing_cell(r)] + ([_both_cell(r)] if dso else [])
            parts += [_draws_cell(r) if "draws" in r else ""] if several else []
            lines.append(f"| {name} | {method} | " + " | ".join(parts) + " |")
    return "\n".join(lines)


def main_mono(cfg: BenchConfig, fmt: str = "table", quiet: bool = False) -> int:
    """``mbavo bench mono``: the presets of ``cfg.presets`` (exposure hidden, depth not read by the
    mono methods), KITTI 07 and the TUM clip sharp and blurred."""
    from .sequences import bench_data, real_clip, tum_blurred, with_hidden_exposure

    if cfg.dso:
        check_dso_binary(cfg.dso)  # before any sequence is made
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
    results = run_mono_benchmark(seqs, root, methods, progress=not quiet, draws=cfg.draws, dso=cfg.dso, dso_timeout=cfg.dso_timeout)
    names, several = {p: [f"{n}_noexp" for n in named] for p, named in groups.items()}, len(cfg.seed_list()) > 1 or cfg.draws > 1
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


def _ate(r: dict) -> float | None:
    """A run's ATE (% of path): the mean over its draws when it has them; None when unscored."""
    return r.get("ate_pct_mean") if "draws" in r else r.get("ate_pct")


def seed_means(results: dict, names: list[str]) -> dict[str, dict]:
    """Per method, over the sequences ``names`` it ran on: the mean ATE (% of path; a sequence
    with draws counts with its mean over them) of those it scored, how many, and against mono_n1 on
    the sequences both scored: the ratio of their mean ATEs and each sequence's ratio."""
    out = {}
    for method in dict.fromkeys(m for n in names for m in results.get(n, {})):
        rows = [(_ate(results[n][method]), _ate(results[n].get("mono_n1", {}))) for n in names if method in results.get(n, {})]
        scored = [a for a, _ in rows if a is not None]
        paired = np.array([(a, b) for a, b in rows if a is not None and b is not None]).reshape(-1, 2)
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
