"""Scoring a run folder (``trajectory.txt``) against ground truth, for ``mbavo track`` and the benchmarks."""

from __future__ import annotations

import pathlib

import numpy as np

from ..config import EvalConfig
from ..errors import MbavoError
from ..io import read_tum_trajectory
from .metrics import aligned_positions, ape, frame_drop_rate

__all__ = ["evaluate_run", "RUN_PLOTS"]

RUN_PLOTS = ("trajectory.png", "ape_over_time.png")  # what ``evaluate_run(..., plots=True)`` writes


def evaluate_run(run, groundtruth, frame_stamps=None, config: EvalConfig = EvalConfig(), plots: bool = False) -> dict:
    """ATE of ``run/trajectory.txt`` against ``groundtruth`` (stamps, poses) after ``config.align``:
    ``ate_rmse_m``, ``ate_median_m`` and, given the sequence's ``frame_stamps``, ``frame_drop_rate``.
    Empty without ground truth or trajectory, or with fewer than 3 matched poses (a lost run, or a
    monocular one that never initialised).
    ``plots``: also write ``trajectory.png`` and ``ape_over_time.png`` into the run folder."""
    run = pathlib.Path(run)
    if groundtruth is None or not (run / "trajectory.txt").is_file():
        return {}
    try:
        t_est, p_est = read_tum_trajectory(run / "trajectory.txt")
    except MbavoError:  # no pose at all (a monocular run that never initialised)
        return {}
    t_gt, p_gt = groundtruth
    if len(t_est) < 3:
        return {}
    try:
        res = ape(t_gt, p_gt, t_est, p_est, align=config.align, max_diff=config.t_max_diff)
    except MbavoError:
        return {}
    out = {"ate_rmse_m": res["rmse"], "ate_median_m": res["median"]}
    if frame_stamps is not None:
        out["frame_drop_rate"] = frame_drop_rate(frame_stamps, t_est, config.t_max_diff)
    if plots:
        from . import plots as plot

        i_est, _, ref_xyz, est_xyz = aligned_positions(t_gt, p_gt, t_est, p_est, config.align, config.t_max_diff)
        plot.plot_trajectories(run / RUN_PLOTS[0], ref_xyz, est_xyz, f"ATE rmse {res['rmse']:.4f} m ({config.align.upper()})")
        plot.plot_error_over_time(run / RUN_PLOTS[1], t_est[i_est], np.asarray(res["errors"]), "APE over time")
    return out
