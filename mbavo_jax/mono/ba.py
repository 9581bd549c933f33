"""Windowed photometric bundle adjustment over keyframes (DSO's back-end, MBA-VO supplement §6),
with the inverse depths eliminated by the Schur complement and DSO's marginalisation.

A residual is one pattern pixel x_k = x + o_k (``tracking.points.PATTERN``) of a point hosted by
keyframe h, seen in another keyframe t of the window (DSO, with the point's one inverse depth ρ):

    p   = R_th π⁻¹(x_k) + ρ t_th        (T_th = T_world_t⁻¹ T_world_h; p ∝ the point in t)
    r_k = I_t(π(p)) − [e^(a_t − a_h) (I_h(x_k) − b_h) + b_t]

With ``samples`` > 1 (``mono.ba_blur_samples``) the residual is blur-aware: I_t is target t's frame
as recorded (``Window.raw``, blurry) and I_h(x_k) is replaced by the host image blurred as t recorded
it (Eq. 6: ``samples`` virtual frames along t's exposure path, ``Window.exposure``, through the host's
frontal-parallel plane at the point's depth, at t's pixel of x_k). Its middle sample is x_k itself
for any state, so these predictions are computed once per solve and held (like I_h(x_k)): only the
shape of the blur, not its place, depends on the variables.

A (point, target) pair is one block of 8 residuals; its Jacobian (8 x 17) is taken by autodiff with
respect to [host pose (6), host affine (2), target pose (6), target affine (2), ρ (1)], pose
increments as in ``Pose.plus``. A pair with a pixel out of the image or behind a camera is masked;
a visible pair whose pattern RMS exceeds the outlier threshold is an outlier. The cost is Huber's
on inlier pairs; a masked or outlier pair of a valid point costs the constant 8 ρ(outlier), so
that the cost is one function of the state and LM steps can be accepted or rejected on it.

Gauge (7 free directions: pose and scale; the affine brightness adds a common offset of all a and
of all b). Without a marginalisation prior the window is held by an ``Anchor``: a prior on the oldest
valid keyframe's pose and affine brightness, and a prior on the distance between the camera centres
of the two oldest valid keyframes, both at their values when the solve starts and 1e3 x as stiff as
the mean data diagonal of the variable (these directions carry no data, so their stiffness does not
bias the rest; it keeps float32 Cholesky well conditioned). Both act on keyframe variables only, so
the inverse-depth block stays diagonal. With a prior the prior holds pose and affine (the first
marginalisation folds the anchor into it); the distance prior stays, at the distance of the prior's
linearisation point (the state at the last marginalisation), because the scale information a prior
carries is weak over the short baselines of a window. Marginalisation folds the distance prior into
the prior only while there is none.
"""

from __future__ import annotations

import dataclasses
import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import cho_factor, cho_solve
from jaxtyping import Array, Bool, Float, Int

from ..config import MonoConfig
from ..errors import ArgumentError
from ..blur import synthesize, virtual_pq
from ..geometry.camera import PinholeCamera
from ..geometry.pose import Pose
from ..geometry.trajectory import ExposureTrajectory
from ..image import bilinear
from ..tracking.points import PATTERN
from .window import VARS, Prior, Window, pose_delta, set_slot_pose

__all__ = ["HostValues", "host_values", "Linearization", "NormalEquations", "Anchor", "BAReport", "linearize", "normal_equations", "make_anchor",
           "camera_terms", "system", "reduce_points", "schur_solve", "dense_solve", "marginalize_slot", "apply_increment",
           "residual_vector", "bundle_adjust", "marginalize", "BLOCK"]

def _full_precision(fn):
    """``fn`` traced with float32 matrix products at full precision (no TF32 / bf16 passes on
    accelerators): the normal equations and the Schur complement cancel large terms."""

    @functools.wraps(fn)
    def wrapped(*args, **kwargs):
        with jax.default_matmul_precision("highest"):
            return fn(*args, **kwargs)

    return wrapped


BLOCK = 2 * VARS + 1  # Jacobian columns of a (point, target) block: host (8), target (8), inverse depth (1)
GAUGE_STRENGTH = 1e3  # the oldest keyframe's prior, relative to the mean data diagonal of each variable


class Linearization(eqx.Module):
    """Residuals of every (point, target) pair and their block Jacobians (zero where not visible)."""

    J: Float[Array, "P K 8 17"]  # columns: host [pose 6, affine 2], target [pose 6, affine 2], ρ
    r: Float[Array, "P K 8"]
    w: Float[Array, "P K 8"]  # Huber weight on inlier pairs, 0 elsewhere
    visible: Bool[Array, "P K"]
    inlier: Bool[Array, "P K"]
    energy: Float[Array, ""]  # robust photometric cost


