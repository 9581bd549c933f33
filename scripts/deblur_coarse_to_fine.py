#!/usr/bin/env python3
"""Coarse-to-fine keyframe deblurring on single frames of a generated sequence (true exposure path
and depth): ``deblur.deblur`` at full resolution only (``coarse_to_fine=False``) against coarse to
fine with 4, 6, 8 and 10 full-resolution steps; PSNR against sharp/ inside a 5 % border and seconds
of one warm call each. Used for "Coarse to fine in the loop" in docs/benchmarks.md.

    python scripts/deblur_coarse_to_fine.py runs/bench_strong_640x480_seed0 runs/bench_extreme_640x480_seed0
"""
import pathlib
import sys
import time

import jax.numpy as jnp
import numpy as np

from mbavo_jax.config import DeblurConfig
from mbavo_jax.datasets import open_sequence
from mbavo_jax.deblur import choose_deblur_n, deblur, psnr
from mbavo_jax.geometry import ExposureTrajectory, Pose
from mbavo_jax.io import read_image_gray

CONFIGS = {"full": DeblurConfig(coarse_to_fine=False), **{f"c2f+{k}": DeblurConfig(fine_iterations=k) for k in (4, 6, 8, 10)}}

for path in sys.argv[1:]:
    seq = open_sequence(path)
    stamps, starts, ends = seq.exposure_paths
    gamma = float(seq.meta.get("response_gamma", 1.0))
    pose = lambda v: Pose.from_vector(jnp.asarray(v, jnp.float32))
    for k in (3, 12, 25):
        f = seq[k]
        j = int(np.argmin(abs(stamps - f.timestamp)))
        traj = ExposureTrajectory(pose(starts[j]), pose(ends[j]))
        sharp = read_image_gray(pathlib.Path(f.path).parent.parent / "sharp" / pathlib.Path(f.path).name)
        h, w = sharp.shape
        inner = np.zeros(sharp.shape, bool)
        inner[h // 20 : -h // 20, w // 20 : -w // 20] = True
        row = [f"{pathlib.Path(path).name} #{k} n{choose_deblur_n(f.depth, seq.camera, traj)} blurry {psnr(f.image, sharp, inner):.2f}"]
        for name, cfg in CONFIGS.items():
            deblur(f.image, f.depth, seq.camera, traj, cfg, gamma)  # compile
            t0 = time.perf_counter()
            x = deblur(f.image, f.depth, seq.camera, traj, cfg, gamma)
            row.append(f"{name} {psnr(x, sharp, inner):.2f} {time.perf_counter() - t0:.2f}s")
        print(" | ".join(row), flush=True)
