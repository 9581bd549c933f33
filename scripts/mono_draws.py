#!/usr/bin/env python3
"""The monocular ATE over draws: each method of ``mbavo bench mono`` run on each sequence once per
draw, each draw a tracker Huber threshold at most a part in a thousand off the default 9/255.

A monocular run either holds its scale or loses it, and which it does can turn on a rounding-sized
change (docs/benchmarks.md, the section that ends "... and the monocular goals over draws"), so one run
per sequence decides a ratio between methods only when it is far from the goal. The threshold is the
draw for the reason ``scripts/ate_draws.py`` gives. Runs are scored as the benchmark scores them
(Sim(3), % of the path). Prints every run, then per method each sequence's mean over the draws, the mean
over the sequences and its ratio to mono_n1's. Example (sequences made by ``mbavo synth ... --no-exposure-info``):

    python scripts/mono_draws.py runs/bench_strong_640x480_seed{0,1,2}_noexp --methods mono_n64,mono_n1 \\
        --out /tmp/draws
"""

import argparse
import pathlib

import numpy as np

from ate_draws import DRAWS  # the RGB-D loop's draws (the script beside this one), the default first
from mbavo_jax.bench_mono import MONO_METHODS, mono_configs, trajectory_scores
from mbavo_jax.config import TrackerConfig, calibration_of
from mbavo_jax.datasets import open_sequence
from mbavo_jax.odometry import run_odometry


def run_draws(sequence: str, methods: list[str], draws: list[float], out: pathlib.Path) -> dict[str, list[float]]:
    """ATE (% of the path; NaN when not scored) of each method on ``sequence`` at each draw."""
    seq = open_sequence(sequence)
    configs = mono_configs(TrackerConfig(**calibration_of(seq.meta)), methods)
    ates: dict[str, list[float]] = {}
    for method, config in configs.items():
        for h in draws:
            run = out / pathlib.Path(sequence).name / method / f"huber{h:.7f}"
            cfg = config.replace(tracker=dict(huber=h))
            summary = run_odometry(seq, run, cfg, progress=False)
            ates.setdefault(method, []).append(trajectory_scores(seq, run, cfg.evaluation).get("ate_pct", float("nan")))
            print(f"{pathlib.Path(sequence).name} {method} huber {h:.7f}: ATE {ates[method][-1]:.3f} % "
                  f"({summary['dropped']} dropped)", flush=True)
    return ates


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", nargs="+")
    ap.add_argument("--methods", default="mono_n64,mono_n1", help=f"comma-separated, of {', '.join(MONO_METHODS[:3])}")
    ap.add_argument("--draws", default=",".join(str(h) for h in DRAWS[:4]), help="Huber thresholds, comma-separated")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    methods = args.methods.split(",")
    draws = [float(x) for x in args.draws.split(",")]
    means: dict[str, list[float]] = {}
    for sequence in args.sequences:
        for method, ates in run_draws(sequence, methods, draws, pathlib.Path(args.out)).items():
            means.setdefault(method, []).append(float(np.nanmean(ates)))
            print(f"{pathlib.Path(sequence).name} {method}: mean {means[method][-1]:.3f} % over {len(ates)} draws "
                  f"({np.nanmin(ates):.3f}-{np.nanmax(ates):.3f})", flush=True)
    for method, m in means.items():
        ratio = f", against mono_n1's {np.mean(m) / np.mean(means['mono_n1']):.2f}" if "mono_n1" in means else ""
        print(f"{method}: mean over sequences {np.mean(m):.3f} %{ratio}", flush=True)


if __name__ == "__main__":
    main()
