"""Initialisation of the monocular system from images alone: the two-view part.

Corners of a reference frame (``cv2.goodFeaturesToTrack``) are tracked frame by frame with
pyramidal KLT from the previous frame, forward-backward checked. Once the tracks' parallax,
measured after removing the rotation that best explains them, is large enough, the essential
matrix (5-point solver in RANSAC) and ``cv2.recoverPose`` give the current camera up to scale; the inliers
are triangulated, and the scale is fixed so that their median depth is 1 (the monocular world's
unit). Pure rotation, too little texture and ill-conditioned geometry are reported in
``TwoView.reason``, never raised: the caller keeps feeding frames (and starts again from a later
reference after too many, or when ``TwoView.restart`` says so). The photometric refinement of
the result is the windowed bundle adjustment's job.
"""

from __future__ import annotations

import dataclasses

import cv2
import jax.numpy as jnp
import numpy as np
from jaxtyping import Bool, Float, UInt8

from ..config import MonoConfig
from ..geometry import PinholeCamera, Pose

__all__ = ["TwoView", "Tracks", "TwoViewTracker", "RelativePose", "Triangulated", "detect_corners", "start_tracks",
           "advance_tracks", "track_forward_backward", "two_view", "relative_pose", "triangulate", "rotation_parallax_deg",
           "best_rotation"]

# KLT: window (px) and pyramid levels above the image; forward-backward tolerance (px).
KLT_WINDOW = 11
KLT_LEVELS = 3
KLT_FB_PX = 1.0
# a chained track is refined straight from the reference image when the two agree within this (px)
KLT_REFINE_PX = 2.0
# goodFeaturesToTrack: corners weaker than this fraction of the strongest are not taken.
CORNER_QUALITY = 0.01
# Triangulated points whose two rays meet at less than this fraction of init_min_parallax_deg are dropped.
POINT_ANGLE_FRACTION = 0.2


@dataclasses.dataclass(frozen=True)
class TwoView:
    """The outcome of one initialisation attempt.

    ``ok``: the geometry is well conditioned and the fields below describe it; else ``reason`` says
    in one line why not (and the arrays are empty). ``T_ref_cur``: the current camera in the
    reference camera (p_ref = T_ref_cur.apply(p_cur)), its translation in the scale where the points'
    median depth is 1. ``pixels`` (N, 2): reference-image pixels of the triangulated points;
    ``idepth`` (N,): their inverse depths in the reference camera. ``parallax_deg``: median parallax
    angle (after removing the rotation); ``tracks``: corners still tracked; ``inliers``: essential-
    matrix inliers; ``frames``: frames between the reference and the current one; ``restart``: the
    reference has too few corners left to ever succeed, start again from a later frame.
    """

    ok: bool
    reason: str
    T_ref_cur: Pose | None
    pixels: Float[np.ndarray, "n 2"]
    idepth: Float[np.ndarray, " n"]
    parallax_deg: float
    tracks: int
    inliers: int
    frames: int = 0
    restart: bool = False


def _failed(reason: str, frames: int, tracks: int, parallax_deg: float = 0.0, inliers: int = 0) -> TwoView:
    """A not-ok TwoView with empty point arrays."""
    return TwoView(False, reason, None, np.zeros((0, 2), np.float32), np.zeros(0, np.float32), float(parallax_deg),
                   int(tracks), int(inliers), frames)


def _to_uint8(image: Float[np.ndarray, "H W"]) -> UInt8[np.ndarray, "H W"]:
    """Display values in [0, 1] as the 8-bit image KLT and the corner detector read."""
    return np.clip(np.rint(np.asarray(image, np.float32) * 255.0), 0, 255).astype(np.uint8)


