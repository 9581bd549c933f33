#!/usr/bin/env python3
"""Coarse-to-fine keyframe deblurring, measured on single frames of a generated sequence (true exposure
path and depth): the full-resolution solve as the loop does it (CG to 1 %, at most 30 steps) against a
half-resolution solve upsampled as the warm start of 3, 6 or 10 full-resolution CG steps; PSNR
against sharp/ and seconds of one warm call each. Used for "Coarse to fine" in docs/benchmarks.md.

    python scripts/deblur_coarse_to_fine.py runs/bench_strong_640x480_seed0 3,12,25
"""
import sys, time, pathlib, numpy as np, jax, jax.numpy as jnp, cv2
from functools import partial
from mbavo_jax.datasets import open_sequence
from mbavo_jax.geometry import ExposureTrajectory, Pose, PinholeCamera
from mbavo_jax import deblur as D
from mbavo_jax.blur import plane_depths_from_keyframe
from mbavo_jax.image import linearize, delinearize
from mbavo_jax.io import read_image_gray

@partial(jax.jit, static_argnames=("n", "iterations"))
def solve(b, x0, planes, cam, traj, n, iterations, tol):
    table = D.sampling_table(planes, cam, traj, n, 0.0, False)
    x, s = D._solve(partial(D.table_blur, table), partial(D.table_blur_adjoint, table), table.valid, b, x0, jnp.float32(0.02), iterations, tol)
    return jnp.clip(x, 0, 1), s

seq = open_sequence(sys.argv[1]); gamma = float(seq.meta.get("response_gamma", 1.0))
stamps, starts, ends = seq.exposure_paths
P = lambda v: Pose.from_vector(jnp.asarray(v, jnp.float32))
cam = seq.camera
half = PinholeCamera.create(float(cam.fx) / 2, float(cam.fy) / 2, (float(cam.cx) - 0.5) / 2, (float(cam.cy) - 0.5) / 2, int(cam.width) // 2, int(cam.height) // 2)
def timed(fn, *a, **k):
    jax.block_until_ready(fn(*a, **k)); t0 = time.perf_counter(); r = jax.block_until_ready(fn(*a, **k)); return r, time.perf_counter() - t0
for k in map(int, sys.argv[2].split(",")):
    f = seq[k]; j = int(np.argmin(abs(stamps - f.timestamp)))
    traj = ExposureTrajectory(P(starts[j]), P(ends[j])).about_middle()
    n = D.choose_deblur_n(f.depth, cam, traj)
    sharp = read_image_gray(pathlib.Path(f.path).parent.parent / "sharp" / pathlib.Path(f.path).name)
    h, w = sharp.shape
    inner = np.zeros(sharp.shape, bool); inner[h // 20:-h // 20, w // 20:-w // 20] = True
    b = linearize(f.image, gamma).astype(np.float32)
    planes = plane_depths_from_keyframe(jnp.asarray(f.depth.astype(np.float32)), cam, Pose.identity())
    (x, s), t = timed(solve, jnp.asarray(b), jnp.asarray(b), planes, cam, traj, n, 30, jnp.float32(0.01))
    row = [f"#{k} n{n} blurry {D.psnr(f.image, sharp, inner):.2f} | full tol: {int(s)} st {D.psnr(delinearize(np.asarray(x), gamma), sharp, inner):.2f} {t:.2f}s"]
    bh = cv2.resize(b, (w // 2, h // 2), interpolation=cv2.INTER_AREA)
    dh = cv2.resize(np.nan_to_num(f.depth.astype(np.float32)), (w // 2, h // 2), interpolation=cv2.INTER_NEAREST); dh[dh <= 0] = np.nan
    ph = plane_depths_from_keyframe(jnp.asarray(dh), half, Pose.identity())
    (xh, sh), th = timed(solve, jnp.asarray(bh), jnp.asarray(bh), ph, half, traj, max(n // 2, 8), 30, jnp.float32(0.01))
    up = cv2.resize(np.asarray(xh), (w, h), interpolation=cv2.INTER_LINEAR)
    row.append(f"half: {int(sh)} st {th:.2f}s, upsampled {D.psnr(delinearize(up, gamma), sharp, inner):.2f}")
    for it in (3, 6, 10):
        (x2, s2), t2 = timed(solve, jnp.asarray(b), jnp.asarray(up), planes, cam, traj, n, it, jnp.float32(0.0))
        row.append(f"+{it} full: {D.psnr(delinearize(np.asarray(x2), gamma), sharp, inner):.2f} {th + t2:.2f}s")
    print(" | ".join(row), flush=True)
