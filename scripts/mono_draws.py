#!/usr/bin/env python3
"""The monocular ATE over draws on any sequence folders: ``mbavo bench mono --draws K`` (each method run
K times per sequence, at K Huber thresholds a part in a thousand apart, ``config.HUBER_DRAWS``) on the
folders given instead of the bench's generated presets and clips.

A monocular run either holds its scale or loses it, and which it does can turn on a rounding-sized
change (docs/benchmarks.md, the section that ends "... and the monocular goals over draws"), so one run
per sequence decides a ratio between methods only when it is far from the goal. Prints the bench's two
tables: every run (with its mean over the draws) and, over all the folders, each method's mean and its
ratio to mono_n1's. Example (sequences made by ``mbavo synth ... --no-exposure-info``):

    python scripts/mono_draws.py runs/bench_strong_640x480_seed{0,1,2}_noexp --methods mono_n64,mono_n1 \\
        --draws 4 --out /tmp/draws
"""

import argparse
import pathlib

from mbavo_jax.bench.mono import MONO_METHODS, format_mono_table, format_seed_table, run_mono_benchmark
from mbavo_jax.config import HUBER_DRAWS


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequences", nargs="+")
    ap.add_argument("--methods", default="mono_n64,mono_n1", help=f"comma-separated, of {', '.join(MONO_METHODS)}")
    ap.add_argument("--draws", type=int, default=4, choices=range(1, len(HUBER_DRAWS) + 1), help="runs per method and sequence")
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    seqs = {pathlib.Path(s).name: pathlib.Path(s) for s in args.sequences}
    results = run_mono_benchmark(seqs, args.out, args.methods.split(","), draws=args.draws)
    print(format_mono_table(results) + "\n\n" + format_seed_table(results, {"all": list(seqs)}))


if __name__ == "__main__":
    main()
