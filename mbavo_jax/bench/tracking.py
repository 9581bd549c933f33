"""``mbavo bench tracking``: the tracking benchmark on frame pairs, ours against Open3D and OpenCV
RGB-D odometry on the same pairs.

Each pair is the sharp mid-exposure image of frame k with its depth (keyframe) and the blurry frame
k+1, from a constant-velocity guess of the true mid-exposure poses of frames k-1 and k
(:func:`~mbavo_jax.bench.sequences.tracking_pairs`). Accuracy: median reprojection error over the
keyframe's points of the estimated start and end poses ("endpoint") and of the mid-exposure pose
("mid"); single-pose methods use their pose for both. Times: median wall time of the tracking call,
first pair (compilation) excluded.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

from ..config import BenchConfig, TrackerConfig, calibration_of
from ..datasets import open_sequence
from ..errors import DataError
from ..geometry import ExposureTrajectory, Pose
from ..peers import Open3DPeer, OpenCVPeer
from ..progress import bar
from ..tracking import Keyframe, compiled_programs, track
from .sequences import bench_data, tracking_pairs, with_hidden_exposure

__all__ = ["OURS_TRACKING", "run_tracking_benchmark", "format_tracking_table", "main_tracking"]

# our tracker settings in the tracking benchmark, on top of the sequence's calibration
OURS_TRACKING = {
    "n1": dict(blur_aware=False),
    "n64": dict(jacobian="autodiff"),
    "n64_analytic": dict(jacobian="analytic"),
    "n64_tangent": dict(jacobian="tangent"),  # the default
    "n64_all_levels": dict(jacobian="tangent", n_per_level="same"),
    "adaptive": dict(jacobian="tangent", n_mode="adaptive"),
}


@jax.jit
def _reproj(cam, pixels, depths, valid, est: Pose, gt: Pose):
    X = jax.vmap(cam.backproject)(pixels, depths)
    pa = jax.vmap(lambda p: cam.project(est.inverse().apply(p)))(X)
    pb = jax.vmap(lambda p: cam.project(gt.inverse().apply(p)))(X)
    return jnp.where(valid, jnp.linalg.norm(pa - pb, axis=1), jnp.nan)


def _errors(kf: Keyframe, est: ExposureTrajectory, gt: ExposureTrajectory):
    pts, cam = kf.points[0], kf.cameras[0]
    args = (cam, *pts.on_device)
    ends = np.concatenate([np.asarray(_reproj(*args, est.start, gt.start)), np.asarray(_reproj(*args, est.end, gt.end))])
    mid = np.asarray(_reproj(*args, est.middle(), gt.middle()))
    return float(np.nanmedian(ends)), float(np.nanmedian(mid))


def _tracking_peers(camera, peers: bool, depth_max: float) -> tuple[dict, dict]:
    """(adapters, notes): the peers that load, and a line on each."""
    adapters, notes = {}, {}
    if not peers:
        return adapters, notes
    try:
        adapters["open3d"] = Open3DPeer(camera, depth_max=depth_max)
        notes["open3d"] = adapters["open3d"].note
    except Exception as exc:  # pragma: no cover - depends on the machine
        notes["open3d"] = f"open3d unavailable ({type(exc).__name__}: {exc})"
    adapters["opencv"] = OpenCVPeer(camera, depth_max)
    notes["opencv"] = adapters["opencv"].note
    return adapters, notes


def _record(row: dict, ms: float, kf: Keyframe, traj: ExposureTrajectory, gt: ExposureTrajectory, ok: bool) -> None:
    e, m = _errors(kf, traj, gt)
    row["ms"].append(ms)
    row["endpoint"].append(e)
    row["mid"].append(m)
    row["ok"] += int(ok)


def _track_pair(rows: dict, recompiles: dict, ours: dict, peers: dict, camera, base: TrackerConfig, first: bool, pair) -> None:
    """Every method on one pair; our programs compiled after the first pair counted in ``recompiles``."""
    _, sharp, depth, frame, init, gt = pair
    for name, cfg in ours.items():
        kf = Keyframe.create(sharp, depth, camera, cfg)
        before = compiled_programs()
        t0 = time.perf_counter()
        traj, status, _ = track(kf, frame.image, init, cfg)
        ms = 1000 * (time.perf_counter() - t0)
        if not first:
            recompiles[name] += compiled_programs() - before
        _record(rows[name], ms, kf, traj, gt, status.ok)
    kf_eval = Keyframe.create(sharp, depth, camera, base)
    guess = np.asarray(init.middle().inverse().as_matrix(), np.float64)  # T_cur_ref
    for name, peer in peers.items():
        t0 = time.perf_counter()
        ok, T_ref_cur = peer.relative_pose(peer.prepare(sharp, depth), peer.prepare(frame.image, frame.depth), guess)
        ms = 1000 * (time.perf_counter() - t0)
        if T_ref_cur is None:
            traj = init
        else:
            pose = Pose.from_matrix(jnp.asarray(T_ref_cur, jnp.float32))
            traj = ExposureTrajectory(pose, pose)
        _record(rows[name], ms, kf_eval, traj, gt, ok)


def _tracking_summary(rows: dict, recompiles: dict) -> dict:
    """Per-method medians and the flat numbers (``n64_ms``, ...) of the tracking benchmark."""
    table = {}
    for name, r in rows.items():
        ms = np.asarray(r["ms"][1:] if len(r["ms"]) > 1 else r["ms"])
        table[name] = {"median_ms": float(np.median(ms)), "endpoint_px": float(np.median(r["endpoint"])),
                       "mid_px": float(np.median(r["mid"])), "endpoint_px_p90": float(np.percentile(r["endpoint"], 90)), "ok": r["ok"]}
    for name, n in recompiles.items():
        table[name]["recompiles_after_first_frame"] = int(n)
    for name in table:
        table[name]["ratio_to_n1"] = table[name]["median_ms"] / table["n1"]["median_ms"]
    # fixed n compiles once per level on the first pair; adaptive n once per new (level, n), so later too
    return {
        "methods": table,
        **{f"{m}_ms": table[m]["median_ms"] for m in ("n1", "n64", "n64_analytic", "n64_tangent", "adaptive")},
        "open3d_ms": table.get("open3d", {}).get("median_ms"),
        "opencv_ms": table.get("opencv", {}).get("median_ms"),
        **{f"{m}_endpoint_px": table[m]["endpoint_px"] for m in ("n64", "n64_analytic", "n64_tangent", "n1", "adaptive")},
        "recompiles_after_first_frame": int(sum(n for m, n in recompiles.items() if m != "adaptive")),
        "adaptive_recompiles_after_first_frame": int(recompiles["adaptive"]),
    }


def run_tracking_benchmark(data, frames: int = 20, peers: bool = True, progress: bool = True,
                           peer_depth_max: float = BenchConfig().peer_depth_max) -> dict:
    """Every method on the same ``frames`` pairs of the generated sequence in ``data``; the results."""
    seq = open_sequence(data)
    if seq.exposure_paths is None or seq.groundtruth is None:
        raise DataError(data, "the tracking benchmark needs a generated sequence with exposure.txt and groundtruth.txt")
    base = TrackerConfig(**calibration_of(seq.meta))
    ours = {name: dataclasses.replace(base, **changes) for name, changes in OURS_TRACKING.items()}
    adapters, notes = _tracking_peers(seq.camera, peers, peer_depth_max)
    rows = {name: {"ms": [], "endpoint": [], "mid": [], "ok": 0} for name in [*ours, *adapters]}
    recompiles = dict.fromkeys(ours, 0)
    pairs = list(tracking_pairs(seq, frames))
    with bar(len(pairs), "bench", progress, unit="pair") as pbar:
        for idx, pair in enumerate(pairs):
            _track_pair(rows, recompiles, ours, adapters, seq.camera, base, idx == 0, pair)
            pbar.update()
    summary = {"frames": len(pairs), "sequence": str(data), "resolution": f"{seq.camera.width}x{seq.camera.height}", "peers": notes}
    summary.update(_tracking_summary(rows, recompiles))
    return summary


def format_tracking_table(s: dict) -> str:
    lines = [
        f"tracking benchmark: {s['frames']} frame pairs, {s['resolution']}, sequence {s['sequence']}",
        f"{'method':<16} {'median ms':>10} {'x n=1':>7} {'endpoint px':>12} {'p90':>7} {'mid px':>8} {'ok':>5}",
    ]
    for name, r in s["methods"].items():
        lines.append(
            f"{name:<16} {r['median_ms']:>10.1f} {r['ratio_to_n1']:>7.2f} {r['endpoint_px']:>12.3f} {r['endpoint_px_p90']:>7.2f} {r['mid_px']:>8.3f} {r['ok']:>3}/{s['frames']}"
        )
    lines.append(
        f"recompilations after the first frame: {s['recompiles_after_first_frame']} (fixed n), "
        f"{s['adaptive_recompiles_after_first_frame']} (adaptive n: one per new (level, n) bucket)"
    )
    for k, v in s["peers"].items():
        lines.append(f"{k}: {v}")
    return "\n".join(lines)


def main_tracking(cfg: BenchConfig, data=None, fmt: str = "table", quiet: bool = False) -> int:
    """``mbavo bench tracking``: one run per preset of ``cfg.preset`` (default strong, then none), or on ``data``."""
    if data:
        runs = {pathlib.Path(data).name: pathlib.Path(data)}
    else:
        runs = {p: bench_data(p, cfg, cfg.frames + 2, quiet) for p in cfg.preset.split(",")}
    runs = with_hidden_exposure(runs, cfg.hide_exposure)
    results = {name: run_tracking_benchmark(path, cfg.frames, peers=not cfg.no_peers, progress=not quiet,
                                                 peer_depth_max=cfg.peer_depth_max) for name, path in runs.items()}
    if fmt == "json":
        print(json.dumps(results if len(results) > 1 else next(iter(results.values())), indent=2))
    else:
        print("\n\n".join(f"[{name}]\n{format_tracking_table(r)}" for name, r in results.items()))
    return 0
