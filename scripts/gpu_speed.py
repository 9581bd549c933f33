#!/usr/bin/env python3
"""Tracking-call and whole-loop speed on this machine's default JAX device beside its CPU, and the
memory-bandwidth ceiling of one LM step (issue "Speed of the whole loop", GPU part).

    PYTHONPATH=. python3 scripts/gpu_speed.py --out OUT [--frames 12] [--width 640] [--height 480]

Runs itself twice in fresh processes (default device, then JAX_PLATFORMS=cpu; at once with
``--parallel K``, each on its own cores) on one generated strong-blur sequence and prints one
markdown table: per device, the median tracking call of n = 1 and n = 64 (the first, compiling, left
out), the start-up (a 3-frame run, compilation included) and the whole loop's seconds per frame of
``run_odometry`` for RGB-D n = 1 and n = 64 and monocular n = 64, plus the ceiling: the bytes one LM step of n = 64 must read (residual
pixels x n virtual frames x 4 bilinear texels x 4 bytes, summed over the pyramid's levels) over the
device's measured copy bandwidth.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import pathlib
import subprocess
import sys
import time


def _bandwidth_gb_s() -> float:
    """Device-to-device copy bandwidth (bytes read + written per second, GB/s) of a 1 GiB array."""
    import jax
    import jax.numpy as jnp

    x = jnp.ones((2**28,), jnp.float32)
    copy = jax.jit(lambda a: a + 1.0)
    copy(x).block_until_ready()
    t0 = time.perf_counter()
    for _ in range(10):
        x = copy(x)
    x.block_until_ready()
    return 2 * x.nbytes * 10 / (time.perf_counter() - t0) / 1e9


def _lm_step_bytes(config) -> int:
    """Bytes of keyframe texels one LM step reads: every level's residual pixels x its n x 4 x 4 B."""
    from mbavo_jax.tracking.points import PATTERN
    from mbavo_jax.tracking.tracker import _n_for_level

    total = 0
    for level in range(config.levels):
        n = _n_for_level(config, float("nan"), level)  # fixed n: the predicted blur is not read
        total += config.points[level] * len(PATTERN) * n * 4 * 4
    return total


def _log(msg: str) -> None:
    print(f"[{time.strftime('%H:%M:%S')}] {msg}", file=sys.stderr, flush=True)


def _tracking_calls(seq, base, frames: int) -> dict:
    """Median milliseconds of one tracking call (first pair, which compiles, left out) for n = 1 and n = 64."""
    import jax
    import numpy as np

    from mbavo_jax.bench.sequences import tracking_pairs
    from mbavo_jax.tracking import Keyframe, track

    row = {}
    for name, cfg in (("n1", dataclasses.replace(base, blur_aware=False)), ("n64", base)):
        ms = []
        for _, sharp, depth, frame, init, _gt in tracking_pairs(seq, frames):
            kf = jax.block_until_ready(Keyframe.create(sharp, depth, seq.camera, cfg))
            t0 = time.perf_counter()
            jax.block_until_ready(track(kf, frame.image, init, cfg))
            ms.append(1000 * (time.perf_counter() - t0))
        row[f"{name}_call_ms"] = float(np.median(ms[1:]))
        _log(f"{name} tracking call {row[f'{name}_call_ms']:.1f} ms (first, compiling: {ms[0]:.0f} ms)")
    return row


def _split(run: pathlib.Path, frames: int) -> dict:
    """Seconds per frame in tracking and in the monocular back-end (frames.csv), and frames tracked."""
    import csv

    with open(run / "frames.csv") as fh:
        rows = list(csv.DictReader(fh))
    total = lambda key: sum(float(r[key]) for r in rows if r.get(key) not in (None, "", "nan")) / 1000 / frames
    return {"track_s_per_frame": total("ms"), "backend_s_per_frame": total("backend_ms"),
            "tracked": sum(r["status"] in ("converged", "max_steps", "keyframe") for r in rows)}


