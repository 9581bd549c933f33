"""``mbavo bench speed``: where the whole loop's time goes, start-up with and without the compilation
cache, and memory over a long run.

* timing: our loop, the same loop blind to blur (n = 1) and, with ``--compare``, ours with other
  settings, unprofiled, run in turns in one process after a warm-up of each (so that tracing and
  compilation are not counted); the ratios are of their medians (cProfile's overhead falls unevenly
  on Python-heavy paths, so it gives no ratio); each variant's ATE, keyframes and keyframe PSNR;
* profile: one more run of ours under cProfile, its wall time split into tracking, deblurring,
  keyframe creation, the monocular back-end, reading frames and writing outputs (the rest is the
  loop's own bookkeeping), and the seconds spent compiling (inside those parts);
* start-up: ``mbavo track`` twice in fresh processes on one cache folder: the first compiles every
  program, the second loads them (seconds to the first tracked frame and programs compiled, each);
* memory: the resident memory frames.csv records after frame 100 and after the last frame of a long
  run (``rss_mb``), and their ratio.
"""

from __future__ import annotations

import cProfile
import csv
import json
import math
import pathlib
import pstats
import statistics
import subprocess
import sys
import tempfile
import time

from ..config import BenchConfig, RunConfig

__all__ = ["PROFILE_PARTS", "profile_run", "timed_runs", "startup_runs", "memory_growth", "speed_benchmark", "format_speed_table", "main_speed"]

# part of the loop -> the functions (file suffix, name) whose cumulative time it is
PROFILE_PARTS = {
    "tracking": [("tracking/tracker.py", "track")],
    "deblurring": [("mbavo_jax/deblur.py", "deblur")],
    "keyframe creation": [("tracking/tracker.py", "create"), ("tracking/tracker.py", "from_points")],
    "back-end (mono)": [("odometry/mono.py", "_backend")],
    "reading frames": [("datasets/base.py", "__getitem__")],
    "writing outputs": [("odometry/outputs.py", "write"), ("odometry/outputs.py", "write_points")],
}


def _part_seconds(stats: pstats.Stats) -> dict[str, float]:
    """Cumulative seconds of each part's functions (a function called inside another of the same
    part is counted once: its callers' time already holds it)."""
    out = dict.fromkeys(PROFILE_PARTS, 0.0)
    for (path, _, name), (_, _, _, cumulative, callers) in stats.stats.items():
        for part, functions in PROFILE_PARTS.items():
            if any(path.endswith(suffix) and name == fn for suffix, fn in functions):
                inner = any(c[0].endswith(s) and c[2] == f for c in callers for s, f in functions)
                out[part] += 0.0 if inner else cumulative
    return out


def profile_run(seq, out, config: RunConfig = RunConfig(), max_frames: int | None = None) -> dict:
    """One ``run_odometry`` of ``seq`` into ``out`` under cProfile: total seconds, seconds per
    part (:data:`PROFILE_PARTS`), the rest, compile seconds and the run's summary."""
    from ..odometry import run_odometry
    from ..runtime import compile_counts

    before = compile_counts()
    profiler = cProfile.Profile()
    t0 = time.perf_counter()
    profiler.enable()
    summary = run_odometry(seq, out, config, max_frames=max_frames, progress=False)
    profiler.disable()
    total = time.perf_counter() - t0
    parts = _part_seconds(pstats.Stats(profiler))
    return {"seconds": total, "frames": summary["frames"], "parts": parts, "rest": total - sum(parts.values()),
            "compile_seconds": compile_counts()["compile_seconds"] - before["compile_seconds"], "summary": summary}


def _track_process(seq, out, overrides: list[str], max_frames: int | None = None) -> dict:
    """``mbavo track`` in a fresh process; its JSON summary (one line if it fails)."""
    cmd = [sys.executable, "-m", "mbavo_jax.cli", "track", str(seq), "--out", str(out), "--quiet", "--format", "json"]
    cmd += [a for o in overrides for a in ("--set", o)] + (["--max-frames", str(max_frames)] if max_frames else [])
    done = subprocess.run(cmd, capture_output=True, text=True)
    if done.returncode != 0:
        raise RuntimeError(f"mbavo track failed: {done.stderr.strip().splitlines()[-1:]}")
    return json.loads(done.stdout)


