#!/usr/bin/env python3
"""Tracking-call and whole-loop speed on this machine's default JAX device beside its CPU, and the
memory-bandwidth ceiling of one LM step (issue "Speed of the whole loop", GPU part).

    PYTHONPATH=. python3 scripts/gpu_speed.py --out OUT [--frames 12] [--width 640] [--height 480]

Runs itself twice in fresh processes (default device, then JAX_PLATFORMS=cpu) on one generated
strong-blur sequence and prints one markdown table: per device, the median tracking call of n = 1
and n = 64 (``bench.run_tracking_benchmark``, no peers) and the whole loop's seconds per frame of
``mbavo track`` with each n, plus the ceiling: the bytes one LM step of n = 64 must read (residual
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

    total = 0
    for level in range(config.levels):
        n = config.n if config.n_per_level == "same" else max(config.n_coarse_min, config.n >> level)
        total += config.points[level] * len(PATTERN) * n * 4 * 4
    return total


def measure(data: pathlib.Path, out: pathlib.Path, frames: int) -> dict:
    """Tracking calls and whole-loop seconds per frame for n = 1 and n = 64 on the default device."""
    import jax

    from mbavo_jax.bench import run_tracking_benchmark
    from mbavo_jax.config import RunConfig, TrackerConfig, calibration_of
    from mbavo_jax.datasets import open_sequence
    from mbavo_jax.odometry import run_odometry

    seq = open_sequence(data)
    track = run_tracking_benchmark(data, frames=frames - 2, peers=False, progress=False)
    row = {"device": str(jax.devices()[0]), "n1_call_ms": track["n1_ms"], "n64_call_ms": track["n64_analytic_ms"]}
    base = TrackerConfig(**calibration_of(seq.meta))
    for name, n in (("n1", dict(blur_aware=False)), ("n64", {})):
        cfg = RunConfig(tracker=dataclasses.replace(base, **n))
        run_odometry(seq, out / f"warm_{name}", cfg, max_frames=3, progress=False)  # compile first
        t0 = time.perf_counter()
        run_odometry(seq, out / name, cfg, progress=False)
        row[f"{name}_loop_s_per_frame"] = (time.perf_counter() - t0) / len(seq)
    row["bandwidth_gb_s"] = _bandwidth_gb_s()
    row["lm_step_mb"] = _lm_step_bytes(base) / 1e6
    row["ceiling_ms_per_lm_step"] = row["lm_step_mb"] / 1e3 / row["bandwidth_gb_s"] * 1e3
    return row


def _child(device: str, args) -> dict:
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    if device == "cpu":
        env["JAX_PLATFORMS"] = "cpu"
    cmd = [sys.executable, __file__, "--out", str(args.out), "--frames", str(args.frames), "--child", device]
    done = subprocess.run(cmd, env=env, capture_output=True, text=True)
    if done.returncode != 0:
        return {"device": device, "error": done.stderr.strip().splitlines()[-1:]}
    return json.loads(done.stdout.strip().splitlines()[-1])


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=pathlib.Path, required=True)
    p.add_argument("--frames", type=int, default=12)
    p.add_argument("--width", type=int, default=640)
    p.add_argument("--height", type=int, default=480)
    p.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = p.parse_args()
    data = args.out / "strong"
    if args.child:
        print(json.dumps(measure(data, args.out / args.child, args.frames)))
        return 0
    from mbavo_jax.config import PRESETS, SynthConfig
    from mbavo_jax.synthetic import generate_sequence

    generate_sequence(SynthConfig(**{**PRESETS["strong"], "frames": args.frames, "width": args.width, "height": args.height}), data,
                      progress=False)
    rows = []
    for device in ("default", "cpu"):
        rows.append(_child(device, args))
        print(json.dumps(rows[-1]), flush=True)  # each device's row as soon as it is measured
    keys = ["device", "n1_call_ms", "n64_call_ms", "n1_loop_s_per_frame", "n64_loop_s_per_frame", "bandwidth_gb_s", "lm_step_mb",
            "ceiling_ms_per_lm_step"]
    print("| " + " | ".join(keys) + " |\n|" + "---|" * len(keys))
    for r in rows:
        cells = [r["device"], f"failed: {r['error']}"] if "error" in r else [r.get(k, "") for k in keys]
        print("| " + " | ".join(f"{c:.4g}" if isinstance(c, float) else str(c) for c in cells) + " |")
    (args.out / "gpu_speed.json").write_text(json.dumps(rows, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
