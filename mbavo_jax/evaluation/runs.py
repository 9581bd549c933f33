"""Scoring a run folder (``trajectory.txt``) against ground truth, for ``mbavo track`` and the benchmarks."""

from __future__ import annotations

import csv
import pathlib

import numpy as np

from ..config import EvalConfig
from ..errors import MbavoError
from ..io import read_tum_trajectory
from .metrics import aligned_positions, ape, frame_drop_rate

__all__ = ["evaluate_run", "run_alignment", "is_monocular_run", "RUN_PLOTS", "ALIGNMENT_NAMES"]

RUN_PLOTS = ("trajectory.png", "ape_over_time.png")  # what ``evaluate_run(..., plots=True)`` writes
ALIGNMENT_NAMES = {"none": "no alignment", "se3": "SE(3) alignment", "sim3": "Sim(3) alignment"}
MONO_WAITING = "initialising"  # frames.csv status of a frame the monocular system waited on (the RGB-D loop has none)


def is_monocular_run(run) -> bool:
    """Whether the run folder ``run`` holds a monocular run: its frames.csv has a frame the
    monocular system waited to initialise on (its first frame always is one)."""
    try:
        with open(pathlib.Path(run) / "frames.csv", newline="", encoding="utf-8", errors="replace") as fh:
            return any(row.get("status") == MONO_WAITING for row in csv.DictReader(fh))
    except OSError:
        return False


def run_alignment(config: EvalConfig, monocular: bool) -> str:
    """The alignment a run is scored after: Sim(3) for a monocular run (its trajectory has no
    metric scale, so a rigid fit would score the scale), else ``config.align``."""
    return "sim3" if monocular else config.align


def evaluate_run(run, groundtruth, frame_stamps=None, config: EvalConfig = EvalConfig(), plots: bool = False,
                 monocular: bool | None = None) -> dict:
    """ATE of ``run/trajectory.txt`` against ``groundtruth`` (stamps, poses) after
    :func:`run_alignment` (``ate_alignment``: Sim(3) for a monocular run, else ``config.align``):
    ``ate_rmse_m``, ``ate_median_m``, with Sim(3) ``ate_scale`` (the fitted scale) and, given the
    sequence's ``frame_stamps``, ``frame_drop_rate``.
    ``monocular``: whether the run is monocular (None: :func:`is_monocular_run` tells from the folder).
    Empty without ground truth or trajectory, or with fewer than 3 matched poses (a lost run, or a
    monocular one that never initialised).
    ``plots``: also write ``trajectory.png`` and ``ape_over_time.png`` into the run folder, their
    titles naming the alignment."""
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
    align = run_alignment(config, is_monocular_run(run) if monocular is None else monocular)
    try:
        res = ape(t_gt, p_gt, t_est, p_est, align=align, max_diff=config.t_max_diff)
    except MbavoError:
        return {}
    out = {"ate_rmse_m": res["rmse"], "ate_median_m": res["median"], "ate_alignment": align,
           **({"ate_scale": res["scale"]} if align == "sim3" else {})}
    if frame_stamps is not None:
        out["frame_drop_rate"] = frame_drop_rate(frame_stamps, t_est, config.t_max_diff)
    if plots:
        _plot_run(run, (t_gt, p_gt), (t_est, p_est), res, align, config.t_max_diff)
    return out


def _plot_run(run: pathlib.Path, groundtruth, estimate, res: dict, align: str, max_diff: float) -> None:
    """trajectory.png and ape_over_time.png of a scored run, their titles naming ``align``."""
    from . import plots as plot

    i_est, _, ref_xyz, est_xyz = aligned_positions(*groundtruth, *estimate, align, max_diff)
    name = ALIGNMENT_NAMES[align] + (f", scale {res['scale']:.4g}" if align == "sim3" else "")
    plot.plot_trajectories(run / RUN_PLOTS[0], ref_xyz, est_xyz, f"ATE rmse {res['rmse']:.4f} m ({name})")
    plot.plot_error_over_time(run / RUN_PLOTS[1], estimate[0][i_est], np.asarray(res["errors"]), f"APE over time ({name})")