class NormalEquations(eqx.Module):
    """``[[H_cc, H_cdᵀ], [H_cd, diag(H_dd)]] [Δc; Δd] = −[b_c; b_d]`` with M = 8K keyframe variables
    (slot-major: pose 6, affine 2) and P inverse depths."""

    H_cc: Float[Array, "M M"]
    H_cd: Float[Array, "P M"]
    H_dd: Float[Array, "P"]
    b_c: Float[Array, "M"]
    b_d: Float[Array, "P"]


class Anchor(eqx.Module):
    """The gauge priors (module text): the pin of the oldest keyframe (only while the window has no
    marginalisation prior) and the distance prior between the two oldest keyframes."""

    slot0: Int[Array, ""]  # oldest valid keyframe
    slot1: Int[Array, ""]  # second oldest
    pose: Pose  # the oldest keyframe's pose and affine to hold
    affine: Float[Array, "2"]
    distance: Float[Array, ""]  # |c1 - c0| to hold
    weights: Float[Array, "8"]
    scale_weight: Float[Array, ""]
    pin: Bool[Array, ""]  # hold the oldest keyframe's pose and affine (no prior yet)


class BAReport(eqx.Module):
    """What one bundle adjustment did (scalars; RMS over the residuals of inlier pairs)."""

    rms_before: Float[Array, ""]
    rms_after: Float[Array, ""]
    energy_before: Float[Array, ""]
    energy_after: Float[Array, ""]
    accepted: Int[Array, ""]  # accepted LM iterations
    residuals: Int[Array, ""]  # inlier residuals (pattern pixels) after the solve
    outliers: Int[Array, ""]  # visible (point, target) pairs over the outlier threshold after the solve
    dropped: Int[Array, ""]  # points invalidated after the solve


# ----------------------------------------------------------------------------- residuals


def _pattern(dtype) -> Float[Array, "8 2"]:
    return jnp.asarray(PATTERN, dtype)


class HostValues(eqx.Module):
    """What each point's pattern predicts in its targets, held through one solve: the host's values
    (sharp model, (P, 8) for every target), or the host's image blurred along each target's exposure
    path ((P, K, 8))."""

    values: Float[Array, "P 8"] | Float[Array, "P K 8"]
    ok: Bool[Array, "P 8"] | Bool[Array, "P K 8"]
    blurred: bool = eqx.field(static=True)  # targets are then compared in their recorded (blurry) images


def _sharp_host_values(window: Window):
    """Each point's pattern in its host image: values (P, 8) and validity (P, 8). Every image is
    sampled at every point (no per-point image gather), then the host's row is taken."""
    pat = _pattern(window.pixels.dtype)
    sample = lambda img, x: jax.vmap(lambda o: bilinear(img, x + o))(pat)
    vals, ok = jax.vmap(lambda img: jax.vmap(lambda x: sample(img, x))(window.pixels))(window.images)
    host = jnp.clip(window.host, 0, window.slots - 1)
    idx = jnp.arange(window.capacity)
    return vals[host, idx], ok[host, idx]


def _blurred_pattern(stack, camera: PinholeCamera, T_wt: Pose, path_t: ExposureTrajectory, T_wh: Pose, row0, pixel, idepth,
                     samples: int):
    """One point's pattern as target t recorded it (Eq. 6): the host image (rows ``row0`` of the
    image ``stack``) along t's exposure path ``path_t`` (about T_wt) with ``samples`` virtual frames,
    through the host's frontal-parallel plane at the point's depth; values (8,), validity (8,)."""
    T_ht = T_wh.inverse().compose(T_wt)
    x_t, front = _project_pattern(camera, T_ht.inverse(), pixel, idepth)
    path = path_t.seen_from(T_ht)  # the target's virtual cameras in the host
    rays = jax.vmap(camera.unit_ray)(x_t)
    depth = jnp.full(x_t.shape[0], 1.0 / jnp.maximum(idepth, 1e-6))
    rows = jnp.zeros(x_t.shape[0], jnp.int32)
    values, ok = synthesize(stack, camera, virtual_pq(path, samples)[None], rays, depth, rows, row0)
    return values, ok & front


def host_values(window: Window, camera: PinholeCamera, samples: int = 1) -> HostValues:
    """The predictions of every (point, target) pair: sharp (``samples`` ≤ 1: the host's values,
    the paper's back-end on deblurred keyframes) or blurred along each target's exposure path with
    ``samples`` virtual frames (module text)."""
    vals, ok = _sharp_host_values(window)
    k = window.slots
    if samples <= 1:
        return HostValues(vals, ok, False)
    if not window.recorded:
        raise ArgumentError(f"a blur-aware adjustment ({samples} virtual frames) needs the keyframes' recorded frames: "
                            "make the window with Window.empty(..., recorded=True)")
    height = window.images.shape[1]
    stack = window.images.reshape(k * height, -1)
    host = jnp.clip(window.host, 0, k - 1)
    T_wh = Pose(window.poses.q[host], window.poses.t[host])
    blur = functools.partial(_blurred_pattern, stack, camera, samples=samples)
    points = jax.vmap(blur, in_axes=(None, None, 0, 0, 0, 0))
    bv, bok = jax.vmap(points, in_axes=(0, 0, None, None, None, None))(window.poses, window.exposure, T_wh, host * height,
                                                                       window.pixels, window.idepth)
    return HostValues(jnp.swapaxes(bv, 0, 1), jnp.swapaxes(bok, 0, 1) & ok[:, None], True)


