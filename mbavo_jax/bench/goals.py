"""The goals of ``mbavo bench odometry`` as columns (issue 57: mild blur must never cost accuracy):
per sequence, each goal that applies at its blur, its measured ratio and whether it is met, computed
from the benchmark's results (``odometry.nested_results``), never written in.

* n64 / n1: ``ours_n64``'s ATE over ``ours_n1``'s; at most 1.05 where the mean blur is at most 5 px
  (with or without exposure metadata), at most 0.55 at 10-40 px without metadata;
* depth / Open3D: ``ours_n64_depth``'s ATE over Open3D hybrid's (``open3d``); at most 1 at up to
  5 px, at most 0.7 at 10-40 px;
* path / true: ``ours_n64``'s estimated exposure-path length over the true one (median over
  frames); within 20 % where the blur is at least 3 px;
* sharp: n64 / n1 within 10 % on sharp sequences (mean blur under ``odometry.sharp_blur_px``).

JAX-free: the table and its tests need only the results.
"""

from __future__ import annotations

import dataclasses
import math

from ..config import OdometryConfig

__all__ = ["OdometryGoals", "GOALS", "GOAL_COLUMNS", "ate_of", "ratio_goal", "depth_goal", "path_goal", "sharp_goal", "check",
           "has_metadata", "sequence_goals", "with_goals", "format_goals_table"]


@dataclasses.dataclass(frozen=True)
class OdometryGoals:
    """The bounds (issue 57 and the RGB-D issue's sharp-frame goal). Blur: the sequence's mean over
    frames (px at its own size, ``synth.yaml``'s ``mean_blur_px``)."""

    mild_px: float = 5.0  # up to this: "mild"
    mild_ratio: float = 1.05  # n64 / n1 at most
    mild_depth_ratio: float = 1.0  # ours_n64_depth / open3d at most
    strong_px: tuple[float, float] = (10.0, 40.0)  # within this: "strong"
    strong_ratio: float = 0.55  # n64 / n1 at most, without metadata
    strong_depth_ratio: float = 0.7  # ours_n64_depth / open3d at most
    path_px: float = 3.0  # from this: the estimated path length is scored
    path_tolerance: float = 0.2  # |estimated / true - 1| at most
    sharp_px: float = OdometryConfig().sharp_blur_px  # under this: a sharp sequence
    sharp_ratio: float = 1.10  # n64 / n1 at most on sharp sequences


GOALS = OdometryGoals()


def ate_of(entry: dict, method: str) -> float | None:
    """A method's ATE (m) on a sequence's results, None when it did not run, failed or lost track."""
    x = entry.get("methods", {}).get(method, {}).get("ate_rmse_m")
    return float(x) if isinstance(x, (int, float)) and math.isfinite(x) else None


def _strong(blur: float, goals: OdometryGoals) -> bool:
    return goals.strong_px[0] <= blur <= goals.strong_px[1]


def ratio_goal(blur: float | None, metadata: bool, goals: OdometryGoals = GOALS) -> float | None:
    """The bound on n64 / n1 at this blur (None: no goal): ``mild_ratio`` up to ``mild_px`` with or
    without metadata, ``strong_ratio`` within ``strong_px`` without metadata."""
    if blur is None:
        return None
    if blur <= goals.mild_px:
        return goals.mild_ratio
    return goals.strong_ratio if _strong(blur, goals) and not metadata else None


def depth_goal(blur: float | None, goals: OdometryGoals = GOALS) -> float | None:
    """The bound on ours_n64_depth / open3d at this blur (None: no goal)."""
    if blur is None:
        return None
    if blur <= goals.mild_px:
        return goals.mild_depth_ratio
    return goals.strong_depth_ratio if _strong(blur, goals) else None


def path_goal(blur: float | None, goals: OdometryGoals = GOALS) -> float | None:
    """The tolerance on the estimated / true exposure-path length at this blur (None: no goal)."""
    return goals.path_tolerance if blur is not None and blur >= goals.path_px else None


def sharp_goal(blur: float | None, goals: OdometryGoals = GOALS) -> float | None:
    """The bound on n64 / n1 on a sharp sequence (None: not sharp)."""
    return goals.sharp_ratio if blur is not None and blur < goals.sharp_px else None