def startup_runs(seq, out, overrides: list[str] = (), max_frames: int = 3) -> dict:
    """Two runs of the first ``max_frames`` frames in fresh processes sharing a new, empty cache
    folder: {"cold": ..., "cached": ...}, each with ``startup_s`` (to the first tracked frame),
    ``compiled`` and ``cache_hits``; and a run with the cache off (``off``)."""
    out = pathlib.Path(out)
    with tempfile.TemporaryDirectory() as cache:
        runs = {}
        for name, extra in (("cold", []), ("cached", []), ("off", ["runtime.compilation_cache=false"])):
            s = _track_process(seq, out / name, [*overrides, f"runtime.cache_dir={cache}", *extra], max_frames)
            runs[name] = {k: s.get(k) for k in ("startup_s", "compiled", "cache_hits")}
    return runs


def memory_growth(run_dir, early: int = 100) -> dict:
    """Resident memory (MiB) that a run's frames.csv records after frame ``early`` and after its last
    frame, and their ratio (1.0: flat)."""
    with open(pathlib.Path(run_dir) / "frames.csv", newline="") as fh:
        rows = [r for r in csv.DictReader(fh) if r.get("rss_mb")]
    if len(rows) <= early:
        raise ValueError(f"{run_dir}: {len(rows)} frames with rss_mb, need more than {early}")
    a, b = float(rows[early - 1]["rss_mb"]), float(rows[-1]["rss_mb"])
    return {"frames": len(rows), f"rss_mb_at_{early}": a, "rss_mb_at_end": b, "peak_rss_mb": max(float(r["rss_mb"]) for r in rows),
            "ratio": b / a}


def timed_runs(seq, out, variants: dict[str, RunConfig], frames: int, reps: int) -> dict[str, list[float]]:
    """Wall seconds of ``reps`` unprofiled ``run_odometry`` calls of each variant (its run settings)
    on ``seq``'s first ``frames`` frames, the variants in turns, after one warm-up run of each in this
    process (tracing and compilation are the start-up runs' to measure)."""
    from ..odometry import run_odometry

    seconds = {name: [] for name in variants}
    for rep in range(reps + 1):
        for name, config in variants.items():
            t0 = time.perf_counter()
            run_odometry(seq, pathlib.Path(out) / name / f"run{rep}", config, max_frames=frames, progress=False)
            if rep:
                seconds[name].append(time.perf_counter() - t0)
    return seconds


def speed_benchmark(cfg: BenchConfig, quiet: bool = False) -> dict:
    """Per blur preset of ``cfg.preset`` (generated at ``cfg.width`` x ``cfg.height``, ``cfg.frames``
    frames; also without its exposure metadata for those named in ``cfg.hide_exposure``): our whole
    loop and the same loop blind to blur (n = 1), ``cfg.speed_reps`` unprofiled runs each in turns
    (:func:`timed_runs`), then ours once under the profile; Open3D hybrid's frame-to-frame odometry on
    the same frames; and, with ``cfg.startup``, the start-up of fresh processes with an empty cache,
    a full one and none."""
    from ..config import calibration_of, load_config
    from ..datasets import open_sequence
    from ..methods import run_peer
    from .sequences import bench_data, with_hidden_exposure

    out, results = pathlib.Path(cfg.out).parent / "bench_speed", {}
    presets = {p: bench_data(p, cfg, cfg.frames, quiet) for p in cfg.preset.split(",") if p}
    compare = [o.strip() for o in cfg.compare.split(";") if o.strip()]
    for name, data in with_hidden_exposure(presets, cfg.hide_exposure).items():
        seq = open_sequence(data)
        startup = startup_runs(data, out / name / "startup") if cfg.startup else {}
        calibration = calibration_of(seq.meta)
        config = load_config(None, [], calibration)
        variants = {"ours": config, "n1": config.replace(tracker=dict(blur_aware=False))}
        if compare:
            variants["compare"] = load_config(None, compare, calibration)
        timed = timed_runs(seq, out / name, variants, cfg.frames, cfg.speed_reps)
        profile = profile_run(seq, out / name / "profiled", config, max_frames=cfg.frames)
        peer = {} if cfg.no_peers else run_peer(seq, out / name / "open3d", "open3d", config.evaluation, cfg.peer_depth_max)
        results[name] = {"frames": profile["frames"], "seconds": timed, "profile": profile, "scores": variant_scores(seq, out / name, variants),
                         "compare": "; ".join(compare), "open3d_s_per_frame": peer.get("seconds_per_frame"), "startup": startup}
    return results