def _project(camera: PinholeCamera, R, t, x, idepth):
    """Host pixel x on the point's plane (inverse depth ``idepth``) in target t (``R``, ``t``: T_th):
    its pixel (2,) and whether it is in front of the target camera (with a positive inverse depth)."""
    ray = jnp.stack([(x[0] - camera.cx) / camera.fx, (x[1] - camera.cy) / camera.fy, jnp.ones_like(x[0])])
    p = R @ ray + idepth * t
    front = (p[2] > 1e-6) & (idepth > 0)
    z = jnp.where(front, p[2], jnp.ones_like(p[2]))
    return jnp.stack([camera.fx * p[0] / z + camera.cx, camera.fy * p[1] / z + camera.cy]), front


def _project_pattern(camera: PinholeCamera, T_th: Pose, pixel, idepth):
    """The 8 pattern pixels of a point (host pixel, inverse depth) in target t: pixels (8, 2) and
    their front flags (:func:`_project`)."""
    R = T_th.rotation()
    return jax.vmap(lambda o: _project(camera, R, T_th.t, pixel + o, idepth))(_pattern(pixel.dtype))


def _pattern_residuals(target, camera: PinholeCamera, T_wt: Pose, aff_t, T_wh: Pose, aff_h, pixel, idepth, host_vals,
                       host_ok):
    """The 8 residuals of one point (pixel, inverse depth, predicted values) in one target image, and
    their validity (in both images, in front of the target camera, positive inverse depth)."""
    T_th = T_wt.inverse().compose(T_wh)
    R = T_th.rotation()
    gain = jnp.exp(aff_t[0] - aff_h[0])

    def one(offset, i_h, ok_h):
        x_t, front = _project(camera, R, T_th.t, pixel + offset, idepth)
        i_t, ok_t = bilinear(target, x_t)
        return i_t - (gain * (i_h - aff_h[1]) + aff_t[1]), ok_t & ok_h & front

    return jax.vmap(one)(_pattern(pixel.dtype), host_vals, host_ok)


def _block(target, camera, T_wt: Pose, aff_t, T_wh: Pose, aff_h, pixel, idepth, host_vals, host_ok, inc):
    """``_pattern_residuals`` at the block increment ``inc`` (17,): (r, (r, valid))."""
    r, ok = _pattern_residuals(target, camera, T_wt.plus(inc[8:14]), aff_t + inc[14:16], T_wh.plus(inc[0:6]),
                               aff_h + inc[6:8], pixel, idepth + inc[16], host_vals, host_ok)
    return r, (r, ok)


def _structural(window: Window) -> Bool[Array, "P K"]:
    """Pairs that exist: valid point, valid host and target, target ≠ host."""
    slots = jnp.arange(window.slots, dtype=window.host.dtype)
    host = jnp.clip(window.host, 0, window.slots - 1)
    return (window.point_valid & window.kf_valid[host])[:, None] & window.kf_valid[None, :] & (host[:, None] != slots[None, :])


def _evaluate(window: Window, camera: PinholeCamera, jacobian: bool, host_vals: HostValues):
    """Residuals (P, K, 8), pixel validity (P, K, 8) and, if asked, block Jacobians (P, K, 8, 17) of every
    (point, target) pair against the predictions ``host_vals``. Targets are the outer map so that
    each lane samples one image."""
    host = jnp.clip(window.host, 0, window.slots - 1)
    T_wh = Pose(window.poses.q[host], window.poses.t[host])
    aff_h = window.affine[host]
    zero = jnp.zeros(BLOCK, window.idepth.dtype)

    def pair(target, T_wt, aff_t, T_h, a_h, x, d, hv, hok):
        f = functools.partial(_block, target, camera, T_wt, aff_t, T_h, a_h, x, d, hv, hok)
        if jacobian:
            J, (r, ok) = jax.jacfwd(f, has_aux=True)(zero)
            return r, ok, J
        _, (r, ok) = f(zero)
        return r, ok, None

    points = jax.vmap(pair, in_axes=(None, None, None, 0, 0, 0, 0, 0, 0))
    per_target = 1 if host_vals.blurred else None
    targets = jax.vmap(points, in_axes=(0, 0, 0, None, None, None, None, per_target, per_target))
    images = window.raw if host_vals.blurred else window.images
    r, ok, J = targets(images, window.poses, window.affine, T_wh, aff_h, window.pixels, window.idepth,
                       host_vals.values, host_vals.ok)
    swap = lambda a: None if a is None else jnp.swapaxes(a, 0, 1)
    return swap(r), swap(ok), swap(J)


