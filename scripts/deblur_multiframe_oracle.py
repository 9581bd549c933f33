#!/usr/bin/env python3
"""How much a keyframe's deconvolution gains from its neighbours' blurry frames, with everything true.

On a generated sequence (true exposure paths, true depth, the sharp mid-exposure render) keyframe k's
sharp image x is solved from frame k alone and from frames k-s..k+s together:

    min_x  (1/|J|) Σ_j ‖A_j x − b_j‖²  +  λ ‖∇x‖²        (conjugate gradients on the normal equations)

A_j is the blur model (``blur.render_blurry``) of frame j's exposure path seen from k's mid pose,
through k's depth (``blur.plane_depths_from_keyframe``), as ``deblur`` uses it for j = k. Prints, per
keyframe, how well A_j of the sharp render explains each frame j (PSNR on the pixels it covers), each
frame's blur (median length and direction of ``blur.blur_segments``), and the PSNR against the sharp
render (30-px border left out) of the blurry frame, the single-frame and the multi-frame solutions.
Example (``mbavo synth --preset extreme --frames 100 --width 640 --height 480 --seed 0 OUT``):

    python scripts/deblur_multiframe_oracle.py OUT --keyframes 30,60 --span 2 --lam 0.02 --iterations 60
"""

import argparse
import pathlib

import cv2
import jax
import jax.numpy as jnp
import numpy as np

from mbavo_jax.blur import blur_segments, plane_depths_from_keyframe, render_blurry
from mbavo_jax.datasets import open_sequence
from mbavo_jax.deblur import _cg, _grad_ops, psnr  # the solver deblur uses, for one frame or several
from mbavo_jax.geometry import ExposureTrajectory, Pose

N = 64  # virtual frames


def true_path(seq, i: int) -> ExposureTrajectory:
    _, start, end = seq.exposure_paths
    return ExposureTrajectory(Pose.from_vector(jnp.asarray(start[i], jnp.float32)), Pose.from_vector(jnp.asarray(end[i], jnp.float32)))


def operator(seq, k: int, j: int):
    """A_j (linear in x), its transpose and the pixels it covers: frame j seen from k's mid pose."""
    traj = true_path(seq, j).seen_from(true_path(seq, k).middle().inverse())
    planes = plane_depths_from_keyframe(jnp.asarray(seq[k].depth, jnp.float32), seq.camera, traj.middle())
    blur = jax.jit(lambda x: render_blurry(x, planes, seq.camera, traj, N)[0])
    adjoint = jax.jit(lambda y: jax.linear_transpose(blur, planes)(y)[0])
    return blur, adjoint, render_blurry(jnp.ones_like(planes), planes, seq.camera, traj, N)[1]


def solve(ops, blurry, x0, lam: float, iterations: int):
    """The normal equations of the multi-frame problem: ``deblur``'s conjugate gradients from x0."""
    reg = jax.grad(lambda z: 0.5 * sum(jnp.sum(g * g) for g in _grad_ops(z)))  # ∇ᵀ∇x, deblur's penalty
    normal = jax.jit(lambda x: sum(at(jnp.where(v, a(x), 0.0)) for a, at, v in ops) / len(ops) + lam * reg(x))
    rhs = sum(at(jnp.where(v, b, 0.0)) for (a, at, v), b in zip(ops, blurry)) / len(ops)
    return np.asarray(_cg(normal, rhs - normal(x0), x0, iterations)[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("sequence")
    ap.add_argument("--keyframes", default="30")
    ap.add_argument("--span", type=int, default=2)
    ap.add_argument("--lam", type=float, default=0.02, help="weight of the gradient penalty (deblur.regularization's default)")
    ap.add_argument("--iterations", type=int, default=60)
    args = ap.parse_args()
    root = pathlib.Path(args.sequence)
    seq = open_sequence(root)
    gamma = float(seq.meta.get("response_gamma", 1.0))
    lin = lambda img: jnp.asarray(np.clip(img, 0.0, 1.0) ** gamma, jnp.float32)
    for k in (int(s) for s in args.keyframes.split(",")):
        sharp = cv2.imread(str(root / "sharp" / pathlib.Path(seq[k].path).name), cv2.IMREAD_GRAYSCALE) / 255.0
        frames = [j for j in range(k - args.span, k + args.span + 1) if 0 <= j < len(seq)]
        ops = {j: operator(seq, k, j) for j in frames}
        inner = np.zeros(sharp.shape, bool)
        inner[30:-30, 30:-30] = True
        for j, (a, _, v) in ops.items():
            covered = np.asarray(v) & inner
            model = np.asarray(a(lin(sharp))) ** (1 / gamma)
            v_, u_ = np.mgrid[40 : sharp.shape[0] - 40 : 16, 40 : sharp.shape[1] - 40 : 16]  # frame j's blur at its own depth
            seg, ok = blur_segments(seq.camera, jnp.asarray(np.stack([u_.ravel(), v_.ravel()], 1), jnp.float32),
                                    jnp.asarray(seq[j].depth[v_.ravel(), u_.ravel()], jnp.float32), true_path(seq, j).about_middle())
            seg = np.asarray(seg)[np.asarray(ok)]
            print(f"k {k}, frame {j}: model {psnr(model, seq[j].image, covered):.2f} dB on {covered.mean():.2f} of the image; blur "
                  f"{np.median(np.linalg.norm(seg, axis=1)):.1f} px at {np.median(np.degrees(np.arctan2(seg[:, 1], seg[:, 0]))):.0f} deg")
        line = f"k {k}: blurry {psnr(seq[k].image, sharp, inner):.2f} dB"
        for s in range(args.span + 1):
            chosen = [j for j in frames if abs(j - k) <= s]
            x = solve([ops[j] for j in chosen], [lin(seq[j].image) for j in chosen], lin(seq[k].image), args.lam, args.iterations)
            line += f", frames k±{s}: {psnr(np.clip(x, 0.0, 1.0) ** (1 / gamma), sharp, inner):.2f} dB"
        print(line, flush=True)


if __name__ == "__main__":
    main()
