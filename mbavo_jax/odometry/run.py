"""The sequence loop: one pipeline step per frame, its records written as it goes, and --resume.

``run_odometry`` writes per frame, so an interrupted run keeps every finished pose; ``resume``
rebuilds the loop's state from a run folder so that the rest of the run goes as if uninterrupted.
"""

from __future__ import annotations

import csv
import dataclasses
import pathlib

import jax.numpy as jnp
import numpy as np
import yaml

from ..config import RunConfig, as_dict
from ..errors import DataError, MbavoError
from ..geometry import Pose
from ..io import read_tum_trajectory
from ..progress import bar
from ..tracking import Keyframe
from .outputs import RunOutputs, keyframe_image_path, read_keyframe_image
from .rgbd import RGBDPipeline
from .exposure import RawFrame
from .state import FrameOutcome, KeyframeState, Pipeline, RunState

__all__ = ["run_odometry", "resume_state"]


def _pose(v) -> Pose:
    return Pose.from_vector(jnp.asarray(v, jnp.float32))


def _exposure_rows(out: pathlib.Path, before: float) -> list[dict]:
    """frames.csv rows of frames stamped before ``before`` (none when the file is missing)."""
    path = out / "frames.csv"
    if not path.is_file():
        return []
    with open(path, newline="") as fh:
        return [r for r in csv.DictReader(fh) if float(r["timestamp"]) < before]


def _restore_exposure(state: RunState, out: pathlib.Path, seq, before: float, poses: dict, pipeline: Pipeline) -> RunState:
    """The exposure estimate's samples and the raw frames kept for pairing, as frames.csv records
    them up to the frame stamped ``before`` (``poses``: stamp -> T_world_mid of tracked frames)."""
    if not hasattr(pipeline, "estimate"):
        return state
    rows = _exposure_rows(out, before)
    est = pipeline.estimate(state)
    samples = tuple((float(r["sample_s"]), float(r["sample_weight"]), float(r["sample_dt_s"])) for r in rows if r.get("sample_s"))
    if any(r.get("exposure") == "estimate" for r in rows):
        state = state.replace(exposure=dataclasses.replace(est, samples=samples[-est.window:]))
    stamps = np.array(sorted(poses))
    keep = pipeline.config.odometry.exposure_pair_frames
    recent = []
    for r in [r for r in rows if r.get("speed_px_s")][-keep:]:  # only the frames the pairing keeps are loaded
        k = int(np.argmin(np.abs(stamps - float(r["timestamp"]))))
        if k == 0:
            continue
        frame = seq[int(r["index"])]
        recent.append(RawFrame(frame.timestamp, frame.image, frame.depth, poses[stamps[k]], poses[stamps[k - 1]],
                               frame.timestamp - stamps[k - 1], float(r["speed_px_s"])))
    return state.replace(recent=tuple(recent))


def resume_state(out, seq, pipeline: Pipeline) -> tuple[RunState, int]:
    """(state, index of the next frame) of the run in ``out``, or (a fresh state, 0) when it holds
    no finished frame. The loop goes on after the last tracked frame or keyframe (a keyframe made
    after drops comes later than the last tracked frame), with the last two mid poses as velocity."""
    out = pathlib.Path(out)
    if not ((out / "trajectory.txt").is_file() and (out / "keyframes.txt").is_file()):
        return RunState(), 0
    t_done, p_done = read_tum_trajectory(out / "trajectory.txt")
    t_kf, p_kf = read_tum_trajectory(out / "keyframes.txt")
    stamps = seq.timestamps
    start = int(np.searchsorted(stamps, max(t_done[-1], t_kf[-1]) + 1e-6))
    mids = tuple((float(t), _pose(p)) for t, p in zip(t_done[-2:], p_done[-2:]))
    k = int(np.argmin(np.abs(stamps - t_kf[-1])))
    image = read_keyframe_image(out, t_kf[-1])
    if image is None:
        raise DataError(keyframe_image_path(out, t_kf[-1]), "keyframe image needed for --resume is missing")
    cfg = pipeline.config
    kf = KeyframeState(Keyframe.create(image, seq[k].depth, seq.camera, cfg.tracker), _pose(p_kf[-1]), float(t_kf[-1]))
    triptychs = len(list(out.glob("triptych_*.png")))
    state = RunState(keyframe=kf, mids=mids, keyframes=len(t_kf), tracked=len(t_done), triptychs=triptychs)
    before = stamps[start] - 1e-6 if start < len(stamps) else np.inf
    state = _restore_exposure(state, out, seq, before, {float(t): _pose(p) for t, p in zip(t_done, p_done)}, pipeline)
    # a keyframe made without an exposure path that no frame has tracked against yet is still the raw
    # image and waits to be deblurred: the first frame with nothing tracked after it, or a reset
    # after drops (later than every tracked frame; the drops before it forgot the velocity)
    reset = t_kf[-1] > t_done[-1] + 1e-6
    if reset or (len(t_done) == 1 and abs(t_kf[-1] - t_done[0]) < 1e-6):
        state = state.replace(pending=pipeline.pending_of(seq[k]))
    if reset:
        state = state.replace(mids=mids[-1:])
    return state, start


def _summary(state: RunState, frames: int, start: RunState, last: FrameOutcome | None) -> dict:
    """The run's counts over the frames this call processed, and its exposure time after the last."""
    tracked, dropped = state.tracked - start.tracked, state.dropped - start.dropped
    out = {"frames": frames, "tracked": tracked, "dropped": dropped, "keyframes": state.keyframes,
           "frame_drop_rate": dropped / max(frames, 1)}
    if last is not None and last.exposure is not None:
        e = last.exposure
        out.update(exposure=e.mode, exposure_ms=1000 * e.seconds)
        if e.fraction is not None and e.mode == "estimate":
            out.update(exposure_fraction=e.fraction, exposure_samples=0 if e.estimate is None else e.estimate.count)
    return out


def run_odometry(seq, out, config: RunConfig = RunConfig(), resume: bool = False, max_frames: int | None = None,
                 progress: bool = True, pipeline: Pipeline | None = None) -> dict:
    """Track a whole RGB-D sequence into ``out`` and return a summary (frames, tracked, dropped,
    keyframes, frame-drop rate). ``resume``: continue after the last frame of the run in ``out``.
    ``pipeline``: the per-frame step (default: the RGB-D pipeline with ``config``; a given pipeline
    brings its own config)."""
    out = pathlib.Path(out)
    if not seq.has_depth:
        raise MbavoError(f"{seq.path}: 'mbavo track' needs depth (an RGB-D sequence); the monocular back-end is not built yet")
    pipeline = pipeline or RGBDPipeline(seq.camera, config)
    config = pipeline.config
    out.mkdir(parents=True, exist_ok=True)
    (out / "config.yaml").write_text(yaml.safe_dump(as_dict(config), sort_keys=False))
    state, start = resume_state(out, seq, pipeline) if resume else (RunState(), 0)
    first, outcome = state, None
    n_total = len(seq) if max_frames is None else min(len(seq), max_frames)
    with RunOutputs(out, seq.camera, config.tracker.response_gamma, append=start > 0) as outputs, \
            bar(max(n_total - start, 0), "track", progress) as pbar:
        for index in range(start, n_total):
            state, outcome = pipeline.step(state, seq[index], index)
            outputs.write(outcome)
            pbar.set_postfix(status=outcome.status, keyframes=state.keyframes, dropped=state.dropped, refresh=False)
            pbar.update()
    return _summary(state, n_total - start, first, outcome)
