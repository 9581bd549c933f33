"""APE, RPE, frame drops and exposure-path error (numpy, float64)."""

from __future__ import annotations

import numpy as np

from ..errors import MbavoError
from ..io import CAMERA_KEYS
from .align import umeyama
from .associate import associate
from .poses import pose_matrices, slerp

__all__ = ["statistics", "ape", "rpe", "aligned_positions", "frame_drop_rate", "relative_drift", "exposure_path_error", "exposure_path_lengths", "pose_matrices"]


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


def _about_middle(start: np.ndarray, end: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(T_mid_start, T_mid_end) 4x4 of a path given as camera-to-world vectors (mid: Eqs. 43-44 at ½)."""
    mid = np.concatenate([(start[:3] + end[:3]) / 2, slerp(start[3:], end[3:], 0.5)])
    Tm_inv = np.linalg.inv(pose_matrices(mid[None])[0])
    return Tm_inv @ pose_matrices(start[None])[0], Tm_inv @ pose_matrices(end[None])[0]


def exposure_path_lengths(paths, camera: dict, depth: float = 2.0, grid: int = 8) -> np.ndarray:
    """Per frame of ``paths`` (stamps, start (N, 7), end (N, 7)), the mean pixel distance between a
    grid of points at ``depth`` metres (in the mid-exposure frame) seen from the start and end poses."""
    P = _grid_points(camera, depth, grid)
    return np.asarray([_mean_shift(camera, P, *_about_middle(np.asarray(start, np.float64), np.asarray(end, np.float64)))
                       for start, end in zip(paths[1], paths[2])])


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
