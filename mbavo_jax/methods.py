"""The methods of ``mbavo bench odometry`` and ``mbavo sweep``: their names, and one method's run over
a sequence, scored: ours (:func:`run_ours`, the odometry loop) or a peer (:func:`run_peer`, its
frame-to-frame odometry chained). The sweep's workers and the benchmarks both call these.
JAX-free at import, so that the command line can list and check the names; a run imports what it needs.
"""

from __future__ import annotations

import csv
import pathlib
import time

import numpy as np

from .config import EvalConfig, RunConfig
from .errors import MbavoError

__all__ = ["ODOMETRY_METHODS", "check_methods", "parse_methods", "run_ours", "run_peer", "ate_rmse", "deblur_quality"]

ODOMETRY_METHODS = ("ours_n64", "ours_n1", "ours_adaptive", "ours_n64_depth", "ours_n1_depth", "open3d", "open3d_color", "opencv")


def check_methods(methods) -> None:
    """Raise MbavoError naming the unknown methods (or an empty selection)."""
    unknown = sorted(set(methods) - set(ODOMETRY_METHODS))
    if unknown or not methods:
        raise MbavoError(f"unknown benchmark method(s) {', '.join(unknown) or '(none left)'}; choose from {', '.join(ODOMETRY_METHODS)}")


def parse_methods(text: str, no_peers: bool = False) -> list[str]:
    """The methods of a comma-separated list ('' = all), peers dropped with ``no_peers``; checked."""
    methods = [m.strip() for m in text.split(",") if m.strip()] if text else list(ODOMETRY_METHODS)
    if no_peers:
        methods = [m for m in methods if m.startswith("ours_")]
    check_methods(methods)
    return methods


def ate_rmse(seq, run: pathlib.Path, config: EvalConfig) -> float:
    """ATE RMSE of a run; NaN when it cannot be scored (fewer than 3 matched poses: a lost run)."""
    from .evaluation import evaluate_run

    return evaluate_run(run, seq.groundtruth, config=config).get("ate_rmse_m", float("nan"))


def deblur_quality(seq, run: pathlib.Path) -> dict:
    """Mean PSNR/SSIM of this run's keyframe images (deblurred where blurred) and of the blurry
    input, both against the generated sharp frames."""
    from .deblur import psnr, ssim
    from .io import read_image_gray, read_tum_trajectory

    rows = []
    stamps, _ = read_tum_trajectory(run / "keyframes.txt")  # this run's keyframes, not stale files
    for stamp in stamps:
        p = run / "keyframes" / f"{stamp:.6f}.png"
        k = int(np.argmin(np.abs(seq.timestamps - stamp)))
        sharp_path = pathlib.Path(seq[k].path).parent.parent / "sharp" / pathlib.Path(seq[k].path).name
        if not sharp_path.is_file():
            continue
        ref = read_image_gray(sharp_path)
        deb = read_image_gray(p)  # 16-bit keyframe image
        rows.append((psnr(deb, ref), psnr(seq[k].image, ref), ssim(deb, ref), ssim(seq[k].image, ref)))
    if not rows:
        return {}
    a = np.asarray(rows)
    return {"keyframes": len(rows), "psnr_deblurred": float(a[:, 0].mean()), "psnr_blurry": float(a[:, 1].mean()),
            "ssim_deblurred": float(a[:, 2].mean()), "ssim_blurry": float(a[:, 3].mean())}


def _exposure_quality(seq, run: pathlib.Path, summ: dict) -> dict:
    """How the run had its exposure time (and the estimate), and the median over frames of its
    exposure paths' length over the true ones (generated sequences)."""
    from .evaluation import exposure_path_error
    from .io import read_exposure_file

    out = {k: summ[k] for k in ("exposure", "exposure_ms", "exposure_fraction", "exposure_samples") if k in summ}
    if seq.exposure_paths is not None:
        cam = seq.camera.as_dict()
        ratio = exposure_path_error(seq.exposure_paths, read_exposure_file(run / "exposure.txt"), cam).get("length_ratio")
        if ratio:
            out["exposure_length_ratio"] = ratio["median"]
    return out


def run_ours(seq, run: pathlib.Path, config: RunConfig, progress: bool = False) -> dict:
    """Our loop over a sequence: ATE, frame drops, keyframes, whole-loop seconds per frame, the
    exposure quality and (generated sequences) the deblurred keyframes' PSNR/SSIM."""
    from .odometry import run_odometry

    t0 = time.perf_counter()
    summ = run_odometry(seq, run, config, progress=progress)
    el = time.perf_counter() - t0
    with open(run / "frames.csv") as fh:
        track_ms = [float(r["ms"]) for r in csv.DictReader(fh) if r["status"] != "keyframe"]
    deblur = {("deblur_keyframes" if k == "keyframes" else k): v for k, v in deblur_quality(seq, run).items()}
    return {"ate_rmse_m": ate_rmse(seq, run, config.evaluation), "frame_drop_rate": summ["frame_drop_rate"], "keyframes": summ["keyframes"],
            "seconds_per_frame": el / max(summ["frames"], 1), "median_track_ms": float(np.median(track_ms)) if track_ms else 0.0,
            **_exposure_quality(seq, run, summ), **deblur}


def run_peer(seq, run: pathlib.Path, method: str, evaluation: EvalConfig, depth_max: float) -> dict:
    """A peer's chained frame-to-frame odometry over a sequence: ATE, frame drops, median seconds per call."""
    from .peers import make_peer, peer_odometry

    p_sum = peer_odometry(seq, run, make_peer(method, seq.camera, depth_max))
    return {"ate_rmse_m": ate_rmse(seq, run, evaluation), "frame_drop_rate": p_sum["dropped"] / p_sum["frames"],
            "seconds_per_frame": p_sum["median_ms"] / 1000}
