"""Candidate (immature) points of a monocular keyframe: each one's inverse depth is an interval that
is searched along its epipolar line in the frames that follow, until it is small enough for the point
to join the bundle-adjustment window (DSO's immature points, Engel et al., TPAMI 2018).

A candidate is a host pixel with an inverse z-depth interval ``[idepth_min, idepth_max]`` (``+inf``
until its first trace). One trace in a frame:

1. projects the interval's ends into the frame: a segment of the epipolar line (an unbounded interval
   searches a fixed length from its far end, DSO's maxPixSearch);
2. steps along it a pixel at a time, scoring DSO's 8-pixel pattern (Huber SSD against the host's
   pattern under the affine brightness e^a·I + b; with the frame's exposure path, the host's pattern
   is first blurred as the frame sees it, by the blur model); quality = the best energy outside the best's
   neighbourhood / the best energy;
3. refines the best position by Gauss-Newton along the line and sets the interval to the inverse
   depths at best ± the expected error in pixels (large when the image gradient is nearly
   perpendicular to the line).

Slots are fixed (``valid`` pads them) and the search has a bounded number of steps, so a sequence
compiles once per image size.
"""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from ..blur import synthesize, virtual_pq_table
from ..config import MonoConfig
from ..geometry import PinholeCamera, Pose
from ..geometry.spline import ExposurePath
from ..geometry.trajectory import row_times
from ..image import bilinear, bilinear_with_gradient
from ..tracking.points import PATTERN, gradient_magnitude
from .window import Window, insert_points

__all__ = ["Candidates", "FrameBlur", "select_candidates", "trace", "ready", "estimates", "parallax", "activate", "UNTRACED", "GOOD",
           "SKIPPED", "BAD_CONDITION", "OUT_OF_IMAGE", "OUTLIER"]

# Status of a candidate's last trace.
UNTRACED, GOOD, SKIPPED, BAD_CONDITION, OUT_OF_IMAGE, OUTLIER = range(6)

MAX_PIX_SEARCH = 0.027  # longest search along the line, as a fraction of W + H (DSO's maxPixSearch)
SLACK_INTERVAL = 1.5  # px: a shorter segment is already certain, the trace is skipped
MIN_IMPROVEMENT = 2.0  # a bounded segment must be this many times the expected error to be searched
TEST_RADIUS = 2  # steps: the second best lies farther than this from the best
GN_ITERATIONS = 3
GN_THRESHOLD = 0.1  # px: Gauss-Newton along the line stops below this step
GN_DAMPING = (1.0 / 255.0) ** 2  # added to the 1-D Hessian (intensities in [0, 1])
MAX_ERROR_PX = 10.0
GRAD_WEIGHT = (50.0 / 255.0) ** 2  # pattern weights c / (c + |∇I|²) (DSO's outlierTHSumComponent)
SCALE_RANGE = (0.75, 1.5)  # frame depth / host depth outside this: the pattern no longer matches
BORDER = 4.0  # px: a segment end closer to the image border is out of the image
MISSING = 1.0  # energy of a pattern sample outside the frame (far above any radiance residual²)
MIN_QUALITY = 3.0  # second best / best energy of a ready candidate (DSO's minTraceQuality)
READY_PIXELS = 8.0  # px: largest interval along the last line of a ready candidate (DSO's)
GRAD_ADD = 7.0 / 255.0  # selection: a pixel's gradient must exceed its region's median by this
REGION = 32  # px: blocks of the region-adaptive gradient threshold
SELECT_LEVELS = 3  # selection passes with cells 1x, 2x, 4x, each with the threshold x 0.75
MIN_PARALLAX = 1.0  # px: a point at the window's median depth must move this far from host to latest frame to activate
BLUR_SAMPLES = 16  # virtual frames of the blur model when a sharp host's pattern is blurred for a blurry frame


