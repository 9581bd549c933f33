#!/usr/bin/env python3
"""How far a whole-loop ATE moves when nothing material changes: the RGB-D loop of each variant run
once per draw, each draw a Huber threshold a few parts in a thousand off the default 9/255.

The threshold is the draw because it changes every robust weight by a rounding-sized amount and
nothing else: the tracked paths move by thousandths of a pixel, and what the ATE does then is the
noise floor of a one-sequence comparison. Prints each run's ATE and, per variant, the mean, the
smallest and the largest. Used for "The extreme ATE clause against its noise floor" in
docs/benchmarks.md. Example (a sequence ``mbavo bench speed`` generated):

    python scripts/ate_draws.py runs/bench_extreme_640x480_seed0 --frames 40 --out /tmp/draws \\
        --variant "chord=tracker.fresh_jacobian_levels=1" --variant "per-step=tracker.fresh_jacobian_levels=4"
"""

import argparse
import pathlib

import numpy as np

from mbavo_jax.methods import ate_rmse
from mbavo_jax.config import HUBER_DRAWS, calibration_of, load_config
from mbavo_jax.datasets import open_sequence
from mbavo_jax.odometry import run_odometry


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--out", required=True)
    ap.add_argument("--variant", action="append", default=[],
                    help="NAME=section.key=value;section.key=value (repeatable; none: the defaults alone)")
    ap.add_argument("--draws", default=",".join(str(h) for h in HUBER_DRAWS), help="Huber thresholds, comma-separated")
    args = ap.parse_args()
    seq = open_sequence(args.sequence)
    variants = dict(v.split("=", 1) for v in args.variant) or {"default": ""}
    for name, sets in variants.items():
        ates = []
        for h in (float(x) for x in args.draws.split(",")):
            config = load_config(None, [*filter(None, sets.split(";")), f"tracker.huber={h!r}"], calibration_of(seq.meta))
            run = pathlib.Path(args.out) / name / f"huber{h:.7f}"
            run_odometry(seq, run, config, max_frames=args.frames, progress=False)
            ates.append(1000 * ate_rmse(seq, run, config.evaluation))
            print(f"{name} huber {h:.7f}: ATE {ates[-1]:.2f} mm", flush=True)
        print(f"{name}: mean {np.mean(ates):.2f} mm, {min(ates):.2f}-{max(ates):.2f} over {len(ates)} draws", flush=True)


if __name__ == "__main__":
    main()
