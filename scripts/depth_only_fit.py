#!/usr/bin/env python3
"""The depth term alone, per pyramid level: how far its optimum lies from the ground truth.

Builds the depth term (``tracking.geometric``) of keyframe ``--kf`` against frame ``--frame`` of a
generated sequence at the true relative mid-exposure pose and minimises it alone by Gauss-Newton
with Huber weights (IRLS, 15 steps), at every level of the tracker's depth pyramid. A well-posed
term stays at the truth; the printed offset is how far depth alone pulls the pose. Used for the
``depth_levels`` finding in docs/benchmarks.md. Example:

    python scripts/depth_only_fit.py runs/bench_mild_640x480_seed0 --kf 0 --frame 10
"""

import argparse

import jax
import jax.numpy as jnp
import numpy as np

from mbavo_jax.config import TrackerConfig, calibration_of
from mbavo_jax.datasets import open_sequence
from mbavo_jax.geometry.pose import Pose
from mbavo_jax.tracking.geometric import depth_residuals, select_depth_points
from mbavo_jax.tracking.points import downsample_depth


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sequence")
    ap.add_argument("--kf", type=int, default=0)
    ap.add_argument("--frame", type=int, default=10)
    ap.add_argument("--levels", type=int, default=4)
    args = ap.parse_args()
    seq = open_sequence(args.sequence)
    cfg = TrackerConfig(**calibration_of(seq.meta))
    ts, P = seq.groundtruth

    def T(i):
        return Pose.from_vector(jnp.asarray(P[int(np.argmin(np.abs(ts - seq.timestamps[i])))], jnp.float32))

    mid = T(args.kf).inverse().compose(T(args.frame))
    d0, dk = seq[args.kf].depth, seq[args.frame].depth
    print(f"{'level':>5} {'size':>9} {'points':>6}  at the truth: beyond Huber (beyond depth_outlier, dropped)  offset of the depth-only optimum")
    for level in range(args.levels):
        if level:
            d0, dk = downsample_depth(d0), downsample_depth(dk)
        cam = seq.camera.scaled(level)
        pts = select_depth_points(np.nan_to_num(d0, nan=0.0), max(2, cfg.depth_stride >> level), cfg.depth_edge)
        D = jnp.asarray(np.nan_to_num(dk, nan=0.0))
        args_r = (cam, D, jnp.asarray(pts.pixels), jnp.asarray(pts.depths), jnp.asarray(pts.valid), cfg.depth_edge, tuple(cfg.depth_sigma))
        r_all, ok_all = (np.asarray(x) for x in depth_residuals(mid, *args_r))
        beyond = int((ok_all & (np.abs(r_all) > cfg.depth_huber)).sum())
        dropped = int((ok_all & (np.abs(r_all) >= cfg.depth_outlier)).sum())
        f = jax.jit(lambda d: depth_residuals(mid.plus(d), *args_r, cfg.depth_outlier))
        jac = jax.jit(jax.jacfwd(lambda d: f(d)[0]))
        d = np.zeros(6, np.float32)
        for _ in range(15):
            r, ok = (np.asarray(x) for x in f(jnp.asarray(d)))
            J = np.asarray(jac(jnp.asarray(d)))
            a = np.abs(r)
            w = np.where(a <= cfg.depth_huber, 1.0, cfg.depth_huber / np.maximum(a, 1e-9)) * ok
            d = d - np.linalg.solve(J.T @ (w[:, None] * J), J.T @ (w * r))
        print(f"{level:>5} {cam.width:>4}x{cam.height:<4} {int(ok.sum()):>6}  {beyond:>18} ({dropped:>4}){'':>24}translation {1000 * np.linalg.norm(d[3:]):7.2f} mm"
              f"  rotation {np.degrees(np.linalg.norm(d[:3])):.3f} deg")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