def _huber(r, k):
    """Huber's cost ρ and IRLS weight of residuals r with threshold k."""
    a = jnp.abs(r)
    small = a <= k
    rho = jnp.where(small, 0.5 * r * r, k * (a - 0.5 * k))
    w = jnp.where(small, jnp.ones_like(a), k / jnp.where(small, jnp.ones_like(a), a))
    return rho, w


def _robust(r, visible, structural, huber, outlier):
    """Inlier pairs, Huber weights (P, K, 8) and the robust cost (module text)."""
    rms = jnp.sqrt(jnp.mean(r * r, axis=-1))
    inlier = visible & (rms <= outlier)
    rho, w = _huber(r, huber)
    cap = 8.0 * _huber(jnp.asarray(outlier, r.dtype), huber)[0]
    pair = jnp.where(inlier, rho.sum(-1), jnp.where(structural, cap, jnp.zeros_like(cap)))
    return inlier, jnp.where(inlier[..., None], w, jnp.zeros_like(w)), pair.sum()


def _visible(window, ok):
    return _structural(window) & jnp.all(ok, axis=-1)


@_full_precision
def linearize(window: Window, camera: PinholeCamera, huber, outlier, host: HostValues | None = None) -> Linearization:
    """Residuals, block Jacobians, Huber weights, masks and the robust cost at the window's state
    against the predictions ``host`` (None: the sharp model's)."""
    host = host_values(window, camera) if host is None else host
    r, ok, J = _evaluate(window, camera, True, host)
    visible = _visible(window, ok)
    r = jnp.where(visible[..., None], r, jnp.zeros_like(r))
    J = jnp.where(visible[..., None, None], J, jnp.zeros_like(J))
    inlier, w, energy = _robust(r, visible, _structural(window), huber, outlier)
    return Linearization(J, r, w, visible, inlier, energy)


@_full_precision
def _photometric_energy(window: Window, camera: PinholeCamera, huber, outlier, host: HostValues):
    """The robust cost alone (no Jacobians), with the inlier and visible masks."""
    r, ok, _ = _evaluate(window, camera, False, host)
    visible = _visible(window, ok)
    r = jnp.where(visible[..., None], r, jnp.zeros_like(r))
    inlier, _, energy = _robust(r, visible, _structural(window), huber, outlier)
    return energy, r, visible, inlier


def apply_increment(window: Window, dc: Float[Array, "M"], dd: Float[Array, "P"]) -> Window:
    """The window's variables moved by Δc (8K: per slot [Δr, Δt, Δa, Δb], ``Pose.plus``) and Δd (P,
    inverse depths); invalid slots and points are left as they are."""
    dc = dc.reshape(window.slots, VARS)
    moved = jax.vmap(lambda T, d: T.plus(d))(window.poses, dc[:, :6])
    keep = window.kf_valid
    poses = Pose(jnp.where(keep[:, None], moved.q, window.poses.q), jnp.where(keep[:, None], moved.t, window.poses.t))
    affine = jnp.where(keep[:, None], window.affine + dc[:, 6:], window.affine)
    idepth = jnp.where(window.point_valid, window.idepth + dd, window.idepth)
    return dataclasses.replace(window, poses=poses, affine=affine, idepth=idepth)


@_full_precision
def residual_vector(window: Window, camera: PinholeCamera, increment: Float[Array, "N"] | None = None,
                    samples: int = 1) -> Float[Array, "R"]:
    """All residuals (P·K·8, ordered point, target, pattern pixel; zero where a pair is not visible) at
    the window moved by ``increment`` = [Δc (8K), Δd (P)] (zero when None), against the predictions
    of the unmoved window (``host_values`` with ``samples``): ``jax.jacfwd`` of this is the full
    Jacobian the structured blocks must reproduce."""
    m = VARS * window.slots
    host = host_values(window, camera, samples)
    if increment is not None:
        window = apply_increment(window, increment[:m], increment[m:])
    r, ok, _ = _evaluate(window, camera, False, host)
    visible = _visible(window, ok)
    return jnp.where(visible[..., None], r, jnp.zeros_like(r)).reshape(-1)


# ------------------------------------------------------------------------- normal equations


def _segment(x, ids, n):
    return jax.ops.segment_sum(x, ids, num_segments=n)