def detect_corners(image: Float[np.ndarray, "H W"], config: MonoConfig) -> Float[np.ndarray, "m 2"]:
    """Shi-Tomasi corners of a [0, 1] image: at most ``init_corners``, spread by a minimum distance
    that lets that many cover the image, and of step contrast at least ``init_corner_contrast``
    (a step corner of contrast c has a minimum structure-tensor eigenvalue of c²/4 in OpenCV's scaling)."""
    img = np.asarray(image, np.float32)
    h, w = img.shape
    strongest = float(cv2.cornerMinEigenVal(img, 3, ksize=3).max())
    floor = 0.25 * config.init_corner_contrast**2
    if not strongest > floor:
        return np.zeros((0, 2), np.float32)
    spacing = max(3.0, 0.5 * np.sqrt(h * w / config.init_corners))
    quality = min(1.0, max(CORNER_QUALITY, floor / strongest))
    found = cv2.goodFeaturesToTrack(img, config.init_corners, quality, spacing, blockSize=3)
    return np.zeros((0, 2), np.float32) if found is None else found.reshape(-1, 2).astype(np.float32)


def _klt(prev: np.ndarray, cur: np.ndarray, pts: np.ndarray, guess: np.ndarray | None = None, levels: int = KLT_LEVELS):
    """Pyramidal KLT of ``pts`` (N, 2) from 8-bit ``prev`` to ``cur`` over ``levels`` levels above the
    image, from ``guess`` (N, 2) if given: (positions (N, 2), ok (N,))."""
    flags = cv2.OPTFLOW_USE_INITIAL_FLOW if guess is not None else 0
    crit = (cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01)
    start = None if guess is None else guess.reshape(-1, 1, 2).copy()
    nxt, status, _ = cv2.calcOpticalFlowPyrLK(prev, cur, pts.reshape(-1, 1, 2), start, winSize=(KLT_WINDOW, KLT_WINDOW),
                                              maxLevel=levels, criteria=crit, flags=flags)
    return nxt.reshape(-1, 2), status.reshape(-1).astype(bool)


def track_forward_backward(prev: np.ndarray, cur: np.ndarray, pts: Float[np.ndarray, "n 2"]):
    """KLT of ``pts`` from 8-bit ``prev`` to ``cur`` and back: (positions (n, 2) in ``cur``, ok (n,)),
    ok where both directions converged, the round trip returns within ``KLT_FB_PX`` and the point
    stays inside the image."""
    if len(pts) == 0:
        return pts, np.zeros(0, bool)
    fwd, ok_f = _klt(prev, cur, pts)
    back, ok_b = _klt(cur, prev, fwd)
    h, w = cur.shape
    inside = (fwd[:, 0] >= 0) & (fwd[:, 1] >= 0) & (fwd[:, 0] <= w - 1) & (fwd[:, 1] <= h - 1)
    close = np.linalg.norm(back - pts, axis=1) < KLT_FB_PX
    return fwd.astype(np.float32), ok_f & ok_b & inside & close


@dataclasses.dataclass(frozen=True)
class Tracks:
    """Corners of a reference frame and where they are now.

    ``ref`` (M, 2): the corners in the reference image; ``cur`` (M, 2): their positions in the
    latest image (meaningless where not ``alive``); ``alive`` (M,): still tracked; ``ref_image`` and
    ``last``: the reference and the latest image, 8-bit; ``frames``: images tracked since the
    reference (0: the reference itself).
    """

    ref: Float[np.ndarray, "m 2"]
    cur: Float[np.ndarray, "m 2"]
    alive: Bool[np.ndarray, " m"]
    ref_image: UInt8[np.ndarray, "H W"]
    last: UInt8[np.ndarray, "H W"]
    frames: int


def start_tracks(image: Float[np.ndarray, "H W"], config: MonoConfig) -> Tracks:
    """Tracks of a new reference frame: its corners, all alive, where they are."""
    corners = detect_corners(image, config)
    image8 = _to_uint8(image)
    return Tracks(corners, corners.copy(), np.ones(len(corners), bool), image8, image8, 0)


