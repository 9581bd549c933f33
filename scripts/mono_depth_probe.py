#!/usr/bin/env python3
"""How right a monocular run's depths are: per new keyframe, the tracker's points against the true depth.

Runs one ``mbavo bench mono`` method on a generated sequence that has depth maps (the monocular
pipeline does not read them). At each new keyframe it prints, over the tracker's level-0 points:

- ``scale``: the median ratio of estimated to true inverse depth (the map's scale; steady when the
  scale does not drift);
- ``log_err``: the median absolute log ratio of estimated to true depth after that scale;
- ``corr``: the correlation of estimated and true inverse depth;
- ``true_cv``: the coefficient of variation of the true inverse depths (what tells translation from
  rotation).

After the run: the frame-to-frame rotation error and translation direction error against the
ground truth (medians per block of frames), and the ATE. ``--oracle`` sets each point that joins
the window to its true inverse depth at its host pixel, brought to the window's scale (the median
ratio over the points already there). ``--keyframes`` changes how each new keyframe is deblurred
(``estimated``: as the run does, with the PSNR of each deblurred keyframe against the generator's
sharp render and how far the run's blur kernels are from the truth, :func:`kernel_error`, printed;
``true-depth``: with the true depth map; ``true-path``: with the true depth
and the true exposure path; ``sharp``: the sharp render itself). With ``--keyframes sharp``,
``--sharp-in tracker|ba|trace`` gives the sharp render to one part of the system only (the tracker's
reference, the bundle adjustment's window, the candidates' traces; class ``SharpIn``). Used for "The
collapse traced to the new points' depths", "Where the monocular depths go wrong", "Extreme blur
with sharp keyframes" and "The tracker's exposure path against the truth" in docs/benchmarks.md. Example:

    python scripts/mono_depth_probe.py runs/bench_extreme_640x480_seed0 --method mono_n64 --out /tmp/probe
"""

import argparse
import dataclasses
import json
import pathlib

import equinox as eqx
import jax.numpy as jnp
import numpy as np

from mbavo_jax.blur import blur_segments
from mbavo_jax.bench_mono import MONO_METHODS, mono_configs, trajectory_scores
from mbavo_jax.config import TrackerConfig, calibration_of, load_config
from mbavo_jax.datasets import open_sequence
from mbavo_jax.evaluation.associate import associate
from mbavo_jax.evaluation.poses import pose_matrices
from mbavo_jax.deblur import choose_deblur_n, psnr
from mbavo_jax.geometry import ExposureTrajectory, Pose
from mbavo_jax.image import linearize, quantize16
from mbavo_jax.io import read_image_gray, read_tum_trajectory
from mbavo_jax.odometry import run_odometry
from mbavo_jax.odometry import mono as om
from mbavo_jax.odometry import rgbd


@dataclasses.dataclass
class Truth:
    """The sequence's true depth maps, looked up by stamp (``associate``), each read once."""

    seq: object
    max_diff: float
    maps: dict = dataclasses.field(default_factory=dict)

    def depth(self, stamp: float) -> np.ndarray:
        _, i = associate(np.array([stamp]), np.asarray(self.seq.timestamps), self.max_diff)
        if len(i) == 0:
            raise SystemExit(f"mono_depth_probe: no frame of the sequence at stamp {stamp}")
        if int(i[0]) not in self.maps:
            self.maps[int(i[0])] = self.seq[int(i[0])].depth
        return self.maps[int(i[0])]

    def idepth(self, stamp: float, pixels: np.ndarray) -> np.ndarray:
        """(N,) true inverse depth at host pixels (N, 2) of the frame at ``stamp`` (NaN where none)."""
        d = self.depth(stamp)
        u = np.clip(np.rint(pixels[:, 0]).astype(int), 0, d.shape[1] - 1)
        v = np.clip(np.rint(pixels[:, 1]).astype(int), 0, d.shape[0] - 1)
        z = d[v, u]
        return np.where(np.isfinite(z) & (z > 0), 1.0 / np.where(z > 0, z, 1.0), np.nan)


def depth_row(truth: Truth, stamp: float, pixels: np.ndarray, depths: np.ndarray) -> dict:
    """The figures of one keyframe's points (module docstring)."""
    rt = truth.idepth(stamp, pixels)
    ok = np.isfinite(rt) & np.isfinite(depths) & (depths > 0)
    re, rt = 1.0 / depths[ok], rt[ok]
    if len(rt) < 3:
        return {"points": int(ok.sum())}
    scale = float(np.median(re / rt))
    return {"points": int(ok.sum()), "scale": round(scale, 3), "log_err": round(float(np.median(np.abs(np.log(re / (rt * scale))))), 3),
            "corr": round(float(np.corrcoef(rt, re)[0, 1]), 2), "true_cv": round(float(rt.std() / rt.mean()), 2)}