class Candidates(eqx.Module):
    """M candidate slots of one host keyframe.

    ``pixels`` (M, 2) host pixels (level 0); ``[idepth_min, idepth_max]`` (M,) the inverse z-depth
    interval (max +inf before the first trace); ``quality`` (M,) second-best / best energy (DSO's,
    +inf before the first search); ``energy`` (M,) the last search's best energy; ``pixel_interval``
    (M,) the interval's length (px) along the last line traced; ``valid`` (M,) the slot holds a
    candidate; ``outlier`` (M,) dropped (two outlier traces in a row); ``status`` (M,) the last trace's
    status (UNTRACED, GOOD, ...); ``traced`` (M,) the number of GOOD traces.
    """

    pixels: Float[Array, "M 2"]
    idepth_min: Float[Array, " M"]
    idepth_max: Float[Array, " M"]
    quality: Float[Array, " M"]
    energy: Float[Array, " M"]
    pixel_interval: Float[Array, " M"]
    valid: Bool[Array, " M"]
    outlier: Bool[Array, " M"]
    status: Int[Array, " M"]
    traced: Int[Array, " M"]

    @staticmethod
    def create(pixels: Float[np.ndarray, "M 2"] | Float[Array, "M 2"],
               valid: Bool[np.ndarray, " M"] | Bool[Array, " M"]) -> "Candidates":
        """Untraced candidates at ``pixels`` with the interval [0, +inf)."""
        m = len(pixels)
        zeros = jnp.zeros(m, jnp.float32)
        return Candidates(
            jnp.asarray(pixels, jnp.float32), zeros, jnp.full(m, jnp.inf, jnp.float32), jnp.full(m, jnp.inf, jnp.float32),
            zeros, zeros, jnp.asarray(valid, bool), jnp.zeros(m, bool), jnp.full(m, UNTRACED, jnp.int32),
            jnp.zeros(m, jnp.int32),
        )


# ------------------------------------------------------------------------------------------ selection