def _camera_blocks(A, g, host, k: int):
    """H_cc (8K x 8K) and b_c (8K) from the per-block products A = JᵀWJ (P, K, 17, 17) and g = JᵀWr
    (P, K, 17): host-host sums scattered by host, target-target sums by target slot (the block's own
    axis), host-target blocks scattered by host into (K, K)."""
    v = VARS
    diag = A[..., v:2 * v, v:2 * v].sum(0) + _segment(A[..., :v, :v].sum(1), host, k)  # (K, 8, 8)
    off = _segment(A[..., :v, v:2 * v], host, k)  # (K_host, K_target, 8, 8)
    eye = jnp.eye(k, dtype=A.dtype)[:, :, None, None]
    blocks = off + jnp.swapaxes(jnp.swapaxes(off, 0, 1), 2, 3) + eye * diag[:, None]
    H_cc = jnp.transpose(blocks, (0, 2, 1, 3)).reshape(k * v, k * v)
    b_c = g[..., v:2 * v].sum(0) + _segment(g[..., :v].sum(1), host, k)
    return H_cc, b_c.reshape(-1)


@_full_precision
def normal_equations(lin: Linearization, window: Window) -> NormalEquations:
    """The photometric normal equations assembled from the block Jacobians (Gauss-Newton with the
    Huber weights): no dense Jacobian row is formed; camera blocks are summed with segment sums."""
    k, p = window.slots, window.capacity
    v = VARS
    Jw = lin.J * lin.w[..., None]
    A = jnp.einsum("pkri,pkrj->pkij", Jw, lin.J)
    g = jnp.einsum("pkri,pkr->pki", Jw, lin.r)
    host = jnp.clip(window.host, 0, k - 1)
    H_cc, b_c = _camera_blocks(A, g, host, k)
    onehot = (host[:, None] == jnp.arange(k, dtype=host.dtype)[None, :]).astype(A.dtype)
    H_cd = A[..., v:2 * v, 2 * v] + onehot[..., None] * A[..., :v, 2 * v].sum(1)[:, None, :]
    return NormalEquations(H_cc, H_cd.reshape(p, k * v), A[..., 2 * v, 2 * v].sum(1), b_c, g[..., 2 * v].sum(1))


def _safe_norm(x):
    sq = jnp.sum(x * x)
    pos = sq > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, sq, jnp.ones_like(sq))), jnp.zeros_like(sq))


def make_anchor(window: Window, data: NormalEquations, scale_with_prior: bool = True) -> Anchor:
    """The gauge anchor of ``window`` (module text), weighted by the mean data diagonal over the valid
    keyframes: the pin only without a marginalisation prior, the distance prior also with one unless
    ``scale_with_prior`` is False. The distance held is the current one, or with a prior that informs
    both keyframes, the one at the prior's linearisation point (the last marginalisation)."""
    k = window.slots
    big = jnp.iinfo(jnp.int32).max
    order = jnp.argsort(jnp.where(window.kf_valid, window.stamp, big))
    s0, s1 = order[0], order[1]
    n = window.kf_valid.sum()
    valid = window.kf_valid.astype(data.H_cc.dtype)
    diag = jnp.diagonal(data.H_cc).reshape(k, VARS)
    mean = (diag * valid[:, None]).sum(0) / jnp.maximum(valid.sum(), 1.0)
    prior = window.prior.active()
    informed = jnp.any(window.prior.H != 0, axis=1).reshape(k, VARS).any(1)
    at_lin = prior & informed[s0] & informed[s1]
    centres = jnp.where(at_lin, window.prior.poses.t, window.poses.t)
    distance = _safe_norm(centres[s1] - centres[s0])
    scale_ok = (n >= 2) & (distance > 1e-9) & (scale_with_prior | ~prior)
    scale_weight = jnp.where(scale_ok, GAUGE_STRENGTH * jnp.mean(mean[3:6]), jnp.zeros_like(distance))
    pose0 = Pose(window.poses.q[s0], window.poses.t[s0])
    return Anchor(s0, s1, pose0, window.affine[s0], distance, GAUGE_STRENGTH * mean + 1.0, scale_weight,
                  ~prior & (n >= 1))


def _anchor_residual(anchor: Anchor, poses: Pose, affine) -> Float[Array, "9"]:
    """sqrt-weighted [oldest keyframe's pose and affine from the held ones (8), camera distance (1)]."""
    T0 = Pose(poses.q[anchor.slot0], poses.t[anchor.slot0])
    held = jnp.concatenate([pose_delta(T0, anchor.pose), affine[anchor.slot0] - anchor.affine]) * jnp.sqrt(anchor.weights)
    held = jnp.where(anchor.pin, held, jnp.zeros_like(held))
    dist = _safe_norm(poses.t[anchor.slot1] - poses.t[anchor.slot0]) - anchor.distance
    return jnp.concatenate([held, (jnp.sqrt(anchor.scale_weight) * dist)[None]])


def _move_cameras(window: Window, dc):
    moved = apply_increment(window, dc, jnp.zeros_like(window.idepth))
    return moved.poses, moved.affine