def observer(truth: Truth):
    """The loop's observer: prints ``depth_row`` of the tracker's keyframe at each new keyframe."""

    def observe(frame, before, outcome, after):
        kf = after.keyframe
        if kf is None or (before.keyframe is not None and before.keyframe.stamp == kf.stamp):
            return
        points = kf.keyframe.points[0]
        row = depth_row(truth, kf.stamp, points.pixels[points.valid], points.depths[points.valid])
        print(json.dumps({"frame": frame.index, **row}), flush=True)

    return observe


def oracle_activate(truth: Truth):
    """``MonoPipeline._activate`` that sets the points joining the window to their true inverse
    depth at the window's scale."""
    activate = om.MonoPipeline._activate

    def patched(self, mono, T_world_frame):
        before = np.asarray(mono.window.point_valid)
        mono = activate(self, mono, T_world_frame)
        w = mono.window
        new = np.asarray(w.point_valid) & ~before
        if not new.any():
            return mono
        host, pixels, est = np.asarray(w.host), np.asarray(w.pixels), np.asarray(w.idepth)
        rt = np.full(est.shape, np.nan)
        for slot, stamp in zip(mono.slots, mono.stamps):
            rt[host == slot] = truth.idepth(stamp, pixels[host == slot])
        old = before & np.isfinite(rt)
        ref = old if old.sum() > 20 else new & np.isfinite(rt)
        scale = float(np.median(est[ref] / rt[ref])) if ref.any() else 1.0
        idepth = np.where(new & np.isfinite(rt), rt * scale, est).astype(np.float32)
        return mono.replace(window=eqx.tree_at(lambda x: x.idepth, w, jnp.asarray(idepth)))

    return patched