def variant_scores(seq, out, variants: dict[str, RunConfig]) -> dict[str, dict]:
    """ATE (m, NaN: lost), keyframes and mean keyframe PSNR (dB, against the generated sharp frames)
    of each variant's first timed run (``out/<variant>/run1``), scored as ``mbavo bench odometry`` does."""
    from ..io import read_tum_trajectory
    from ..methods import ate_rmse, deblur_quality

    scores = {}
    for name, config in variants.items():
        run = pathlib.Path(out) / name / "run1"
        scores[name] = {"ate_m": ate_rmse(seq, run, config.evaluation),
                        "keyframes": len(read_tum_trajectory(run / "keyframes.txt")[0]),
                        "keyframe_psnr": deblur_quality(seq, run).get("psnr_deblurred")}
    return scores


def format_speed_table(res: dict) -> str:
    """The whole loop against Open3D and n = 1, where its time goes, and start-up, one block per preset."""
    lines = []
    for preset, r in res.items():
        o, frames = r["profile"], max(r["frames"], 1)
        ours, blind = (statistics.median(r["seconds"][k]) / frames for k in ("ours", "n1"))
        peer = r["open3d_s_per_frame"]
        ratio = f"{ours / peer:.1f}x Open3D hybrid ({peer:.3f} s)" if peer else "no Open3D"
        runs = {k: ", ".join(f"{x:.2f}" for x in v) for k, v in r["seconds"].items()}
        lines += [f"[{preset}] whole loop {ours:.3f} s/frame over {r['frames']} frames = {ratio}; {ours / blind:.2f}x ours "
                  f"blind to blur (n = 1, {blind:.3f} s); medians of unprofiled runs in turns (ours {runs['ours']} s; n = 1 {runs['n1']} s)"]
        lines += _score_lines(r, frames)
        lines += [f"where the time goes, one run under cProfile ({o['seconds']:.2f} s):", "| part | seconds | share |", "|---|---|---|"]
        for part, sec in [*o["parts"].items(), ("rest", o["rest"])]:
            lines.append(f"| {part} | {sec:.2f} | {100 * sec / o['seconds']:.0f} % |")
        lines.append(f"| (compiling or loading programs, inside the parts) | {o['compile_seconds']:.2f} | |")
        if r["startup"]:
            lines += ["| start-up run | programs compiled | from the cache | s to first tracked frame |", "|---|---|---|---|"]
            lines += [f"| {k} | {v['compiled']} | {v['cache_hits']} | {v['startup_s']:.1f} |" for k, v in r["startup"].items()]
        lines.append("")
    return "\n".join(lines)


def _score_lines(r: dict, frames: int) -> list[str]:
    """The variants side by side: seconds per frame (median), its ratio to ours, ATE, keyframes, PSNR."""
    if not r.get("scores"):
        return []
    ours = statistics.median(r["seconds"]["ours"])
    label = {"ours": "ours", "n1": "n = 1", "compare": f"ours with {r.get('compare')}"}
    lines = ["| variant | s/frame | x ours | ATE (mm) | keyframes | keyframe PSNR (dB) |", "|---|---|---|---|---|---|"]
    for name, sc in r["scores"].items():
        sec = statistics.median(r["seconds"][name])
        ate = "lost" if math.isnan(sc["ate_m"]) else f"{1000 * sc['ate_m']:.2f}"
        psnr = "-" if sc["keyframe_psnr"] is None else f"{sc['keyframe_psnr']:.2f}"
        lines.append(f"| {label[name]} | {sec / frames:.3f} | {sec / ours:.2f} | {ate} | {sc['keyframes']} | {psnr} |")
    return lines


def main_speed(cfg: BenchConfig, fmt: str = "table", quiet: bool = False) -> int:
    """``mbavo bench speed``."""
    res = speed_benchmark(cfg, quiet)
    print(json.dumps(res, indent=2, default=float) if fmt == "json" else format_speed_table(res))
    return 0
