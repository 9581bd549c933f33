#!/usr/bin/env python3
"""Keyframe deblurring, solver against solver: seconds per keyframe, PSNR/SSIM against the sharp
ground truth and memory, on frames of generated sequences (``mbavo synth``) with their true exposure
paths (exposure.txt) and depth.

Each variant is a set of ``deblur`` settings over the defaults; the first is the baseline of the
ratios. Per frame: one warm-up call per variant (compilation), then ``--repeats`` rounds that
alternate the variants in one process (timings drift on a shared CPU; ratios drift less), and the
median. ``--memory`` also runs each variant once in a fresh process and reports its peak RSS.
Used for the deblurring section of docs/benchmarks.md. Example:

    mbavo synth --preset strong --frames 6 --width 640 --height 480 --out /tmp/ds_strong
    python scripts/deblur_speed.py /tmp/ds_strong --frames 3 \\
        --variant today:solver=render --variant table:solver=table --variant table20:iterations=20
"""

import argparse
import dataclasses
import json
import pathlib
import statistics
import subprocess
import sys
import time

import jax.numpy as jnp
import numpy as np

from mbavo_jax.config import DeblurConfig, EvalConfig
from mbavo_jax.datasets import open_sequence
from mbavo_jax.deblur import choose_deblur_n, deblur, psnr, ssim
from mbavo_jax.evaluation import associate
from mbavo_jax.geometry import ExposureTrajectory, Pose
from mbavo_jax.geometry.trajectory import readout_fraction
from mbavo_jax.io import read_image_gray


def parse_variant(text: str) -> tuple[str, dict]:
    """``label:key=value,key=value`` -> (label, DeblurConfig overrides typed as the fields are)."""
    label, _, rest = text.partition(":")
    fields = {f.name: f.type for f in dataclasses.fields(DeblurConfig)}
    sets = {}
    for item in filter(None, rest.split(",")):
        key, _, value = item.partition("=")
        if key not in fields:
            raise SystemExit(f"deblur_speed: error: unknown deblur setting {key!r} (one of {', '.join(fields)})")
        sets[key] = type(getattr(DeblurConfig(), key))(value)
    return label, sets


def load_frame(path: str, index: int) -> dict:
    """A frame of a generated sequence: image, depth, camera, true exposure path, response gamma,
    readout fraction and the sharp ground truth."""
    seq = open_sequence(path)
    frame = seq[index]
    stamps, starts, ends = seq.exposure_paths
    _, match = associate(np.array([frame.timestamp]), stamps, EvalConfig().t_max_diff)
    j = int(match[0])
    pose = lambda v: Pose.from_vector(jnp.asarray(v, jnp.float32))
    source = pathlib.Path(frame.path)
    exposure_s = float(seq.meta.get("exposure_ms", 0.0)) / 1000.0
    return dict(image=frame.image, depth=frame.depth, camera=seq.camera, path=ExposureTrajectory(pose(starts[j]), pose(ends[j])),
                gamma=float(seq.meta.get("response_gamma", 1.0)), readout=readout_fraction(seq.readout_s, exposure_s),
                sharp=read_image_gray(source.parent.parent / "sharp" / source.name))


def run_once(frame: dict, config: DeblurConfig) -> tuple[float, np.ndarray]:
    """(seconds, deblurred image) of one ``deblur`` call."""
    t = time.perf_counter()
    out = deblur(frame["image"], frame["depth"], frame["camera"], frame["path"], config, frame["gamma"], frame["readout"])
    return time.perf_counter() - t, out


def table_mb(frame: dict, config: DeblurConfig) -> float:
    """Megabytes of the table solver's sampling table (int32 cell + 2 x uint16 position per sample)."""
    if config.solver != "table":
        return 0.0
    return 8 * frame["image"].size * config.n / 1e6


def peak_rss_mb(sequence: str, index: int, sets: dict) -> float:
    """Peak RSS (MB) of a fresh process that loads the frame and deblurs it once with ``sets``."""
    child = [sys.executable, __file__, sequence, "--child", json.dumps({"frame": index, "sets": sets})]
    return float(subprocess.run(child, check=True, capture_output=True, text=True).stdout.split()[-1])