def check(value: float | None, bound: float | None, around_one: bool = False) -> dict | None:
    """A goal's cell: ``value`` against ``bound`` (``value <= bound``, or with ``around_one``
    ``|value - 1| <= bound``); ``met`` None when the value is missing; None when no goal applies."""
    if bound is None:
        return None
    met = None if value is None else (abs(value - 1.0) if around_one else value) <= bound
    return {"value": value, "bound": bound, "met": met, "around_one": around_one}


def _over(a: float | None, b: float | None) -> float | None:
    return a / b if a is not None and b is not None and b > 0 else None


def has_metadata(name: str, entry: dict) -> bool:
    """Whether the sequence carried its exposure metadata: from our runs' exposure modes when one
    says ('estimate': it did not; 'known': it did; n = 1 without metadata records 'none'), else
    from the name (``_noexp``: the hidden copy)."""
    modes = {c.get("exposure") for c in entry.get("methods", {}).values() if isinstance(c, dict)}
    if "estimate" in modes or "known" in modes:
        return "estimate" not in modes
    return not name.endswith("_noexp")


def sequence_goals(name: str, entry: dict, goals: OdometryGoals = GOALS) -> dict:
    """One row of the goals table: blur, metadata, and per goal its cell (:func:`check`)."""
    blur, meta = entry.get("mean_blur_px"), has_metadata(name, entry)
    n64, n1 = ate_of(entry, "ours_n64"), ate_of(entry, "ours_n1")
    path = entry.get("methods", {}).get("ours_n64", {}).get("exposure_length_ratio")
    return {"blur_px": blur, "metadata": meta,
            "n64_n1": check(_over(n64, n1), ratio_goal(blur, meta, goals)),
            "depth_open3d": check(_over(ate_of(entry, "ours_n64_depth"), ate_of(entry, "open3d")), depth_goal(blur, goals)),
            "path_true": check(path, path_goal(blur, goals), around_one=True),
            "sharp_n64_n1": check(_over(n64, n1), sharp_goal(blur, goals))}


def with_goals(res: dict, goals: OdometryGoals = GOALS) -> dict:
    """The benchmark's results with each sequence's ``goals`` row added."""
    return {name: {**entry, "goals": sequence_goals(name, entry, goals)} for name, entry in res.items()}


GOAL_COLUMNS = {"n64_n1": "n64 / n1", "depth_open3d": "n64_depth / open3d", "path_true": "path / true", "sharp_n64_n1": "sharp: n64 / n1"}


def _cell(c: dict | None) -> str:
    """'0.95 <=1.05 met', '1.21 <=1.05 NOT', '? <=1.05' (a method missing) or '-' (no goal)."""
    if c is None:
        return "-"
    bound = f"1±{c['bound']:.2f}" if c["around_one"] else f"<={c['bound']:.2f}"
    if c["met"] is None:
        return f"? {bound}"
    return f"{c['value']:.2f} {bound} {'met' if c['met'] else 'NOT'}"


def format_goals_table(res: dict, goals: OdometryGoals = GOALS) -> str:
    """The goals as a table, one row per sequence, then how many of the goals that apply are met."""
    rows = {name: entry.get("goals") or sequence_goals(name, entry, goals) for name, entry in res.items()}
    w = max([10, *(len(n) + 2 for n in rows)])
    lines = [f"goals (issue 57; '-': none at this blur, '?': a method missing): mild <= {goals.mild_px:g} px, "
             f"strong {goals.strong_px[0]:g}-{goals.strong_px[1]:g} px, path scored from {goals.path_px:g} px, sharp < {goals.sharp_px:g} px",
             f"{'sequence':<{w}}{'blur px':>8}  {'metadata':<9}" + "".join(f"{t:<22}" for t in GOAL_COLUMNS.values())]
    for name, r in rows.items():
        blur = f"{r['blur_px']:.1f}" if r["blur_px"] is not None else "?"
        lines.append(f"{name:<{w}}{blur:>8}  {('yes' if r['metadata'] else 'no'):<9}" + "".join(f"{_cell(r[k]):<22}" for k in GOAL_COLUMNS))
    cells = [r[k] for r in rows.values() for k in GOAL_COLUMNS if r[k] is not None]
    met, scored = sum(c["met"] is True for c in cells), sum(c["met"] is not None for c in cells)
    lines.append(f"met {met} of {scored} goals scored ({len(cells) - scored} without their methods' numbers)")
    return "\n".join(line.rstrip() for line in lines)