def advance_tracks(tracks: Tracks, image: Float[np.ndarray, "H W"]) -> Tracks:
    """The tracks one image later: the alive corners tracked from the previous image (KLT,
    forward-backward checked); lost ones stay dead."""
    cur8 = _to_uint8(image)
    idx = np.flatnonzero(tracks.alive)
    moved, ok = track_forward_backward(tracks.last, cur8, tracks.cur[idx])
    if ok.any():  # refine straight from the reference, starting from the chained positions: no drift
        direct, ok_d = _klt(tracks.ref_image, cur8, tracks.ref[idx], guess=moved, levels=1)
        agree = ok_d & (np.linalg.norm(direct - moved, axis=1) < KLT_REFINE_PX)
        moved = np.where(agree[:, None], direct, moved).astype(np.float32)
    cur, alive = tracks.cur.copy(), np.zeros_like(tracks.alive)
    cur[idx[ok]] = moved[ok]
    alive[idx[ok]] = True
    return Tracks(tracks.ref, cur, alive, tracks.ref_image, cur8, tracks.frames + 1)


def _unit_rays(K: np.ndarray, pixels: np.ndarray) -> Float[np.ndarray, "n 3"]:
    """Unit-length rays (n, 3), float64, through ``pixels`` (n, 2) of a camera with intrinsics K."""
    h = np.concatenate([np.asarray(pixels, np.float64), np.ones((len(pixels), 1))], axis=1)
    rays = h @ np.linalg.inv(K).T
    return rays / np.linalg.norm(rays, axis=1, keepdims=True)