def measure(data: pathlib.Path, out: pathlib.Path, frames: int, loops: str, calls: bool) -> dict:
    """Tracking calls, start-up and whole-loop seconds per frame for n = 1 and n = 64 on the default device."""
    import jax

    from mbavo_jax.bench.mono import trajectory_scores
    from mbavo_jax.config import EvalConfig, RunConfig, TrackerConfig, calibration_of
    from mbavo_jax.datasets import open_sequence
    from mbavo_jax.odometry import run_odometry

    seq = open_sequence(data)
    base = TrackerConfig(**calibration_of(seq.meta))
    row = {"device": str(jax.devices()[0]), **(_tracking_calls(seq, base, frames - 2) if calls else {})}
    for name, n in (("n1", dict(blur_aware=False)), ("n64", {}), ("mono_n64", {})):
        if name not in loops.split(","):
            continue
        mode = "mono" if name.startswith("mono") else "rgbd"
        cfg = RunConfig(tracker=dataclasses.replace(base, **n)).replace(odometry=dict(mode=mode))
        t0 = time.perf_counter()  # compiles: 3 frames; monocular, whole (its back-end starts later)
        run_odometry(seq, out / f"warm_{name}", cfg, max_frames=None if mode == "mono" else 3, progress=False)
        row[f"{name}_startup_s"] = time.perf_counter() - t0
        t0 = time.perf_counter()
        run_odometry(seq, out / name, cfg, progress=False)
        row[f"{name}_loop_s_per_frame"] = (time.perf_counter() - t0) / len(seq)
        row[f"{name}_ate_pct"] = trajectory_scores(seq, out / name, EvalConfig()).get("ate_pct", float("nan"))
        row.update({f"{name}_{k}": v for k, v in _split(out / name, len(seq)).items()})
        _log(f"{name} loop {row[f'{name}_loop_s_per_frame']:.3f} s/frame, ATE {row[f'{name}_ate_pct']:.2f} % of the path "
             f"(warm-up run {row[f'{name}_startup_s']:.1f} s)")
    row["bandwidth_gb_s"] = _bandwidth_gb_s()
    row["lm_step_mb"] = _lm_step_bytes(base) / 1e6
    row["ceiling_ms_per_lm_step"] = row["lm_step_mb"] / 1e3 / row["bandwidth_gb_s"] * 1e3
    return row


def _start_child(device: str, args, cores: list[int] | None) -> subprocess.Popen:
    """The measuring process of one device (``cores``: the CPU cores it may use, or all)."""
    env = {k: v for k, v in os.environ.items() if k != "JAX_PLATFORMS"} | {"PYTHONUNBUFFERED": "1"}
    if device == "cpu":
        env["JAX_PLATFORMS"] = "cpu"
    cmd = [sys.executable, __file__, "--out", str(args.out), "--frames", str(args.frames), "--child", device, "--loops", args.loops]
    cmd += [] if args.calls else ["--no-calls"]
    cmd += ["--cores", ",".join(map(str, cores))] if cores else []
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, text=True)  # progress on stderr passes through


def _row(device: str, proc: subprocess.Popen, cores: list[int] | None) -> dict:
    out, _ = proc.communicate()
    if proc.returncode != 0:
        return {"device": device, "error": f"exit {proc.returncode}"}
    return {**json.loads(out.strip().splitlines()[-1]), "cpu_cores": len(cores) if cores else os.cpu_count()}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=pathlib.Path, required=True)
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--parallel", type=int, default=0, metavar="K",
                   help="measure both devices at once: the default device's process on the first K cores, the CPU's on the rest")
    p.add_argument("--loops", default="n1,n64,mono_n64", help="whole loops to time (of n1, n64, mono_n64)")
    p.add_argument("--no-calls", dest="calls", action="store_false", help="skip the single tracking calls")
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    p.add_argument("--cores", default="", help=argparse.SUPPRESS)
    args = p.parse_args()
    if args.cores:  # before JAX starts its threads
        os.sched_setaffinity(0, [int(c) for c in args.cores.split(",")])
    data = args.out / "strong"
    if args.child:
        print(json.dumps(measure(data, args.out / args.child, args.frames, args.loops, args.calls)))
        return 0
    os.environ["JAX_PLATFORMS"] = "cpu"  # this process only generates: the GPU's memory stays for the child
    from mbavo_jax.config import PRESETS, SynthConfig
    from mbavo_jax.synthetic import generate_sequence

    generate_sequence(SynthConfig(**{**PRESETS["strong"], "frames": args.frames, "width": args.width, "height": args.height}), data,
                      progress=False)
    cores = sorted(os.sched_getaffinity(0))
    split = {"default": cores[:args.parallel], "cpu": cores[args.parallel:]} if args.parallel else {"default": None, "cpu": None}
    rows = []
    if args.parallel:
        procs = {d: _start_child(d, args, split[d]) for d in split}
        rows = [_row(d, procs[d], split[d]) for d in split]
    for device in () if args.parallel else split:
        rows.append(_row(device, _start_child(device, args, None), None))
        print(json.dumps(rows[-1]), flush=True)  # each device's row as soon as it is measured
    keys = ["device", "cpu_cores", "n64_track_s_per_frame", "mono_n64_track_s_per_frame", "mono_n64_backend_s_per_frame",
            "n64_tracked", "mono_n64_tracked", "n1_call_ms", "n64_call_ms", "n1_startup_s", "n64_startup_s", "n1_loop_s_per_frame", "n64_loop_s_per_frame",
            "mono_n64_startup_s", "mono_n64_loop_s_per_frame", "n1_ate_pct", "n64_ate_pct", "mono_n64_ate_pct", "bandwidth_gb_s", "lm_step_mb", "ceiling_ms_per_lm_step"]
    print("| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    for r in rows:
        cells = [r["device"], f"failed: {r['error']}"] if "error" in r else [r.get(k, "") for k in keys]
        print("| " + " | ".join(f"{c:.4g}" if isinstance(c, float) else str(c) for c in cells) + " |")
    (args.out / "gpu_speed.json").write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
