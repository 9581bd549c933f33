"""The table solver of keyframe deblurring (``deblur.solver = table``): its precomputed operator is
the blur model (``render_blurry``) with and without a rolling-shutter readout, its adjoint is the
operator's transpose, and the deblurred frame is sharper than its input and as sharp as the
reference solver's (``render``); CG stops at its tolerance, which costs little sharpness; coarse
to fine (the default) is as sharp as the full-resolution solve. Small images (160x120)."""

from __future__ import annotations

import dataclasses

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mbavo_jax.blur import render_blurry
from mbavo_jax.config import DeblurConfig
from mbavo_jax.deblur import _cg, deblur, psnr, sampling_table, table_blur, table_blur_adjoint, table_seen
from mbavo_jax.geometry import ExposureTrajectory, PinholeCamera
from tests.test_rolling_shutter import GT, render, scene

N = 16
TABLE = jax.jit(sampling_table, static_argnames=("n", "rolling"))


def frame(rho: float):
    """(sharp mid-exposure image, blurry frame, its depth, camera) of the slanted textured plane
    blurred along ``GT`` with readout fraction ``rho``."""
    img, cam, depth = scene()
    blurry, planes = render(img, cam, depth, GT, 64, rho)
    mid = GT.middle()
    sharp = np.asarray(render_blurry(jnp.asarray(img), planes, cam, ExposureTrajectory(mid, mid), 1)[0])
    return sharp, blurry.astype(np.float32), np.asarray(planes), cam


def table_of(rho: float):
    _, blurry, planes, cam = frame(rho)
    return TABLE(jnp.asarray(planes), cam, GT.about_middle(), n=N, readout=jnp.float32(rho), rolling=rho > 0), blurry, planes, cam


@pytest.mark.slow
@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_table_operator_is_the_blur_model(rho):
    table, blurry, planes, cam = table_of(rho)
    x = jnp.asarray(blurry)
    ref, ok = render_blurry(x, jnp.asarray(planes), cam, GT.about_middle(), N, rho)
    assert bool(jnp.all(table.valid == ok)) and 0.5 < float(ok.mean()) < 1.0
    assert float(jnp.max(jnp.abs(table_blur(table, x) - ref))) < 1e-4


@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_table_adjoint_is_the_transpose(rho, rng):
    table, blurry, _, _ = table_of(rho)
    x, y = (jnp.asarray(rng.uniform(size=blurry.shape).astype(np.float32)) for _ in range(2))
    lhs = float(jnp.vdot(table_blur(table, x), y))
    rhs = float(jnp.vdot(x, table_blur_adjoint(table, y)))
    assert lhs == pytest.approx(rhs, rel=1e-5)
    (auto,) = jax.linear_transpose(lambda z: table_blur(table, z), x)(y)
    assert float(jnp.max(jnp.abs(auto - table_blur_adjoint(table, y)))) < 1e-5


@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_table_seen_marks_the_cell_corners_of_valid_samples(rho):
    """The solve's unknowns: the four corners of every cell a valid pixel's sample falls in (a
    brute-force count), which covers every pixel that Aᵀ of the valid mask gives weight to."""
    table, blurry, _, _ = table_of(rho)
    h, w = blurry.shape
    cells = np.asarray(table.corner)[:, np.asarray(table.valid).ravel()].ravel()
    expect = np.zeros(h * w, bool)
    for offset in (0, 1, w, w + 1):
        expect[cells + offset] = True
    seen = np.asarray(table_seen(table)).ravel()
    assert np.array_equal(seen, expect) and 0.5 < seen.mean() < 1.0
    weighted = np.asarray(table_blur_adjoint(table, table.valid.astype(jnp.float32))).ravel() > 1e-6
    assert not np.any(weighted & ~seen) and np.sum(seen & ~weighted) <= 0.01 * np.sum(seen)


def deblurred_psnr(rho: float, **settings) -> tuple[float, float]:
    """(PSNR of the deblurred frame, of the blurry frame) against the sharp image, inside a border."""
    sharp, blurry, depth, cam = frame(rho)
    inner = np.zeros(sharp.shape, bool)
    inner[12:-12, 16:-16] = True
    cfg = dataclasses.replace(DeblurConfig(), n=32, **settings)
    return psnr(deblur(blurry, depth, cam, GT, cfg, 1.0, rho), sharp, inner), psnr(blurry, sharp, inner)