@_full_precision
def camera_terms(window: Window, anchor: Anchor):
    """The keyframe-only terms at the window's state: the marginalisation prior (its gradient moved to
    the current state: b + H δ) and the anchor (Gauss-Newton of its residual). ``(H, b, energy)``."""
    prior = window.prior
    informed = jnp.any(prior.H != 0, axis=1) | (prior.b != 0)
    delta = prior.delta(window.poses, window.affine)
    delta = jnp.where(informed, delta, jnp.zeros_like(delta))
    Hd = prior.H @ delta
    e_prior = 0.5 * delta @ Hd + prior.b @ delta
    f = lambda dc: _anchor_residual(anchor, *_move_cameras(window, dc))
    zero = jnp.zeros(VARS * window.slots, delta.dtype)
    a, Ja = f(zero), jax.jacfwd(f)(zero)
    return prior.H + Ja.T @ Ja, prior.b + Hd + Ja.T @ a, e_prior + 0.5 * a @ a


def _mask_cameras(neq: NormalEquations, kf_valid) -> NormalEquations:
    """Rows and columns of invalid slots zeroed (they take part in nothing)."""
    free = jnp.repeat(kf_valid, VARS)
    both = free[:, None] & free[None, :]
    return dataclasses.replace(neq, H_cc=jnp.where(both, neq.H_cc, 0.0), H_cd=jnp.where(free[None, :], neq.H_cd, 0.0),
                               b_c=jnp.where(free, neq.b_c, 0.0))


def _with_camera_terms(window: Window, data: NormalEquations, energy, anchor: Anchor):
    H, b, e = camera_terms(window, anchor)
    neq = dataclasses.replace(data, H_cc=data.H_cc + H, b_c=data.b_c + b)
    return _mask_cameras(neq, window.kf_valid), energy + e


def system(window: Window, camera: PinholeCamera, huber, outlier, anchor: Anchor, host: HostValues | None = None):
    """The full normal equations at the window's state (photometric + prior + anchor) and the total
    cost: ``(NormalEquations, energy)``."""
    lin = linearize(window, camera, huber, outlier, host)
    return _with_camera_terms(window, normal_equations(lin, window), lin.energy, anchor)


# --------------------------------------------------------------------------------- solvers


def _damped(neq: NormalEquations, lam) -> NormalEquations:
    """Levenberg-Marquardt damping H_ii (1 + λ); a zero diagonal (invalid slot, point without
    residuals) becomes 1 so that the system stays regular and the variable does not move."""
    d = jnp.diagonal(neq.H_cc)
    add = jnp.where(d > 0, lam * d, jnp.ones_like(d))
    H_dd = jnp.where(neq.H_dd > 0, neq.H_dd * (1.0 + lam), jnp.ones_like(neq.H_dd))
    return dataclasses.replace(neq, H_cc=neq.H_cc + jnp.diag(add), H_dd=H_dd)


@_full_precision
def reduce_points(neq: NormalEquations):
    """The Schur complement over the inverse depths (their block is diagonal):
    ``H = H_cc − H_cdᵀ H_dd⁻¹ H_cd``, ``b = b_c − H_cdᵀ H_dd⁻¹ b_d`` (a zero H_dd counts as 1)."""
    inv = 1.0 / jnp.where(neq.H_dd > 0, neq.H_dd, jnp.ones_like(neq.H_dd))
    H = neq.H_cc - neq.H_cd.T @ (neq.H_cd * inv[:, None])
    b = neq.b_c - neq.H_cd.T @ (neq.b_d * inv)
    return 0.5 * (H + H.T), b


def _spd_solve(H, b):
    """H⁻¹ b by Cholesky of the Jacobi-scaled H (keyframe variables have very different units)."""
    d = jnp.diagonal(H)
    s = 1.0 / jnp.sqrt(jnp.where(d > 0, d, jnp.ones_like(d)))
    c = cho_factor(H * s[:, None] * s[None, :], lower=True)
    return cho_solve(c, b * s) * s


@_full_precision
def schur_solve(neq: NormalEquations, lam) -> tuple[Float[Array, "M"], Float[Array, "P"]]:
    """The damped Gauss-Newton step (Δc, Δd): the reduced camera system solved by Cholesky, then the
    inverse depths by back-substitution ``Δd = −H_dd⁻¹ (b_d + H_cd Δc)``."""
    neq = _damped(neq, lam)
    H, b = reduce_points(neq)
    dc = -_spd_solve(H, b)
    return dc, -(neq.b_d + neq.H_cd @ dc) / neq.H_dd


@_full_precision
def dense_solve(neq: NormalEquations, lam) -> tuple[Float[Array, "M"], Float[Array, "P"]]:
    """The same damped step from the full (8K + P) normal equations, solved densely (for tests)."""
    neq = _damped(neq, lam)
    m = neq.b_c.shape[0]
    H = jnp.block([[neq.H_cc, neq.H_cd.T], [neq.H_cd, jnp.diag(neq.H_dd)]])
    x = -jnp.linalg.solve(H, jnp.concatenate([neq.b_c, neq.b_d]))
    return x[:m], x[m:]


