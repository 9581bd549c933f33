#!/usr/bin/env python3
"""The whole RGB-D loop with CG run to every iteration (``deblur.tolerance = 0``) against the default
tolerance, in turns in one process after a warm-up run of each (``bench_speed.timed_runs``), on the
odometry benchmark's generated sequences; ATE, keyframe PSNR and Open3D hybrid's seconds per frame
on the same frames. Used for "CG stopped at a tolerance" in docs/benchmarks.md.

    python scripts/deblur_tolerance_loop.py --presets strong,extreme --out /tmp/tol_loop
"""

import argparse
import json
import pathlib
import statistics

from mbavo_jax.bench import deblur_quality, run_peer
from mbavo_jax.bench_speed import timed_runs
from mbavo_jax.config import calibration_of, load_config
from mbavo_jax.datasets import open_sequence
from mbavo_jax.evaluation import evaluate_run


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--presets", default="strong,extreme")
    p.add_argument("--data", default="runs/bench_{}_640x480_seed0", help="sequence folder per preset ({} = the preset)")
    p.add_argument("--out", type=pathlib.Path, default=pathlib.Path("/tmp/tol_loop"))
    args = p.parse_args()
    for preset in args.presets.split(","):
        seq = open_sequence(args.data.format(preset))
        cfg = load_config(None, [], calibration_of(seq.meta))
        variants = {"all_iterations": cfg.replace(deblur=dict(tolerance=0.0)), "default": cfg}
        out = args.out / preset
        seconds = timed_runs(seq, out, variants, len(seq), 1)
        peer = run_peer(seq, out / "open3d", "open3d", cfg.evaluation, 3.0)
        for name in variants:
            run = out / name / "run1"
            row = dict(s_per_frame=statistics.median(seconds[name]) / len(seq),
                       ate_m=evaluate_run(run, seq.groundtruth, seq.timestamps, cfg.evaluation).get("ate_rmse_m"),
                       psnr=deblur_quality(seq, run).get("psnr_deblurred"), open3d_s_per_frame=peer.get("seconds_per_frame"))
            print(preset, name, json.dumps(row), flush=True)


if __name__ == "__main__":
    main()
