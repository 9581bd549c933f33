"""APE, RPE, frame drops and exposure-path error, per frame and per image row (numpy, float64)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import MbavoError
from ..geometry.pose import Pose
from ..geometry.spline import SplineTrajectory
from ..geometry.trajectory import row_times
from ..io import CAMERA_KEYS, ExposureRows, sampled_rows
from .align import umeyama
from .associate import associate
from .poses import pose_matrices, slerp

__all__ = ["statistics", "ape", "rpe", "aligned_positions", "frame_drop_rate", "relative_drift", "exposure_path_error", "exposure_path_lengths",
           "row_path_error", "row_fractions", "global_shutter_rows", "pose_matrices"]


def statistics(errors: np.ndarray) -> dict:
    e = np.asarray(errors, np.float64)
    return {
        "rmse": float(np.sqrt(np.mean(e**2))),
        "mean": float(np.mean(e)),
        "median": float(np.median(e)),
        "std": float(np.std(e)),
        "min": float(np.min(e)),
        "max": float(np.max(e)),
        "sse": float(np.sum(e**2)),
    }


def _matched(stamps_ref, poses_ref, stamps_est, poses_est, max_diff, offset=0.0):
    i_est, i_ref = associate(stamps_est, stamps_ref, max_diff, offset)
    if len(i_est) == 0:
        raise MbavoError(f"no overlapping timestamps between estimate and reference (max_diff {max_diff} s)")
    return i_est, i_ref, pose_matrices(poses_ref[i_ref]), pose_matrices(poses_est[i_est])


def _align(T_ref, T_est, align: str):
    if align == "none":
        return T_est, np.eye(3), np.zeros(3), 1.0
    if align not in ("se3", "sim3"):
        raise MbavoError(f"unknown alignment '{align}' (none, se3, sim3)")
    R, t, s = umeyama(T_est[:, :3, 3], T_ref[:, :3, 3], with_scale=align == "sim3")
    out = T_est.copy()
    out[:, :3, :3] = R @ T_est[:, :3, :3]
    out[:, :3, 3] = s * T_est[:, :3, 3] @ R.T + t
    return out, R, t, s


def ape(stamps_ref, poses_ref, stamps_est, poses_est, align: str = "se3", max_diff: float = 0.01) -> dict:
    """Absolute trajectory error of the translation part after alignment (evo's ``ape -a [-s]``)."""
    i_est, _, T_ref, T_est = _matched(stamps_ref, poses_ref, stamps_est, poses_est, max_diff)
    T_al, R, t, s = _align(T_ref, T_est, align)
    err = np.linalg.norm(T_al[:, :3, 3] - T_ref[:, :3, 3], axis=1)
    out = statistics(err)
    out.update(n_matched=int(len(i_est)), alignment=align, scale=float(s), errors=err.tolist())
    return out


def aligned_positions(stamps_ref, poses_ref, stamps_est, poses_est, align: str = "se3", max_diff: float = 0.01):
    """The matched poses as ``ape`` sees them: (i_est, i_ref, reference positions (M, 3), estimated
    positions after alignment (M, 3)); for plots."""
    i_est, i_ref, T_ref, T_est = _matched(stamps_ref, poses_ref, stamps_est, poses_est, max_diff)
    return i_est, i_ref, T_ref[:, :3, 3], _align(T_ref, T_est, align)[0][:, :3, 3]


def rpe(stamps_ref, poses_ref, stamps_est, poses_est, delta: int = 1, align: str = "none", max_diff: float = 0.01) -> dict:
    """Relative pose error of the translation part over ``delta`` matched frames (evo's ``rpe``)."""
    i_est, _, T_ref, T_est = _matched(stamps_ref, poses_ref, stamps_est, poses_est, max_diff)
    if len(i_est) <= delta:
        raise MbavoError(f"RPE needs more than delta={delta} matched poses, got {len(i_est)}")
    if align == "sim3":
        T_est, _, _, _ = _align(T_ref, T_est, align)
    errs = []
    for k in range(len(T_ref) - delta):
        dr = np.linalg.inv(T_ref[k]) @ T_ref[k + delta]
        de = np.linalg.inv(T_est[k]) @ T_est[k + delta]
        E = np.linalg.inv(dr) @ de
        errs.append(np.linalg.norm(E[:3, 3]))
    out = statistics(np.array(errs))
    out.update(n_matched=int(len(i_est)), delta=delta, errors=errs)
    return out


def relative_drift(stamps_ref, poses_ref, stamps_est, poses_est, delta: int = 10, max_diff: float = 0.01) -> dict:
    """Drift over ``delta`` matched frames after Sim(3) alignment, in % of the true segment length:
    ``drift_trans_pct`` (mean relative translation error) and ``drift_scale_pct`` (mean |estimated
    segment length / true - 1|); segments shorter than 1 mm are left out. Also the matched path length."""
    _, _, T_ref, T_est = _matched(stamps_ref, poses_ref, stamps_est, poses_est, max_diff)
    T_est = _align(T_ref, T_est, "sim3")[0]
    p_ref, p_est = T_ref[:, :3, 3], T_est[:, :3, 3]
    trans, scale = [], []
    for k in range(len(T_ref) - delta):
        dr = np.linalg.inv(T_ref[k]) @ T_ref[k + delta]
        de = np.linalg.inv(T_est[k]) @ T_est[k + delta]
        length = np.linalg.norm(dr[:3, 3])
        if length > 1e-3:
            trans.append(np.linalg.norm((np.linalg.inv(dr) @ de)[:3, 3]) / length)
            scale.append(abs(np.linalg.norm(de[:3, 3]) / length - 1.0))
    nan = float("nan")
    return {"drift_trans_pct": 100 * float(np.mean(trans)) if trans else nan, "drift_scale_pct": 100 * float(np.mean(scale)) if scale else nan,
            "path_length_m": float(np.linalg.norm(np.diff(p_ref, axis=0), axis=1).sum()), "delta": delta,
            "estimated_length_m": float(np.linalg.norm(np.diff(p_est, axis=0), axis=1).sum())}


def frame_drop_rate(stamps_frames, stamps_est, max_diff: float = 0.01) -> float:
    """Fraction of the sequence's frames that have no estimated pose."""
    if len(stamps_frames) == 0:
        return 0.0
    i, _ = associate(np.asarray(stamps_frames), np.asarray(stamps_est), max_diff) if len(stamps_est) else ([], [])
    return 1.0 - len(i) / len(stamps_frames)


def _grid_points(camera: dict, depth: float, grid: int) -> np.ndarray:
    """A ``grid`` x ``grid`` pixel grid (10-90 % of the image) back-projected at ``depth`` metres."""
    fx, fy, cx, cy, w, h = (camera[k] for k in CAMERA_KEYS)
    u, v = np.meshgrid(np.linspace(0.1 * w, 0.9 * w, grid), np.linspace(0.1 * h, 0.9 * h, grid))
    return np.stack([(u.ravel() - cx) / fx * depth, (v.ravel() - cy) / fy * depth, np.full(u.size, depth)], 1)


def _project(camera: dict, P: np.ndarray, T_cur_ref: np.ndarray) -> np.ndarray:
    Q = P @ T_cur_ref[:3, :3].T + T_cur_ref[:3, 3]
    return np.stack([camera["fx"] * Q[:, 0] / Q[:, 2] + camera["cx"], camera["fy"] * Q[:, 1] / Q[:, 2] + camera["cy"]], 1)


def _mean_shift(camera: dict, P: np.ndarray, T_mid_a: np.ndarray, T_mid_b: np.ndarray) -> float:
    """Mean pixel distance between the points ``P`` (N, 3) of the mid frame seen from poses a and b (4x4, T_mid_a)."""
    shift = _project(camera, P, np.linalg.inv(T_mid_b)) - _project(camera, P, np.linalg.inv(T_mid_a))
    return float(np.mean(np.linalg.norm(shift, axis=1)))


def _along(start: np.ndarray, end: np.ndarray, s) -> np.ndarray:
    """Poses (M, 7) at fractions ``s`` (M,) of the path start → end (camera-to-world vectors), by
    Eqs. 43-44 (interpolating world poses equals interpolating them in any reference frame)."""
    s = np.asarray(s, np.float64).reshape(-1)
    t = (1 - s)[:, None] * start[:3] + s[:, None] * end[:3]
    return np.concatenate([t, slerp(np.tile(start[3:], (len(s), 1)), np.tile(end[3:], (len(s), 1)), s)], 1)


def _about_middle(start: np.ndarray, end: np.ndarray, poses: np.ndarray | None = None) -> np.ndarray:
    """T_mid⁻¹ T (4x4 each) of ``poses`` (M, 7; default: start and end), camera-to-world vectors,
    relative to the mid pose of the path start → end (Eqs. 43-44 at ½)."""
    Tm_inv = np.linalg.inv(pose_matrices(_along(start, end, [0.5]))[0])
    return Tm_inv @ pose_matrices(np.stack([start, end]) if poses is None else poses)


def exposure_path_lengths(paths, camera: dict, depth: float = 2.0, grid: int = 8) -> np.ndarray:
    """Per frame of ``paths`` (stamps, start (N, 7), end (N, 7)), the mean pixel distance between a
    grid of points at ``depth`` metres (in the mid-exposure frame) seen from the start and end poses."""
    P = _grid_points(camera, depth, grid)
    return np.asarray([_mean_shift(camera, P, *_about_middle(np.asarray(start, np.float64), np.asarray(end, np.float64)))
                       for start, end in zip(paths[1], paths[2])])


def global_shutter_rows(paths, height: int, rows: int = 9) -> ExposureRows:
    """Per-row ground truth of a global-shutter sequence from its exposure ``paths`` (stamps, start
    (N, 7), end (N, 7)): ``rows`` evenly spaced rows, each exposed along the whole path."""
    stamps, start, end = (np.asarray(a, np.float64) for a in paths)
    v = sampled_rows(height, rows)
    rep = lambda a: np.repeat(a[:, None], len(v), 1)
    return ExposureRows(stamps, np.tile(v, (len(stamps), 1)), rep(start), rep(end))


def row_fractions(rows: np.ndarray, height: int, readout: float) -> np.ndarray:
    """(K, 2) fractions of a frame's path at which rows ``rows`` (K,) start and end their exposure,
    for readout fraction ρ = ``readout`` (``geometry.trajectory.row_times`` with two virtual frames)."""
    with jax.enable_x64(True):
        return np.asarray(row_times(2, jnp.asarray(rows, jnp.float64), height, readout))


def _estimate_about_middle(est, i, s: np.ndarray) -> np.ndarray:
    """T_mid⁻¹ T (4x4 each) at fractions ``s`` of frame i's estimated path. ``est`` is (stamps,
    start, end) (straight paths: T_mid at ½) or (stamps, controls (N, 4, 7)) (cubic paths,
    ``exposure_spline.txt``, evaluated by ``geometry.spline`` in float64; T_mid at ½ of the straight
    path between the poses at min(s) and max(s), as the reference's mid is taken)."""
    if len(est) == 3:
        start, end = (np.asarray(a[i], np.float64) for a in (est[1], est[2]))
        return _about_middle(start, end, _along(start, end, s))
    with jax.enable_x64(True):
        spline = SplineTrajectory(jax.vmap(Pose.from_vector)(jnp.asarray(est[1][i], jnp.float64)))
        at = jnp.asarray(np.concatenate([[np.min(s), np.max(s)], s]), jnp.float64)
        poses = np.asarray(jax.vmap(lambda u: spline.at(u).to_vector())(at))
    return _about_middle(poses[0], poses[1], poses[2:])


def row_path_error(ref: ExposureRows, est, camera: dict, readout: float = 0.0, depth: float = 2.0, grid: int = 8,
                   max_diff: float = 0.01) -> dict:
    """Per-row endpoint error of estimated exposure paths against a rolling shutter's true ones.

    ``ref``: the true start and end poses of sampled rows (``exposure_rows.txt``). ``est``:
    (stamps, start (N, 7), end (N, 7)), each frame's estimated path over its whole span, or
    (stamps, controls (N, 4, 7)) for cubic paths (:func:`_estimate_about_middle`); row v of
    the estimate runs from s = ρ·v/(H-1) to s + 1 − ρ along it (:func:`row_fractions`, ρ =
    ``readout``, the estimate's model; 0: a global-shutter estimate, every row the whole path).
    Every pose is taken relative to its frame's mid pose (the reference's: the straight path from
    the first sampled row's start to the last's end, at ½; the estimate's: its path at ½), and the
    error of a row's start (end) is the mean reprojection distance of :func:`exposure_path_error`'s
    point grid. Returns ``reprojection_px`` (statistics over frames, rows, start and end) and
    ``per_row_px`` (mean per sampled row position)."""
    i_est, i_ref = associate(est[0], ref.stamps, max_diff)
    if len(i_est) == 0:
        raise MbavoError("no overlapping timestamps between the estimated exposure paths and the per-row ground truth")
    P = _grid_points(camera, depth, grid)
    errors = []
    for ie, ir in zip(i_est, i_ref):
        r_start, r_end = (np.asarray(a[ir], np.float64) for a in (ref.starts, ref.ends))
        s = row_fractions(ref.rows[ir], int(camera["height"]), readout)
        R = _about_middle(r_start[0], r_end[-1], np.concatenate([r_start, r_end]))
        E = _estimate_about_middle(est, ie, np.concatenate([s[:, 0], s[:, 1]]))
        errors.append([_mean_shift(camera, P, Tr, Te) for Tr, Te in zip(R, E)])
    errors = np.asarray(errors).reshape(len(i_est), 2, -1)  # (frames, start|end, rows)
    return {"n_matched": int(len(i_est)), "rows": int(errors.shape[2]), "readout": float(readout),
            "reprojection_px": statistics(errors.ravel()), "per_row_px": errors.mean(axis=(0, 1)).tolist()}


def exposure_path_error(ref, est, camera: dict, depth: float = 2.0, grid: int = 8, max_diff: float = 0.01) -> dict:
    """Start and end pose errors of estimated exposure paths, and their mean reprojection error.

    ``ref`` and ``est`` are (stamps, start (N, 7), end (N, 7)) camera-to-world. Each path is taken
    relative to its own mid-exposure pose (so global drift is removed): the error of the start pose
    is that of T_mid⁻¹ T_start. The reprojection error is the mean pixel distance, over a
    ``grid`` x ``grid`` pixel grid back-projected at ``depth`` metres in the reference mid frame, of
    the points projected with the estimated vs reference start (and end) relative poses.
    ``length_ratio``: per frame, the estimated path's length over the reference's
    (:func:`exposure_path_lengths`), for frames whose reference path is 0.5 px or longer.
    """
    i_est, i_ref = associate(est[0], ref[0], max_diff)
    if len(i_est) == 0:
        raise MbavoError("no overlapping timestamps between estimated and reference exposure paths")
    P = _grid_points(camera, depth, grid)
    trans, rot, reproj, ref_len, est_len = [], [], [], [], []
    for ie, ir in zip(i_est, i_ref):
        rs, re_ = _about_middle(np.asarray(ref[1][ir], np.float64), np.asarray(ref[2][ir], np.float64))
        es, ee = _about_middle(np.asarray(est[1][ie], np.float64), np.asarray(est[2][ie], np.float64))
        for Tr, Te in ((rs, es), (re_, ee)):
            E = np.linalg.inv(Tr) @ Te
            trans.append(np.linalg.norm(E[:3, 3]))
            rot.append(np.degrees(np.arccos(np.clip((np.trace(E[:3, :3]) - 1) / 2, -1, 1))))
            reproj.append(_mean_shift(camera, P, Tr, Te))
        ref_len.append(_mean_shift(camera, P, rs, re_))  # the paths' lengths, as exposure_path_lengths measures them
        est_len.append(_mean_shift(camera, P, es, ee))
    ref_len, est_len = np.asarray(ref_len), np.asarray(est_len)
    long = ref_len >= 0.5
    return {
        "n_matched": int(len(i_est)),
        "translation_m": statistics(np.array(trans)),
        "rotation_deg": statistics(np.array(rot)),
        "reprojection_px": statistics(np.array(reproj)),
        "length_ratio": statistics(est_len[long] / ref_len[long]) if long.any() else {},
    }