@_full_precision
def marginalize_slot(H: Float[Array, "M M"], b: Float[Array, "M"], slot) -> tuple[Float[Array, "M M"], Float[Array, "M"]]:
    """The Schur complement of keyframe ``slot``'s 8 variables out of (H, b); its rows and columns
    become zero. The 8 x 8 block is inverted Jacobi-scaled, by pseudo-inverse (DSO's recipe)."""
    slot = jnp.asarray(slot, jnp.int32)
    idx = slot * VARS + jnp.arange(VARS, dtype=jnp.int32)
    cols = jnp.take(H, idx, axis=1)  # (M, 8)
    Hss = cols[idx]
    d = jnp.diagonal(Hss)
    s = 1.0 / jnp.sqrt(jnp.where(d > 0, d, jnp.ones_like(d)))
    inv = s[:, None] * jnp.linalg.pinv(0.5 * (Hss + Hss.T) * s[:, None] * s[None, :]) * s[None, :]
    H = H - cols @ inv @ cols.T
    b = b - cols @ (inv @ b[idx])
    keep = jnp.arange(H.shape[0], dtype=jnp.int32) // VARS != slot
    H = jnp.where(keep[:, None] & keep[None, :], H, 0.0)
    return 0.5 * (H + H.T), jnp.where(keep, b, 0.0)


# ------------------------------------------------------------------------ bundle adjustment


class _Measured(eqx.Module):
    """The photometric state at a point of the solve: inlier sum of squares, masks (P, K)."""

    sq: Float[Array, ""]
    visible: Bool[Array, "P K"]
    inlier: Bool[Array, "P K"]


class _LMState(eqx.Module):
    window: Window
    neq: NormalEquations  # at ``window`` unless ``stale``
    anchor: Anchor  # taken from the first linearisation
    energy: Float[Array, ""]  # total cost at ``window`` (with the anchor once it has its weights)
    energy_start: Float[Array, ""]  # total cost at the start, with the anchor's weights
    measured: _Measured
    lam: Float[Array, ""]
    accepted: Int[Array, ""]
    stale: Bool[Array, ""]
    first: Bool[Array, ""]


def _select(pred, a, b):
    return jax.tree.map(lambda x, y: jnp.where(pred, x, y), a, b)


def _measure(window: Window, camera, huber, outlier, host: HostValues):
    energy, r, visible, inlier = _photometric_energy(window, camera, huber, outlier, host)
    sq = jnp.sum(jnp.where(inlier[..., None], r * r, jnp.zeros_like(r)))
    return energy, _Measured(sq, visible, inlier)


def _relinearize(state: _LMState, camera, huber, outlier, host: HostValues):
    """The normal equations and the total cost at the state's window; the first linearisation also
    fixes the anchor's weights. ``(NormalEquations, Anchor, energy)``."""
    lin = linearize(state.window, camera, huber, outlier, host)
    data = normal_equations(lin, state.window)
    anchor = _select(state.first, make_anchor(state.window, data), state.anchor)
    return *_with_camera_terms(state.window, data, lin.energy, anchor), anchor


def _lm_iteration(state: _LMState, camera, huber, outlier, host: HostValues) -> _LMState:
    """One LM iteration: relinearise if the last step was accepted, take the Schur step, accept it when
    it lowers the cost (λ halves), else keep the state (λ grows tenfold)."""
    neq, current, anchor = jax.lax.cond(state.stale, lambda s: _relinearize(s, camera, huber, outlier, host),
                                        lambda s: (s.neq, s.energy, s.anchor), state)
    dc, dd = schur_solve(neq, state.lam)
    cand = apply_increment(state.window, dc, dd)
    energy, measured = _measure(cand, camera, huber, outlier, host)
    energy = energy + camera_terms(cand, anchor)[2]
    ok = jnp.isfinite(energy) & (energy < current)
    return _LMState(_select(ok, cand, state.window), neq, anchor, jnp.where(ok, energy, current),
                    jnp.where(state.first, current, state.energy_start), _select(ok, measured, state.measured),
                    jnp.where(ok, state.lam * 0.5, state.lam * 10.0), state.accepted + ok.astype(jnp.int32), ok,
                    jnp.zeros((), bool))


def _drop_points(window: Window, visible, inlier) -> Bool[Array, "P"]:
    """Points to invalidate after a solve: outliers in more than half of their visible targets, or a
    non-positive / non-finite inverse depth (DSO drops such points)."""
    n_vis = visible.sum(1)
    n_out = (visible & ~inlier).sum(1)
    bad_depth = ~(jnp.isfinite(window.idepth) & (window.idepth > 0))
    return window.point_valid & ((2 * n_out > n_vis) | bad_depth)