def measure_frame(sequence: str, index: int, variants: list[tuple[str, dict]], repeats: int, memory: bool) -> list[dict]:
    """One row per variant for frame ``index``: median seconds, ratio to the first, PSNR, SSIM, MB."""
    frame = load_frame(sequence, index)
    n = choose_deblur_n(frame["depth"], frame["camera"], frame["path"], DeblurConfig(), frame["readout"])
    configs = [dataclasses.replace(DeblurConfig(), n=n, **sets) for _, sets in variants]
    rows = []
    for (label, sets), config in zip(variants, configs):
        first, out = run_once(frame, config)
        rows.append(dict(sequence=sequence, frame=index, n=n, readout=round(frame["readout"], 3), variant=label, settings=sets,
                         first_s=first, times=[], psnr=psnr(out, frame["sharp"]), ssim=ssim(out, frame["sharp"]),
                         psnr_blurry=psnr(frame["image"], frame["sharp"]), table_mb=table_mb(frame, config)))
    for _ in range(repeats):
        for row, config in zip(rows, configs):
            row["times"].append(run_once(frame, config)[0])
    for row in rows:
        row["seconds"] = statistics.median(row["times"])
        row["speedup"] = rows[0]["seconds"] / row["seconds"]
        row["psnr_change"] = row["psnr"] - rows[0]["psnr"]
        if memory:
            row["peak_rss_mb"] = peak_rss_mb(sequence, index, {**row["settings"], "n": n})
    return rows


def markdown(rows: list[dict]) -> str:
    """The rows as a markdown table."""
    head = ("| sequence | frame | n | variant | s / keyframe (median) | speed-up | PSNR dB (blurry) | ΔPSNR | SSIM | table MB | peak RSS MB |\n"
            "|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [f"| {pathlib.Path(r['sequence']).name} | {r['frame']} | {r['n']} | {r['variant']} | {r['seconds']:.2f} | {r['speedup']:.1f}x | "
             f"{r['psnr']:.2f} ({r['psnr_blurry']:.2f}) | {r['psnr_change']:+.2f} | {r['ssim']:.4f} | {r['table_mb']:.0f} | "
             f"{r.get('peak_rss_mb', float('nan')):.0f} |" for r in rows]
    return "\n".join([head, *lines])


def child(sequence: str, spec: str) -> int:
    """``--memory``'s worker: one deblur call, then its peak RSS in MB (VmHWM: ru_maxrss would carry
    the parent's peak over the exec)."""
    spec = json.loads(spec)
    run_once(load_frame(sequence, spec["frame"]), dataclasses.replace(DeblurConfig(), **spec["sets"]))
    status = pathlib.Path("/proc/self/status").read_text().splitlines()
    print(next(int(line.split()[1]) for line in status if line.startswith("VmHWM:")) / 1024)
    return 0


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("sequences", nargs="+", help="generated sequences (mbavo synth output folders)")
    ap.add_argument("--frames", type=int, nargs="+", default=[3], help="frame indices to deblur (default 3)")
    ap.add_argument("--variant", action="append", default=None,
                    help="label:key=value,... deblur settings over the defaults (repeatable; the first is the baseline)")
    ap.add_argument("--repeats", type=int, default=3, help="timed rounds after the warm-up (default 3)")
    ap.add_argument("--memory", action="store_true", help="also the peak RSS of each variant in a fresh process")
    ap.add_argument("--json", default=None, help="write the rows to this file too")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.child:
        return child(args.sequences[0], args.child)
    variants = [parse_variant(v) for v in (args.variant or ["today:solver=render", "table:solver=table"])]
    rows = []
    for sequence in args.sequences:
        for index in args.frames:
            rows += measure_frame(sequence, index, variants, args.repeats, args.memory)
            print(markdown(rows[-len(variants):]), flush=True)
    if args.json:
        pathlib.Path(args.json).write_text(json.dumps(rows, indent=1))
    print(markdown(rows))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