def region_threshold(grad: Float[np.ndarray, "H W"], block: int = REGION, add: float = GRAD_ADD) -> np.ndarray:
    """(H, W) gradient threshold: the median gradient of each ``block`` x ``block`` region, averaged
    with its 8 neighbours, plus ``add`` (DSO's PixelSelector)."""
    h, w = grad.shape
    hb, wb = -(-h // block), -(-w // block)
    pad = np.full((hb * block, wb * block), np.nan, np.float32)
    pad[:h, :w] = grad
    med = np.nanmedian(pad.reshape(hb, block, wb, block).transpose(0, 2, 1, 3).reshape(hb, wb, -1), axis=-1)
    ext = np.pad(med, 1, mode="edge")
    smooth = sum(ext[i : i + hb, j : j + wb] for i in range(3) for j in range(3)) / 9.0
    return (np.repeat(np.repeat(smooth, block, 0), block, 1)[:h, :w] + add).astype(np.float32)


def _cells(a: np.ndarray, cell: int) -> np.ndarray:
    """(hc, wc, cell²) blocks of ``a`` (its whole cells only)."""
    hc, wc = a.shape[0] // cell, a.shape[1] // cell
    return a[: hc * cell, : wc * cell].reshape(hc, cell, wc, cell).transpose(0, 2, 1, 3).reshape(hc, wc, -1)


def _pick(grad: np.ndarray, thresh: np.ndarray, cell: int) -> np.ndarray:
    """(H, W) bool: one pixel per cell, the strongest gradient above ``thresh``; coarser passes
    (cells 2x, 4x, threshold x 0.75 each) fill cells that found nothing."""
    chosen = np.zeros(grad.shape, bool)
    for level in range(SELECT_LEVELS):
        size = cell << level
        if size > min(grad.shape):
            break
        score = np.where(grad > thresh * 0.75**level, grad, -1.0)
        blocks = _cells(score, size)
        arg = blocks.argmax(-1)
        ok = (np.take_along_axis(blocks, arg[..., None], -1)[..., 0] > 0) & ~_cells(chosen, size).any(-1)
        r, c = np.nonzero(ok)
        chosen[r * size + arg[r, c] // size, c * size + arg[r, c] % size] = True
    return chosen


def select_candidates(image: Float[np.ndarray, "H W"] | Float[Array, "H W"], count: int | None = None,
                      config: MonoConfig = MonoConfig()) -> Candidates:
    """DSO-like candidates on a keyframe (linear radiance, (H, W)): pixels whose gradient exceeds a
    region-adaptive threshold, one per cell, the cell size chosen to give about ``count`` points
    (``config.candidates`` by default), coarser cells with lower thresholds filling weakly textured
    regions; thinned evenly to at most ``count`` and padded to exactly ``count`` slots."""
    count = config.candidates if count is None else int(count)
    grad = gradient_magnitude(np.asarray(image, np.float32))
    b = int(BORDER) + 1
    inner = np.zeros(grad.shape, bool)
    inner[b:-b, b:-b] = True
    grad = np.where(inner, grad, 0.0)
    thresh = region_threshold(grad)
    lo, hi = 1, max(1, min(grad.shape) // 2)
    while lo < hi:  # the largest cell that still gives `count` points (fewer points in larger cells)
        mid = (lo + hi + 1) // 2
        lo, hi = (mid, hi) if _pick(grad, thresh, mid).sum() >= count else (lo, mid - 1)
    rows, cols = np.nonzero(_pick(grad, thresh, lo))
    if len(rows) > count:
        keep = np.unique(np.round(np.linspace(0, len(rows) - 1, count)).astype(int))
        rows, cols = rows[keep], cols[keep]
    pixels = np.zeros((count, 2), np.float32)
    pixels[: len(rows)] = np.stack([cols, rows], -1)
    return Candidates.create(pixels, np.arange(count) < len(rows))


# ------------------------------------------------------------------------------- one point's trace


class _Host(eqx.Module):
    """The host's pattern of one candidate: colours (8,), weights (8,), gradient outer products (2, 2)."""

    colours: Float[Array, " P"]
    weights: Float[Array, " P"]
    grad_outer: Float[Array, "2 2"]


def host_pattern(host_image: Float[Array, "H W"], pixel: Float[Array, "2"]) -> _Host:
    """The pattern's colours around ``pixel``, their gradients (central differences) as Σ g gᵀ and
    DSO's weights c / (c + |g|²)."""
    offsets = jnp.array([[0.0, 0.0], [1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    pts = pixel + jnp.asarray(PATTERN)[:, None, :] + offsets  # (P, 5, 2)
    vals = jax.vmap(jax.vmap(lambda x: bilinear(host_image, x)[0]))(pts)
    g = 0.5 * jnp.stack([vals[:, 1] - vals[:, 2], vals[:, 3] - vals[:, 4]], -1)  # (P, 2)
    weights = jnp.sqrt(GRAD_WEIGHT / (GRAD_WEIGHT + jnp.sum(g * g, -1)))
    return _Host(vals[:, 0], weights, g.T @ g)


class _Line(eqx.Module):
    """A host pixel's epipolar line in the frame: at inverse depth ρ its homogeneous pixel is
    ``pr + ρ kt``; ``plane`` (2, 2) is K R K⁻¹'s top-left block (rotates the pattern)."""

    pr: Float[Array, "3"]
    kt: Float[Array, "3"]
    plane: Float[Array, "2 2"]

    def project(self, idepth):
        """The frame pixel (2,) at inverse depth ``idepth`` and its depth ratio z_frame·ρ (> 0: in front)."""
        h = self.pr + idepth * self.kt
        z = jnp.where(jnp.abs(h[2]) > 1e-9, h[2], 1e-9)
        return h[:2] / z, h[2]

    def idepth_at(self, x: Float[Array, "2"], direction: Float[Array, "2"]):
        """The inverse depth whose projection is ``x`` (on the line), solved from the coordinate that
        varies most along ``direction``."""
        i = jnp.where(jnp.abs(direction[0]) >= jnp.abs(direction[1]), 0, 1)
        num = self.pr[2] * x[i] - self.pr[i]
        den = self.kt[i] - self.kt[2] * x[i]
        return num / jnp.where(jnp.abs(den) > 1e-12, den, 1e-12)


def epipolar_line(camera: PinholeCamera, T_frame_host: Pose, pixel: Float[Array, "2"]) -> _Line:
    """The epipolar line of a host pixel in the frame (``T_frame_host`` maps host points into it)."""
    K = camera.K()
    KR = K @ T_frame_host.rotation()
    ray = jnp.stack([(pixel[0] - camera.cx) / camera.fx, (pixel[1] - camera.cy) / camera.fy, jnp.ones_like(camera.fx)])
    Kinv = jnp.linalg.inv(K)
    return _Line(KR @ ray, K @ T_frame_host.t, (KR @ Kinv)[:2, :2])


class _Segment(eqx.Module):
    """The searched part of a line: from ``start`` along the unit ``direction`` for ``length`` px;
    ``span`` the whole interval's length (px); ``status`` GOOD (search it), SKIPPED, BAD_CONDITION or
    OUT_OF_IMAGE; ``error`` the expected matching error (px) along it."""

    start: Float[Array, "2"]
    direction: Float[Array, "2"]
    length: Float[Array, ""]
    span: Float[Array, ""]
    error: Float[Array, ""]
    status: Int[Array, ""]


def matching_error(grad_outer: Float[Array, "2 2"], direction: Float[Array, "2"]):
    """DSO's error model (px): 0.2 + 0.2 (a + b) / a, a and b the pattern's squared gradient along
    and across the line: large when the gradient is nearly perpendicular to it."""
    normal = jnp.stack([direction[1], -direction[0]])
    a = direction @ grad_outer @ direction
    b = normal @ grad_outer @ normal
    err = 0.2 + 0.2 * (a + b) / jnp.where(a > 1e-12, a, 1e-12)
    return jnp.where(a > 1e-12, jnp.minimum(err, MAX_ERROR_PX), MAX_ERROR_PX)


def _inside(camera: PinholeCamera, x: Float[Array, "2"]):
    return jnp.all(jnp.isfinite(x)) & camera.in_image(jnp.where(jnp.isfinite(x), x, -1.0), BORDER)


def search_segment(line: _Line, camera: PinholeCamera, idepth_min, idepth_max, grad_outer, max_pix: float) -> _Segment:
    """Project the interval into the frame and decide whether to search it: OUT_OF_IMAGE when an end
    leaves the image, lies behind the camera, or the scale changes too much; SKIPPED when the
    segment is shorter than the slack; BAD_CONDITION when the expected error would not shrink it."""
    x_min, z_min = line.project(idepth_min)
    bounded = jnp.isfinite(idepth_max)
    x_far, z_far = line.project(jnp.where(bounded, idepth_max, idepth_min))
    slope = (line.kt[:2] - x_min * line.kt[2]) / jnp.where(z_min > 1e-9, z_min, 1e-9)  # dx/dρ at idepth_min
    slope_norm = jnp.linalg.norm(slope)
    x_max = jnp.where(bounded, x_far, x_min + max_pix * slope / jnp.where(slope_norm > 1e-9, slope_norm, 1.0))
    span = jnp.linalg.norm(x_max - x_min)
    direction = (x_max - x_min) / jnp.where(span > 1e-9, span, 1.0)
    scale_ok = (idepth_min <= 0) | ((z_min > SCALE_RANGE[0]) & (z_min < SCALE_RANGE[1]))
    out = ~(_inside(camera, x_min) & _inside(camera, x_max) & (z_min > 0) & (~bounded | (z_far > 0)) & scale_ok
            & (bounded | (slope_norm > 1e-6)))
    error = matching_error(grad_outer, direction)
    status = jnp.where(out, OUT_OF_IMAGE,
                       jnp.where(bounded & (span < SLACK_INTERVAL), SKIPPED,
                                 jnp.where(bounded & (error * MIN_IMPROVEMENT > span), BAD_CONDITION, GOOD)))
    return _Segment(x_min, direction, jnp.minimum(span, max_pix), span, error, jnp.asarray(status, jnp.int32))


def _residuals(frame: Float[Array, "H W"], x: Float[Array, "2"], pattern: Float[Array, "P 2"], target: Float[Array, " P"]):
    """The pattern's residuals frame(x + pattern) - target (P,) and their validity."""
    vals, ok = jax.vmap(lambda p: bilinear(frame, x + p))(pattern)
    return vals - target, ok


def _huber_weight(r, huber: float):
    a = jnp.abs(r)
    return jnp.where(a < huber, 1.0, huber / jnp.where(a < huber, 1.0, a))


def pattern_energy(r: Float[Array, " P"], ok: Bool[Array, " P"], weights: Float[Array, " P"], huber: float):
    """Σ w² · Huber(r) (DSO's hw r² (2 - hw)); a sample outside the frame costs ``MISSING``."""
    hw = _huber_weight(r, huber)
    return jnp.sum(jnp.where(ok, weights**2 * hw * r * r * (2.0 - hw), MISSING))


def discrete_search(frame, seg: _Segment, pattern, target, weights, huber: float, steps: int):
    """Energies at ``steps`` 1-px steps from the segment's start (those past its length cost +inf):
    the best step, its energy and the best energy farther than TEST_RADIUS steps from it."""
    k = jnp.arange(steps)
    n = jnp.minimum(jnp.floor(1.9999 + seg.length).astype(jnp.int32), steps)
    at = lambda s: pattern_energy(*_residuals(frame, seg.start + s * seg.direction, pattern, target), weights, huber)  # noqa: E731
    energy = jax.vmap(at)(k.astype(jnp.float32))
    energy = jnp.where(k < n, energy, jnp.inf)
    best = jnp.argmin(energy)
    second = jnp.min(jnp.where(jnp.abs(k - best) > TEST_RADIUS, energy, jnp.inf))
    return best.astype(jnp.float32), energy[best], second, n


def refine_along_line(frame, seg: _Segment, s0, pattern, target, weights, huber: float):
    """Gauss-Newton on the position s (px from the segment's start), steps clipped to ±0.5 px and
    halved back after an increase (DSO's): the final s and the energy of the last accepted one."""

    def energy_and_step(s):
        pts = seg.start + s * seg.direction + pattern
        vals, grads, ok = jax.vmap(lambda p: bilinear_with_gradient(frame, p))(pts)
        r = vals - target
        hw = _huber_weight(r, huber)
        j = grads @ seg.direction
        w = jnp.where(ok, weights**2 * hw, 0.0)
        h, b = GN_DAMPING + jnp.sum(w * j * j), jnp.sum(w * r * j)
        return pattern_energy(r, ok, weights, huber), jnp.clip(-b / h, -0.5, 0.5)

    def body(_, state):
        s, s_back, back, e_best, done = state
        e, step = energy_and_step(s)
        worse = e > e_best
        new = (jnp.where(worse, s_back + 0.5 * back, s + step), jnp.where(worse, s_back, s), jnp.where(worse, 0.5 * back, step),
               jnp.where(worse, e_best, e))
        stop = jnp.abs(new[2]) < GN_THRESHOLD
        return tuple(jnp.where(done, old, nw) for old, nw in zip(state[:4], new)) + (done | stop,)

    zero = jnp.zeros_like(s0)
    s, _, _, e_best, _ = jax.lax.fori_loop(0, GN_ITERATIONS, body, (s0, s0, zero, jnp.full_like(s0, jnp.inf), jnp.array(False)))
    return s, e_best


class _Trace(eqx.Module):
    """Candidates' state (the fields of :class:`Candidates` without pixels and valid): one
    candidate's (scalars) or all of them (M,)."""

    idepth_min: Float[Array, " *m"]
    idepth_max: Float[Array, " *m"]
    quality: Float[Array, " *m"]
    energy: Float[Array, " *m"]
    pixel_interval: Float[Array, " *m"]
    outlier: Bool[Array, " *m"]
    status: Int[Array, " *m"]
    traced: Int[Array, " *m"]


def _searched(old: _Trace, line: _Line, seg: _Segment, s, energy, quality, energy_th) -> _Trace:
    """The state after a search: the interval at s ± error (an outlier when the energy exceeds
    ``energy_th`` or the interval is meaningless; dropped after two outlier traces in a row)."""
    a = line.idepth_at(seg.start + (s - seg.error) * seg.direction, seg.direction)
    b = line.idepth_at(seg.start + (s + seg.error) * seg.direction, seg.direction)
    lo, hi = jnp.minimum(a, b), jnp.maximum(a, b)
    bad = ~(energy < energy_th) | ~jnp.isfinite(lo) | ~jnp.isfinite(hi) | (hi <= 0)
    good = _Trace(jnp.maximum(lo, 0.0), hi, quality, energy, 2.0 * seg.error, old.outlier, jnp.asarray(GOOD, jnp.int32),
                  old.traced + 1)
    outlier = eqx.tree_at(lambda t: (t.quality, t.energy, t.outlier, t.status), old,
                          (quality, energy, old.outlier | (old.status == OUTLIER), jnp.asarray(OUTLIER, jnp.int32)))
    return jax.tree_util.tree_map(lambda o, g: jnp.where(bad, o, g), outlier, good)


class FrameBlur(eqx.Module):
    """How a blurry frame was exposed, for tracing a sharp host's candidates in it: ``path`` the
    frame's exposure path in the host (``T_host_i``; its middle is the frame's pose), ``readout`` its
    readout fraction, ``idepth`` the inverse depth that a candidate without a bounded interval is
    blurred at (a typical one of the host's scene; 0: the near end of its search)."""

    path: ExposurePath
    readout: Float[Array, ""]
    idepth: Float[Array, ""]

    @staticmethod
    def create(path: ExposurePath, readout: float = 0.0, idepth: float = 0.0) -> "FrameBlur":
        return FrameBlur(path, jnp.asarray(readout, jnp.float32), jnp.asarray(idepth, jnp.float32))


def blurred_colours(host_image: Float[Array, "H W"], camera: PinholeCamera, blur: FrameBlur, line: _Line, seg: _Segment,
                    old: _Trace, pattern: Float[Array, "P 2"], fallback: Float[Array, " P"]) -> Float[Array, " P"]:
    """The host's pattern as the blurry frame shows it (the blur model ``blur.synthesize`` with
    ``BLUR_SAMPLES`` virtual frames along ``blur.path``), on the host's frontal-parallel plane at the
    middle of the candidate's inverse-depth interval (unbounded: ``blur.idepth``, or the segment's
    start), around that depth's frame pixel; ``fallback`` where a sample leaves the host."""
    bounded = jnp.isfinite(old.idepth_max)
    near = line.idepth_at(seg.start, seg.direction)
    guess = jnp.where(blur.idepth > 0, blur.idepth, near)
    idepth = jnp.maximum(jnp.where(bounded, 0.5 * (old.idepth_min + jnp.where(bounded, old.idepth_max, 0.0)), guess), 1e-6)
    x, _ = line.project(idepth)
    x = jnp.where(jnp.isfinite(x), x, seg.start)
    rows = jnp.zeros(pattern.shape[0], jnp.int32)
    pqs = virtual_pq_table(blur.path, row_times(BLUR_SAMPLES, x[1:2], camera.height, blur.readout))
    rays = jax.vmap(camera.unit_ray)(x + pattern)
    values, ok = synthesize(host_image, camera, pqs, rays, jnp.full(pattern.shape[0], 1.0 / idepth), rows)
    return jnp.where(ok, values, fallback)


def trace_one(host_image, frame_image, camera: PinholeCamera, T_frame_host: Pose, affine_ab, pixel, old: _Trace, huber: float,
              energy_th: float, steps: int, max_pix: float, blur: FrameBlur | None = None) -> _Trace:
    """One candidate traced in a frame (see the module docstring); skipped traces keep the interval.
    With the frame's ``blur``, the host's pattern is blurred as the frame sees it first."""
    host = host_pattern(host_image, pixel)
    line = epipolar_line(camera, T_frame_host, pixel)
    seg = search_segment(line, camera, old.idepth_min, old.idepth_max, host.grad_outer, max_pix)
    pattern = jnp.asarray(PATTERN) @ line.plane.T
    colours = host.colours if blur is None else blurred_colours(host_image, camera, blur, line, seg, old, pattern, host.colours)
    target = jnp.exp(affine_ab[0]) * colours + affine_ab[1]
    best, best_e, second, n = discrete_search(frame_image, seg, pattern, target, host.weights, huber, steps)
    quality = second / jnp.maximum(best_e, 1e-12)
    quality = jnp.where((quality < old.quality) | (n > 10), quality, old.quality)
    s, energy = refine_along_line(frame_image, seg, best, pattern, target, host.weights, huber)
    searched = _searched(old, line, seg, s, energy, quality, energy_th)
    skipped = eqx.tree_at(lambda t: (t.status, t.pixel_interval), old,
                          (seg.status, jnp.where(seg.status == OUT_OF_IMAGE, old.pixel_interval, seg.span)))
    return jax.tree_util.tree_map(lambda a, b: jnp.where(seg.status == GOOD, a, b), searched, skipped)


# ----------------------------------------------------------------------------------------- public


def _state(c: Candidates) -> _Trace:
    return _Trace(c.idepth_min, c.idepth_max, c.quality, c.energy, c.pixel_interval, c.outlier, c.status, c.traced)


def search_steps(camera: PinholeCamera) -> tuple[int, float]:
    """The longest search (px) for this image size and the number of 1-px steps that covers it."""
    max_pix = MAX_PIX_SEARCH * (camera.width + camera.height)
    return int(max_pix) + 2, float(max_pix)


@functools.partial(jax.jit, static_argnames=("config",))
def trace(c: Candidates, host_image: Float[Array, "H W"], frame_image: Float[Array, "H W"], camera: PinholeCamera,
          T_frame_host: Pose, affine_ab: Float[Array, "2"], config: MonoConfig = MonoConfig(),
          blur: FrameBlur | None = None) -> Candidates:
    """Trace every valid, not-dropped candidate of a host keyframe in a frame (both linear radiance;
    ``T_frame_host`` maps host points into the frame; the frame ≈ e^a · host + b with ``affine_ab``
    = (a, b)). Huber threshold ``config.ba_huber``; outlier above ``config.trace_outlier`` RMS.
    ``blur``: the frame's exposure (:class:`FrameBlur`) for a sharp host and a blurry frame; None:
    the two look alike."""
    steps, max_pix = search_steps(camera)
    energy_th = len(PATTERN) * config.trace_outlier**2
    new = jax.vmap(lambda p, s: trace_one(host_image, frame_image, camera, T_frame_host, affine_ab, p, s, config.ba_huber,
                                          energy_th, steps, max_pix, blur))(c.pixels, _state(c))
    active = c.valid & ~c.outlier
    new = jax.tree_util.tree_map(lambda a, b: jnp.where(active, a, b), new, _state(c))
    return Candidates(c.pixels, new.idepth_min, new.idepth_max, new.quality, new.energy, new.pixel_interval, c.valid,
                      new.outlier, new.status, new.traced)


def ready(c: Candidates, config: MonoConfig = MonoConfig()) -> Bool[Array, " M"]:
    """Candidates that may join the window: traced at least once, not dropped, the last trace not an
    outlier, quality above MIN_QUALITY, the interval along the last line at most READY_PIXELS px and
    its width in inverse depth at most ``config.ready_interval`` of its (positive) midpoint."""
    mid = 0.5 * (c.idepth_min + c.idepth_max)
    width = c.idepth_max - c.idepth_min
    base = (c.valid & ~c.outlier & (c.traced >= 1) & (c.status != OUTLIER) & (c.quality > MIN_QUALITY)
            & (c.pixel_interval <= READY_PIXELS) & jnp.isfinite(c.idepth_max) & (mid > 0))
    return base & (width <= config.ready_interval * mid)


def estimates(c: Candidates) -> tuple[Float[Array, "M 2"], Float[Array, " M"]]:
    """Host pixels (M, 2) and inverse depths (M,): the intervals' midpoints (0 while unbounded)."""
    bounded = jnp.isfinite(c.idepth_max)
    return c.pixels, jnp.where(bounded, 0.5 * (c.idepth_min + jnp.where(bounded, c.idepth_max, 0.0)), 0.0)


def parallax(c: Candidates, camera: PinholeCamera, T_frame_host: Pose, idepth: Float[Array, ""]) -> Float[Array, " M"]:
    """The disparity (px) each candidate's pixel would have in a frame (``T_frame_host`` maps host
    points into it) at inverse depth ``idepth``: the distance between its projections at ``idepth``
    and at infinity, i.e. the parallax the frame's baseline gives a point at that depth."""

    def one(pixel):
        line = epipolar_line(camera, T_frame_host, pixel)
        (x0, _), (x1, _) = line.project(jnp.zeros_like(idepth)), line.project(idepth)
        return jnp.linalg.norm(x1 - x0)

    return jax.vmap(one)(c.pixels)


def window_idepth(window: Window) -> Float[Array, ""]:
    """The median inverse depth of the window's points (NaN when it has none)."""
    return jnp.nanmedian(jnp.where(window.point_valid, window.idepth, jnp.nan))


@functools.partial(jax.jit, static_argnames=("config",))
def activate(window: Window, slot: Int[Array, ""], c: Candidates, config: MonoConfig = MonoConfig(),
             camera: PinholeCamera | None = None, T_world_frame: Pose | None = None) -> tuple[Window, Candidates]:
    """The ready candidates of ``c`` (hosted by keyframe ``slot``) join ``window`` as points at their
    estimates, in order, as many as there are free point slots; those that joined leave ``c``. With
    ``camera`` and the pose of the latest frame traced (``T_world_frame``), a candidate also needs a
    baseline: a point at the window's median inverse depth would move at least MIN_PARALLAX px
    between its host and that frame (otherwise it waits, and is traced further)."""
    pixels, idepth = estimates(c)
    ok = ready(c, config)
    if camera is not None and T_world_frame is not None:
        typical = window_idepth(window)
        T_frame_host = T_world_frame.inverse().compose(Pose(window.poses.q[slot], window.poses.t[slot]))
        disparity = parallax(c, camera, T_frame_host, jnp.where(typical > 0, typical, 0.0))
        ok = ok & (~(typical > 0) | (disparity >= MIN_PARALLAX))
    window, added = insert_points(window, slot, pixels, idepth, ok)
    return window, eqx.tree_at(lambda x: x.valid, c, c.valid & ~added)