def _rms(m: _Measured):
    n = 8 * m.inlier.sum()
    return jnp.sqrt(m.sq / jnp.maximum(n, 1).astype(m.sq.dtype))


def _zero_equations(window: Window) -> NormalEquations:
    m, p = VARS * window.slots, window.capacity
    z = functools.partial(jnp.zeros, dtype=window.idepth.dtype)
    return NormalEquations(z((m, m)), z((p, m)), z(p), z(m), z(p))


@functools.partial(jax.jit, static_argnames=("samples",))
@_full_precision
def _bundle_adjust(window: Window, camera: PinholeCamera, iterations, huber, outlier, lam0, samples: int):
    host = host_values(window, camera, samples)  # held through the solve (module text)
    zero = _zero_equations(window)
    anchor = make_anchor(window, zero)  # weights (and the cost with them) come with the first linearisation
    energy, measured = _measure(window, camera, huber, outlier, host)
    energy = energy + camera_terms(window, anchor)[2]
    state = _LMState(window, zero, anchor, energy, energy, measured, jnp.asarray(lam0, window.idepth.dtype),
                     jnp.zeros((), jnp.int32), jnp.ones((), bool), jnp.ones((), bool))
    state = jax.lax.fori_loop(0, iterations, lambda _, s: _lm_iteration(s, camera, huber, outlier, host), state)
    final = state.measured
    drop = _drop_points(state.window, final.visible, final.inlier)
    out = dataclasses.replace(state.window, point_valid=state.window.point_valid & ~drop)
    report = BAReport(_rms(measured), _rms(final), state.energy_start, state.energy, state.accepted,
                      8 * final.inlier.sum().astype(jnp.int32), (final.visible & ~final.inlier).sum().astype(jnp.int32),
                      drop.sum().astype(jnp.int32))
    return out, report


def bundle_adjust(window: Window, camera: PinholeCamera, config: MonoConfig, samples: int | None = None) -> tuple[Window, BAReport]:
    """``config.ba_iterations`` LM iterations of the windowed photometric bundle adjustment (one
    compiled program per window shape, dtype and ``samples``; the other settings are traced), with
    ``samples`` virtual frames of the targets' blur (None: ``config.ba_blur_samples``; 1: sharp
    keyframes); points that end as outliers in most of their targets are invalidated."""
    samples = config.ba_blur_samples if samples is None else samples
    return _bundle_adjust(window, camera, jnp.asarray(config.ba_iterations, jnp.int32), config.ba_huber, config.ba_outlier,
                          config.ba_lambda, int(samples))


# --------------------------------------------------------------------------- marginalisation


@functools.partial(jax.jit, static_argnames=("samples",))
@_full_precision
def _marginalize(window: Window, camera: PinholeCamera, slot, huber, outlier, samples: int) -> Window:
    lin = linearize(window, camera, huber, outlier, host_values(window, camera, samples))
    data = jax.lax.cond(window.prior.active(), _zero_equations,  # the anchor's weights matter only without a prior
                        lambda w: normal_equations(lin, w), window)
    anchor = make_anchor(window, data, scale_with_prior=False)
    hosted = window.point_valid & (window.host == slot)
    own = eqx.tree_at(lambda l: l.w, lin, jnp.where(hosted[:, None, None], lin.w, jnp.zeros_like(lin.w)))  # the slot's points only
    neq = _mask_cameras(normal_equations(own, window), window.kf_valid)
    H, b = reduce_points(neq)
    Hc, bc, _ = camera_terms(window, anchor)
    H, b = marginalize_slot(H + Hc, b + bc, slot)
    dtype = window.affine.dtype
    poses = set_slot_pose(window.poses, slot, Pose.identity(dtype))
    prior = Prior(H, b, poses, window.affine.at[slot].set(jnp.zeros(2, dtype)))
    return dataclasses.replace(window, kf_valid=window.kf_valid.at[slot].set(False),
                               point_valid=window.point_valid & (window.host != slot), prior=prior)


def marginalize(window: Window, slot: int, camera: PinholeCamera, config: MonoConfig, samples: int | None = None) -> Window:
    """Keyframe ``slot`` leaves the window (DSO): the points it hosts are marginalised (their
    information on the keyframes, by the Schur complement over their inverse depths), then its own
    variables, together with the existing prior (moved to the current state) or, without one, the
    gauge anchor; the result is the new prior on the remaining keyframes, linearised at their
    current state. Residuals of other points into this keyframe are dropped; the slot becomes free."""
    if not bool(np.asarray(window.kf_valid)[slot]):
        raise ArgumentError(f"keyframe slot {slot} is empty: nothing to marginalise")
    samples = config.ba_blur_samples if samples is None else samples
    return _marginalize(window, camera, jnp.asarray(slot, jnp.int32), config.ba_huber, config.ba_outlier, int(samples))