def _angles_deg(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angles (deg) between rows of unit vectors a and b (n, 3), accurate for small angles."""
    return np.degrees(2.0 * np.arcsin(np.clip(0.5 * np.linalg.norm(a - b, axis=1), 0.0, 1.0)))


def best_rotation(a: Float[np.ndarray, "n 3"], b: Float[np.ndarray, "n 3"]) -> Float[np.ndarray, "3 3"]:
    """The rotation R minimising Σ |a_i − R b_i|² over unit rays (Wahba's problem, by SVD with the
    reflection fix), refitted twice on the rays within 3x the median residual (robust to bad tracks)."""
    use = np.ones(len(a), bool)
    for _ in range(3):
        U, _, Vt = np.linalg.svd(a[use].T @ b[use])
        R = U @ np.diag([1.0, 1.0, np.sign(np.linalg.det(U @ Vt))]) @ Vt
        res = np.linalg.norm(a - b @ R.T, axis=1)
        use = res <= 3.0 * np.median(res) + 1e-12
    return R


def rotation_parallax_deg(a: Float[np.ndarray, "n 3"], b: Float[np.ndarray, "n 3"]) -> float:
    """Median angle (deg) between the reference rays ``a`` and the current rays ``b`` once the
    rotation that best explains them is removed: ~0 for a camera that only rotates, whatever the
    rotation; about the least parallax any rotation leaves, so at most about the parallax left by
    the essential matrix's rotation."""
    return float(np.median(_angles_deg(a, b @ best_rotation(a, b).T)))


@dataclasses.dataclass(frozen=True)
class Triangulated:
    """Points seen in two cameras: ``points`` (n, 3) in the reference camera, ``angle_deg`` (n,) the
    angle between their two viewing rays, ``ok`` (n,): in front of both cameras, reprojected within
    ``max_px`` in both images, and seen under at least the smallest usable angle."""

    points: Float[np.ndarray, "n 3"]
    angle_deg: Float[np.ndarray, " n"]
    ok: Bool[np.ndarray, " n"]


def _reprojection_px(P: np.ndarray, X: np.ndarray, px: np.ndarray) -> np.ndarray:
    """Distances (n,) between the projections of points X (n, 3) by P (3, 4) and pixels px (n, 2)."""
    x = np.concatenate([X, np.ones((len(X), 1))], axis=1) @ P.T
    z = np.where(np.abs(x[:, 2:]) > 1e-12, x[:, 2:], 1e-12)
    return np.linalg.norm(x[:, :2] / z - px, axis=1)


def triangulate(ref: Float[np.ndarray, "n 2"], cur: Float[np.ndarray, "n 2"], K: Float[np.ndarray, "3 3"],
                R: Float[np.ndarray, "3 3"], t: Float[np.ndarray, "3"], min_angle_deg: float, max_px: float) -> Triangulated:
    """Linear triangulation (``cv2.triangulatePoints``) of matched pixels of the reference camera
    K[I|0] and the current camera K[R|t] (x_cur = R x_ref + t), with the checks of :class:`Triangulated`."""
    P1 = K @ np.hstack([np.eye(3), np.zeros((3, 1))])
    P2 = K @ np.hstack([R, t.reshape(3, 1)])
    X4 = cv2.triangulatePoints(P1, P2, np.asarray(ref, np.float64).T, np.asarray(cur, np.float64).T).T
    w = np.where(np.abs(X4[:, 3:]) > 1e-12, X4[:, 3:], 1e-12)
    X = X4[:, :3] / w
    z_cur = X @ R[2] + t[2]
    centre_cur = -R.T @ t  # the current camera's centre in the reference camera
    a = X / np.maximum(np.linalg.norm(X, axis=1, keepdims=True), 1e-12)
    b = X - centre_cur
    b = b / np.maximum(np.linalg.norm(b, axis=1, keepdims=True), 1e-12)
    angle = _angles_deg(a, b)
    err = np.maximum(_reprojection_px(P1, X, ref), _reprojection_px(P2, X, cur))
    ok = np.isfinite(X).all(axis=1) & (X[:, 2] > 0) & (z_cur > 0) & (angle >= min_angle_deg) & (err <= max_px)
    return Triangulated(X, angle, ok)


@dataclasses.dataclass(frozen=True)
class RelativePose:
    """The essential matrix's motion: x_cur = R x_ref + t with |t| = 1; ``ransac`` (n,): its RANSAC
    inliers; ``front`` (n,): the inliers ``cv2.recoverPose`` finds in front of both cameras."""

    R: Float[np.ndarray, "3 3"]
    t: Float[np.ndarray, "3"]
    ransac: Bool[np.ndarray, " n"]
    front: Bool[np.ndarray, " n"]


def relative_pose(ref: Float[np.ndarray, "n 2"], cur: Float[np.ndarray, "n 2"], K: Float[np.ndarray, "3 3"],
                  ransac_px: float) -> RelativePose | None:
    """Essential matrix from matched pixels by the 5-point solver in RANSAC, decomposed by
    ``cv2.recoverPose``; None when OpenCV finds no model. The RANSAC is OpenCV's USAC_ACCURATE, which
    re-fits the model on its inliers (local optimisation): plain RANSAC keeps the best minimal
    sample's model, whose rotation is visibly off on small images."""
    ref, cur = np.asarray(ref, np.float64), np.asarray(cur, np.float64)
    E, mask = cv2.findEssentialMat(ref, cur, K, cv2.USAC_ACCURATE, 0.999, ransac_px)
    if E is None or E.shape[0] < 3 or mask is None:
        return None
    _, R, t, front = cv2.recoverPose(E[:3], ref, cur, K, mask=mask.copy())
    return RelativePose(R, t.reshape(3), mask.reshape(-1) > 0, front.reshape(-1) > 0)


def _scaled_result(ref: np.ndarray, motion: RelativePose, tri: Triangulated, parallax: float, tracks: int,
                   frames: int) -> TwoView:
    """The ok TwoView: the triangulated points and translation scaled so that the median depth is 1."""
    depth = tri.points[tri.ok, 2]
    scale = float(np.median(depth))
    T_cur_ref = np.eye(4)
    T_cur_ref[:3, :3], T_cur_ref[:3, 3] = motion.R, motion.t / scale
    T_ref_cur = Pose.from_matrix(jnp.asarray(np.linalg.inv(T_cur_ref), jnp.float32))
    return TwoView(True, "", T_ref_cur, ref[tri.ok].astype(np.float32), (scale / depth).astype(np.float32), parallax,
                   tracks, int(motion.ransac.sum()), frames)


def two_view(ref: Float[np.ndarray, "n 2"], cur: Float[np.ndarray, "n 2"], camera: PinholeCamera, config: MonoConfig,
             frames: int = 0) -> TwoView:
    """Relative pose and reference inverse depths up to scale from matched pixels of the reference
    and the current image, or the reason why the pair does not determine them, checked in this order:
    too few tracks; too little parallax once the best rotation is removed (a cheap test that pure
    rotation fails); too few essential-matrix inliers; too few points triangulated; too small a
    median angle between their rays. ``frames`` is passed through to the result."""
    n, need, min_deg = len(ref), config.init_min_tracks, config.init_min_parallax_deg
    if n < need:
        return dataclasses.replace(_failed(f"too little texture: {n} corners tracked (need {need})", frames, n), restart=True)
    K = np.asarray(camera.K(), np.float64)
    coarse = rotation_parallax_deg(_unit_rays(K, ref), _unit_rays(K, cur))
    if coarse < min_deg:
        return _failed(f"too little parallax: {coarse:.2f} deg (need {min_deg:g}; rotation only?)", frames, n, coarse)
    motion = relative_pose(ref, cur, K, config.init_ransac_px)
    if motion is None:
        return _failed("two-view geometry failed: no essential matrix", frames, n, coarse)
    ratio, inliers = float(motion.ransac.mean()), int(motion.ransac.sum())
    if ratio < config.init_min_inlier_ratio:
        return _failed(f"two-view geometry failed: {100 * ratio:.0f} % inliers (need {100 * config.init_min_inlier_ratio:.0f} %)",
                       frames, n, coarse, inliers)
    ref64, cur64 = np.asarray(ref, np.float64)[motion.front], np.asarray(cur, np.float64)[motion.front]
    tri = triangulate(ref64, cur64, K, motion.R, motion.t, POINT_ANGLE_FRACTION * min_deg, 2.0 * config.init_ransac_px)
    good = int(tri.ok.sum())
    parallax = float(np.median(tri.angle_deg[tri.ok])) if good else 0.0
    if good < need:
        return _failed(f"two-view geometry failed: {good} points triangulated (need {need})", frames, n, parallax, inliers)
    if parallax < min_deg:
        return _failed(f"too little parallax: {parallax:.2f} deg between the triangulated rays (need {min_deg:g})", frames, n,
                       parallax, inliers)
    return _scaled_result(np.asarray(ref, np.float32)[motion.front], motion, tri, parallax, n, frames)


@dataclasses.dataclass(frozen=True)
class TwoViewTracker:
    """Initialisation state over incoming frames: the camera, the settings and the reference frame's
    :class:`Tracks`. ``start(image, ...)`` makes ``image`` the reference; ``update(image)`` once per
    later frame returns the next state and the frame's :class:`TwoView`.

    The reference never changes inside: the caller starts again from a later frame (after
    ``init_max_frames`` frames without success, or at once when a result says ``restart``).
    """

    camera: PinholeCamera
    config: MonoConfig
    tracks: Tracks

    @staticmethod
    def start(image: Float[np.ndarray, "H W"], camera: PinholeCamera, config: MonoConfig) -> "TwoViewTracker":
        """A tracker whose reference is ``image`` (its corners, all alive)."""
        return TwoViewTracker(camera, config, start_tracks(image, config))

    def update(self, image: Float[np.ndarray, "H W"]) -> "tuple[TwoViewTracker, TwoView]":
        """Track the reference corners into ``image`` and try the two-view geometry."""
        tracks = advance_tracks(self.tracks, image)
        result = two_view(tracks.ref[tracks.alive], tracks.cur[tracks.alive], self.camera, self.config, tracks.frames)
        return dataclasses.replace(self, tracks=tracks), result