@pytest.mark.slow
@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_table_solver_sharpens_like_the_reference(rho):
    table, blurry_psnr = deblurred_psnr(rho, solver="table", tolerance=0.0)  # all iterations, as the reference
    reference, _ = deblurred_psnr(rho, solver="render", tolerance=0.0)
    assert table > blurry_psnr + 2.0, (table, blurry_psnr)
    assert abs(table - reference) < 0.05, (table, reference)


def test_cg_stops_at_its_tolerance(rng):
    """With a tolerance CG stops once the residual has fallen that far (and still solves the
    system to it); without one it takes every iteration."""
    m = rng.normal(size=(60, 60)).astype(np.float32)
    a = jnp.asarray(m @ m.T / 60 + 0.05 * np.eye(60, dtype=np.float32))
    b, x0 = jnp.asarray(rng.normal(size=60).astype(np.float32)), jnp.zeros(60)
    op = lambda x: a @ x
    x, steps = _cg(op, b - op(x0), x0, 50, 1e-2)
    assert 0 < int(steps) < 50
    assert float(jnp.linalg.norm(b - op(x))) <= 1e-2 * float(jnp.linalg.norm(b)) * 1.01
    _, all_steps = _cg(op, b - op(x0), x0, 50, 0.0)
    assert int(all_steps) == 50


def test_default_tolerance_keeps_the_sharpness():
    """Stopping at the default tolerance keeps at least 90 % of the PSNR gain of every iteration
    (at full resolution from the start: with coarse to fine the tolerance is the coarse solve's)."""
    early, blurry_psnr = deblurred_psnr(0.0, coarse_to_fine=False)
    full, _ = deblurred_psnr(0.0, coarse_to_fine=False, tolerance=0.0)
    assert early - blurry_psnr > 0.9 * (full - blurry_psnr), (early, full, blurry_psnr)


@pytest.mark.parametrize("rho", [0.0, 0.6])
def test_coarse_to_fine_keeps_the_sharpness(rho):
    """The default (a half-resolution solve, then a few full-resolution steps from it) keeps at
    least 90 % of the PSNR gain of the full-resolution solve, with and without a rolling shutter."""
    coarse, blurry_psnr = deblurred_psnr(rho)
    full, _ = deblurred_psnr(rho, coarse_to_fine=False)
    assert coarse - blurry_psnr > 0.9 * (full - blurry_psnr), (coarse, full, blurry_psnr)


@pytest.mark.slow
def test_the_coarse_solve_starts_the_fine_steps():
    """One full-resolution step from the upsampled half-resolution solve is far sharper than one
    full-resolution step from the blurry frame: the coarse solve does the work."""
    from_coarse, blurry_psnr = deblurred_psnr(0.0, fine_iterations=1, tolerance=0.0)
    from_blurry, _ = deblurred_psnr(0.0, coarse_to_fine=False, iterations=1)
    assert from_coarse > from_blurry + 5.0 > blurry_psnr + 5.0, (from_coarse, from_blurry, blurry_psnr)


@pytest.mark.slow
def test_coarse_to_fine_on_an_odd_image_size():
    """An image of odd width and height (the half-resolution solve drops the last row and column,
    the upsampled start copies them from their neighbours) is deblurred at its own size, as sharp
    as without coarse to fine (within 1 dB)."""
    sharp, blurry, depth, cam = frame(0.0)
    odd = PinholeCamera.create(cam.fx, cam.fy, cam.cx, cam.cy, 159, 119)
    inner = np.zeros((119, 159), bool)
    inner[12:-12, 16:-16] = True
    scores = []
    for coarse in (True, False):
        cfg = dataclasses.replace(DeblurConfig(), n=32, coarse_to_fine=coarse)
        x = deblur(blurry[:119, :159], depth[:119, :159], odd, GT, cfg, 1.0)
        assert x.shape == (119, 159)
        scores.append(psnr(x, sharp[:119, :159], inner))
    assert scores[0] > psnr(blurry[:119, :159], sharp[:119, :159], inner) + 10.0 and abs(scores[0] - scores[1]) < 1.0, scores
