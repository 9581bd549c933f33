"""A sweep's results table: ``results.csv`` (every column), ``results.md`` (the main ones, for
reading) and ``ate.png`` (ATE per sequence, one bar per method)."""

from __future__ import annotations

import csv
import math
import pathlib

import numpy as np

__all__ = ["COLUMNS", "write_tables", "format_markdown", "plot_ate"]

COLUMNS = ("sequence", "method", "status", "ate_rmse_m", "frame_drop_rate", "seconds_per_frame", "median_track_ms", "keyframes",
           "frames", "mean_blur_px", "psnr_deblurred", "psnr_blurry", "ssim_deblurred", "ssim_blurry", "deblur_keyframes",
           "exposure", "exposure_ms", "exposure_samples", "exposure_fraction", "exposure_length_ratio", "depth_sigma",
           "seconds", "overrides", "error")


def _csv_value(v) -> str:
    if v is None:
        return ""
    return " ".join(map(str, v)) if isinstance(v, (list, tuple)) else str(v)


def _number(row: dict, key: str) -> float | None:
    v = row.get(key)
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) else None


def _cells(row: dict) -> list[str]:
    """ATE mm, drops, seconds per frame [tracking ms], PSNR deblurred (blurry), exposure, note."""
    if row.get("status") != "ok":
        return ["error", "", "", "", "", row.get("error", "").replace("|", "/")[:160]]
    ate, spf, ms = _number(row, "ate_rmse_m"), _number(row, "seconds_per_frame"), _number(row, "median_track_ms")
    psnr, blurry = _number(row, "psnr_deblurred"), _number(row, "psnr_blurry")
    exp, ratio = _number(row, "exposure_ms"), _number(row, "exposure_length_ratio")
    return [f"{1000 * ate:.2f}" if ate is not None else "lost",
            f"{row['frame_drop_rate']:.2f}" if _number(row, "frame_drop_rate") is not None else "-",
            (f"{spf:.3f}" if spf is not None else "-") + (f" [{ms:.0f}]" if ms is not None else ""),
            f"{psnr:.2f} ({blurry:.2f})" if psnr is not None and blurry is not None else "-",
            (f"{exp:.1f} {row.get('exposure', '')}" if exp is not None else "-") + (f" / {ratio:.2f}" if ratio is not None else ""),
            ""]


def format_markdown(rows: list[dict]) -> str:
    """One line per run: sequence, method, ATE (SE3-aligned RMSE, mm), frame-drop rate, seconds per
    frame (ours: whole loop [median tracking ms]; peers: median call), deblurred keyframes' PSNR
    (blurry input's), exposure ms and whence (known, estimate) / estimated path length over the
    true one, and errors."""
    lines = ["| sequence | method | ATE mm | frame drops | s per frame [track ms] | deblurred PSNR dB (blurry) | "
             "exposure ms / path ratio | error |", "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['sequence']} | {r['method']} | " + " | ".join(_cells(r)) + " |" for r in rows]
    return "\n".join(lines)


def plot_ate(rows: list[dict], path) -> None:
    """Grouped bars: ATE (mm, log scale) per sequence, one bar per method; failed or lost runs
    are marked with an x at the axis."""
    from ..evaluation.plots import _plt

    plt = _plt()
    seqs = list(dict.fromkeys(r["sequence"] for r in rows))
    methods = list(dict.fromkeys(r["method"] for r in rows))
    ate = {(r["sequence"], r["method"]): _number(r, "ate_rmse_m") for r in rows}
    width = 0.8 / max(len(methods), 1)
    fig, ax = plt.subplots(figsize=(max(6.0, 1.2 * len(seqs) * max(1, len(methods)) ** 0.5), 4), dpi=100)
    positive = [1000 * v for v in ate.values() if v]
    floor = min(positive) / 2 if positive else 1e-3
    for j, m in enumerate(methods):
        x = np.arange(len(seqs)) + (j - (len(methods) - 1) / 2) * width
        y = np.array([1000 * ate[(s, m)] if ate.get((s, m)) is not None else np.nan for s in seqs])
        ax.bar(x, np.where(np.isfinite(y), np.maximum(y, floor), np.nan), width, label=m, color=f"C{j % 10}")
        missing = [xi for xi, s in zip(x, seqs) if (s, m) in ate and ate[(s, m)] is None]
        ax.plot(missing, [floor] * len(missing), "x", color=f"C{j % 10}", ms=8)
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(seqs)), seqs, rotation=30 if len(seqs) > 4 else 0, ha="right" if len(seqs) > 4 else "center")
    ax.set_ylabel("ATE RMSE [mm] (log)")
    ax.set_title("ATE per sequence and method (x: failed or lost)")
    ax.grid(axis="y", alpha=0.3, which="both")
    ax.legend(fontsize=8, ncols=min(len(methods), 4))
    fig.tight_layout()
    fig.savefig(pathlib.Path(path))
    plt.close(fig)


def write_tables(rows: list[dict], out) -> dict[str, pathlib.Path]:
    """results.csv, results.md and ate.png in ``out``; their paths."""
    out = pathlib.Path(out)
    paths = {"csv": out / "results.csv", "markdown": out / "results.md", "plot": out / "ate.png"}
    with open(paths["csv"], "w", newline="") as fh:
        writer = csv.DictWriter(fh, COLUMNS, extrasaction="ignore")
        writer.writeheader()
        writer.writerows({k: _csv_value(r.get(k)) for k in COLUMNS} for r in rows)
    paths["markdown"].write_text(format_markdown(rows) + "\n")
    plot_ate(rows, paths["plot"])
    return paths
