#!/usr/bin/env python3
"""Track one frame of a generated sequence against the sharp frame of another, from the true
exposure path moved by a fixed 2-3 mm / 0.1-0.2 deg, once per tracker setting; prints the mid,
start and end position errors and the per-level LM steps (c = converged, x = step budget) and RMS.
A controlled look at one tracking call, without the odometry loop. Each ``--set`` is one run
(comma-separated TrackerConfig fields; tuples as a:b). Example (docs/benchmarks.md, depth term):

    python scripts/track_frame_pair.py runs/bench_mild_640x480_seed0 --kf 0 --frame 10 \\
        --set depth_weight=0.03,depth_outlier=1e9,depth_levels=4 --set depth_weight=0.03
"""

import argparse

import jax.numpy as jnp
import numpy as np

from mbavo_jax.config import calibration_of, load_config
from mbavo_jax.datasets import open_sequence
from mbavo_jax.geometry.pose import Pose
from mbavo_jax.geometry.trajectory import ExposureTrajectory
from mbavo_jax.io import read_image_gray
from mbavo_jax.tracking import Keyframe, track

PERTURBATION = np.array([0.002, -0.001, 0.001, 0.003, -0.002, 0.002], np.float32)  # [rad x3, m x3]


def tracker_config(spec: str, seq):
    """One run's tracker settings: comma-separated key=value (tuples as a:b) over the sequence's calibration."""
    overrides = []
    for item in filter(None, spec.split(",")):
        key, value = item.split("=", 1)
        overrides.append(f"tracker.{key}=" + (f"[{value.replace(':', ',')}]" if ":" in value else value))
    return load_config(overrides=overrides, calibration=calibration_of(seq.meta)).tracker


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sequence")
    ap.add_argument("--kf", type=int, default=0)
    ap.add_argument("--frame", type=int, default=10)
    ap.add_argument("--set", action="append", default=[], help="one tracker setting per run, e.g. depth_weight=0.03,depth_levels=2")
    args = ap.parse_args()
    seq = open_sequence(args.sequence)
    stamps, S, E = seq.exposure_paths
    ts, P = seq.groundtruth

    def pose(v):
        return Pose.from_vector(jnp.asarray(v, jnp.float32))

    T_kf = pose(P[int(np.argmin(np.abs(ts - seq.timestamps[args.kf])))])
    i = int(np.argmin(np.abs(stamps - seq.timestamps[args.frame])))
    gt = ExposureTrajectory(T_kf.inverse().compose(pose(S[i])), T_kf.inverse().compose(pose(E[i])))
    init = ExposureTrajectory(gt.start.plus(jnp.asarray(PERTURBATION)), gt.end.plus(jnp.asarray(PERTURBATION)))
    sharp = read_image_gray(seq[args.kf].path.replace("/rgb/", "/sharp/"))
    frame = seq[args.frame]

    def err(a, b):
        return 1000 * float(jnp.linalg.norm(a.t - b.t))

    for spec in args.set or [""]:
        cfg = tracker_config(spec, seq)
        kf = Keyframe.create(sharp, seq[args.kf].depth, seq.camera, cfg)
        traj, status, diag = track(kf, frame.image, init, cfg, depth=frame.depth)
        levels = " ".join(f"L{p['level']}:{p['steps']}{'c' if p['converged'] else 'x'}:{p['rms']:.3f}" for p in diag["levels"])
        print(f"{spec or '(defaults)':<50} {status.name:<10} mid {err(traj.middle(), gt.middle()):6.2f} mm  start {err(traj.start, gt.start):6.2f}"
              f"  end {err(traj.end, gt.end):6.2f}  {levels}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