def blur_vectors(camera, path: ExposureTrajectory, depth: np.ndarray, stride: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """((N, 2) blur segments in pixels, (N,) valid) of a grid of pixels (every ``stride``-th) at
    ``depth`` in the path's mid-exposure frame (``blur.blur_segments``)."""
    v, u = np.mgrid[stride // 2 : depth.shape[0] : stride, stride // 2 : depth.shape[1] : stride]
    pixels = jnp.asarray(np.stack([u.ravel(), v.ravel()], 1), jnp.float32)
    z = jnp.asarray(depth[v.ravel(), u.ravel()], jnp.float32)
    segments, ok = blur_segments(camera, pixels, z, path.about_middle())
    return np.asarray(segments), np.asarray(ok)


def kernel_error(camera, run_path: ExposureTrajectory, run_depth: np.ndarray, true_path: ExposureTrajectory,
                 true_depth: np.ndarray) -> dict:
    """The run's blur kernels (its path through its depth) against the truth's: the mean distance
    between the kernels' segments over the mean true blur length (``kernel_err``), the ratio of the
    mean lengths, the median angle between them (deg), and the angle between the two paths'
    translations start -> end (deg; the scale does not matter). Whole paths: a rolling shutter's
    readout is not split out."""
    vr, ok_r = blur_vectors(camera, run_path, run_depth)
    vt, ok_t = blur_vectors(camera, true_path, true_depth)
    ok = ok_r & ok_t
    if ok.sum() < 3:
        return {}
    vr, vt = vr[ok], vt[ok]
    length = np.linalg.norm(vt, axis=1).mean()
    cos = (vr * vt).sum(1) / (np.linalg.norm(vr, axis=1) * np.linalg.norm(vt, axis=1) + 1e-9)
    move = lambda p: np.asarray(p.start.inverse().compose(p.end).t)  # noqa: E731
    a, b = move(run_path), move(true_path)
    t_cos = float(a @ b / (np.linalg.norm(a) * np.linalg.norm(b) + 1e-12))
    return {"blur_px": round(float(length), 1), "kernel_err": round(float(np.linalg.norm(vr - vt, axis=1).mean() / length), 3),
            "length_ratio": round(float(np.linalg.norm(vr, axis=1).mean() / length), 3),
            "angle_deg": round(float(np.degrees(np.median(np.arccos(np.clip(cos, -1.0, 1.0))))), 1),
            "t_dir_err_deg": round(float(np.degrees(np.arccos(np.clip(t_cos, -1.0, 1.0)))), 1)}


def keyframe_deblurring(truth: Truth, how: str):
    """``RGBDPipeline.deblurred`` that deblurs a keyframe as ``how`` says (module docstring) and
    prints its PSNR against the sharp render; the frame is found by its image (the pipeline passes
    the raw image only), its depth map and exposure path by its stamp as ``truth`` matches them."""
    deblurred, seq = rgbd.RGBDPipeline.deblurred, truth.seq
    index = {hash(seq[i].image.tobytes()): i for i in range(len(seq))}
    stamps, starts, ends = seq.exposure_paths
    pose = lambda v: Pose.from_vector(jnp.asarray(v, jnp.float32))  # noqa: E731

    def patched(self, image, depth, path, readout=0.0):
        i = index.get(hash(np.asarray(image, np.float32).tobytes()))
        if i is None:
            raise SystemExit("mono_depth_probe: a keyframe image is not one of the sequence's frames")
        frame = seq[i]
        sharp = read_image_gray(pathlib.Path(seq.path) / "sharp" / f"{frame.timestamp:.6f}.png")
        if how == "sharp":  # n: what the triptych's blur model uses
            return quantize16(sharp), choose_deblur_n(depth, self.camera, path, self.config.deblur, readout)
        _, j = associate(np.array([frame.timestamp]), stamps, truth.max_diff)
        true_path = ExposureTrajectory(pose(starts[int(j[0])]), pose(ends[int(j[0])]))
        kernel = kernel_error(self.camera, path, np.asarray(depth), true_path, truth.depth(frame.timestamp)) if how == "estimated" else {}
        if how in ("true-depth", "true-path"):
            depth = truth.depth(frame.timestamp)
        if how == "true-path":
            path = true_path
        out, n = deblurred(self, image, depth, path, readout)
        print(json.dumps({"deblurred": i, "psnr_blurry": round(psnr(image, sharp), 2), "psnr_deblurred": round(psnr(out, sharp), 2),
                          **kernel}), flush=True)
        return out, n

    return patched


class SharpIn:
    """``--keyframes sharp --sharp-in PART``: the run deblurs its keyframes as usual and only PART reads
    each keyframe's sharp render in place of its deblurred image: ``tracker`` (the tracker's reference),
    ``ba`` (the window's images: the bundle adjustment and the new candidates' selection; the tracker
    and the traces keep the deblurred image) or ``trace`` (the host patterns of the candidates'
    epipolar search). Images are matched by their bytes, display and linear values alike."""

    def __init__(self, truth: Truth, part: str):
        self.truth, self.part, self.swaps = truth, part, 0
        self.to_sharp, self.to_deblurred = {}, {}
        self.index = {_key(truth.seq[i].image): i for i in range(len(truth.seq))}

    def record(self, raw, out, gamma: float) -> None:
        """Remember the deblurred ``out`` of frame image ``raw`` and its sharp render, both ways."""
        frame = self.truth.seq[self.index[_key(np.asarray(raw, np.float32))]]
        sharp = quantize16(read_image_gray(pathlib.Path(self.truth.seq.path) / "sharp" / f"{frame.timestamp:.6f}.png"))
        for a, b in ((out, sharp), (linearize(out, gamma), linearize(sharp, gamma))):
            self.to_sharp[_key(a)], self.to_deblurred[_key(b)] = b, a

    def swap(self, image, table: dict):
        """``image`` replaced through ``table`` when it is there (counted)."""
        other = table.get(_key(image))
        self.swaps += other is not None
        return image if other is None else (jnp.asarray(other) if isinstance(image, jax.Array) else other)

    def install(self) -> None:
        deblurred, make_keyframe, backend, trace = rgbd.RGBDPipeline.deblurred, om.MonoPipeline.make_keyframe, om.MonoPipeline._backend, om.trace
        probe, part = self, self.part

        def patched_deblurred(pipe, image, depth, path, readout=0.0):
            out, n = deblurred(pipe, image, depth, path, readout)
            probe.record(image, out, pipe.config.tracker.response_gamma)
            return out, n

        def patched_make_keyframe(pipe, state, image, depth, T_world_kf):
            image = probe.swap(image, probe.to_sharp if part == "tracker" else probe.to_deblurred if part == "ba" else {})
            return make_keyframe(pipe, state, image, depth, T_world_kf)

        def patched_backend(pipe, state, frame, outcome):
            new = outcome.new_keyframe
            if part == "ba" and new is not None:
                outcome = dataclasses.replace(outcome, new_keyframe=dataclasses.replace(new, image=probe.swap(new.image, probe.to_sharp)))
            return backend(pipe, state, frame, outcome)

        def patched_trace(c, host_image, *rest, **kw):
            table = probe.to_sharp if part == "trace" else probe.to_deblurred if part == "ba" else {}
            return trace(c, probe.swap(host_image, table), *rest, **kw)

        rgbd.RGBDPipeline.deblurred, om.MonoPipeline.make_keyframe = patched_deblurred, patched_make_keyframe
        om.MonoPipeline._backend, om.trace = patched_backend, patched_trace


def _key(image) -> int:
    return hash(np.asarray(image, np.float32).tobytes())


def motion_errors(seq, run: pathlib.Path, max_diff: float, block: int = 20) -> list[dict]:
    """Per block of ``block`` frame pairs: the median rotation error (deg) and translation direction
    error (deg) of the run's frame-to-frame motion against the ground truth."""
    t_est, p_est = read_tum_trajectory(run / "trajectory.txt")
    t_gt, p_gt = seq.groundtruth
    i_est, i_gt = associate(t_est, t_gt, max_diff)
    E, G = pose_matrices(p_est[i_est]), pose_matrices(p_gt[i_gt])
    de, dg = np.linalg.inv(E[:-1]) @ E[1:], np.linalg.inv(G[:-1]) @ G[1:]
    err = np.linalg.inv(dg) @ de
    rot = np.degrees(np.arccos(np.clip((np.trace(err[:, :3, :3], axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    te, tg = de[:, :3, 3], dg[:, :3, 3]
    cos = (te * tg).sum(1) / (np.linalg.norm(te, axis=1) * np.linalg.norm(tg, axis=1) + 1e-12)
    direction = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    return [{"pairs": f"{k}-{min(k + block, len(rot))}", "rot_err_deg": round(float(np.median(rot[k:k + block])), 3),
             "t_dir_err_deg": round(float(np.median(direction[k:k + block])), 1)} for k in range(0, len(rot), block)]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("sequence", help="a generated sequence (with depth maps)")
    ap.add_argument("--method", default="mono_n64", choices=list(MONO_METHODS))
    ap.add_argument("--out", required=True, help="the run's folder")
    ap.add_argument("--oracle", action="store_true", help="points join the window at their true depth (at the window's scale)")
    ap.add_argument("--keyframes", choices=("run", "estimated", "true-depth", "true-path", "sharp"), default="run",
                    help="how new keyframes are deblurred (module docstring); run: as the run does, nothing printed")
    ap.add_argument("--sharp-in", choices=("all", "tracker", "ba", "trace"), default="all",
                    help="with --keyframes sharp: which part reads the sharp render (class SharpIn); the others the deblurred image")
    ap.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", help="a setting changed (repeatable)")
    args = ap.parse_args()
    seq = open_sequence(args.sequence)
    if not seq.has_depth:
        raise SystemExit(f"mono_depth_probe: {args.sequence} has no depth maps to compare with")
    if args.keyframes != "run" and (seq.exposure_paths is None or not (pathlib.Path(args.sequence) / "sharp").is_dir()):
        raise SystemExit(f"mono_depth_probe: --keyframes needs {args.sequence}'s sharp/ renders and exposure paths")
    config = mono_configs(TrackerConfig(**calibration_of(seq.meta)), (args.method,))[args.method]
    typed = load_config(None, args.set)  # checked and typed as `mbavo track --set` does
    for item in args.set:
        section, key = item.split("=", 1)[0].split(".", 1)
        config = config.replace(**{section: {key: getattr(getattr(typed, section), key)}})
    truth = Truth(open_sequence(args.sequence), config.evaluation.t_max_diff)
    if args.oracle:
        om.MonoPipeline._activate = oracle_activate(truth)
    if args.sharp_in != "all" and args.keyframes != "sharp":
        raise SystemExit("mono_depth_probe: --sharp-in needs --keyframes sharp")
    swap = SharpIn(truth, args.sharp_in) if args.sharp_in != "all" else None
    if swap is not None:
        swap.install()
    elif args.keyframes != "run":
        rgbd.RGBDPipeline.deblurred = keyframe_deblurring(truth, args.keyframes)
    out = pathlib.Path(args.out)
    run_odometry(seq, out, config, progress=False, observer=observer(truth))
    for row in motion_errors(seq, out, config.evaluation.t_max_diff):
        print(json.dumps(row))
    if swap is not None:
        print(json.dumps({"sharp_in": swap.part, "images_swapped": swap.swaps}))
    print(json.dumps(trajectory_scores(seq, out, config.evaluation)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
