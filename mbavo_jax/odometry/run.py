"""The sequence loop: one pipeline step per frame, its records written as it goes, and --resume.

``run_odometry`` writes per frame, so an interrupted run keeps every finished pose; ``resume``
rebuilds the loop's state from a run folder so that the rest of the run goes as if uninterrupted.
"""

from __future__ import annotations

import dataclasses
import pathlib
import sys
import time
from typing import Callable

import jax.numpy as jnp
import numpy as np

from ..config import RunConfig
from ..datasets import open_sequence
from ..errors import DataError, MbavoError
from ..geometry import Pose
from ..image import quantize16
from ..io import prepare_out_dir, read_tum_trajectory
from ..progress import bar
from ..runtime import compile_counts, enable_compilation_cache, make_room_for_programs, release_free_memory
from ..tracking import Keyframe, Status
from ..tracking.memory import check_memory
from .exposure import RawFrame, with_next
from .folder import Checkpoint, check_resume, clear_run, cut_to_checkpoint, read_checkpoint, reconcile, record_run, write_checkpoint
from ..lock import RunLock
from .outputs import RunOutputs, keyframe_image_path, read_keyframe_image
from .mono import MonoPipeline
from .rgbd import RGBDPipeline
from .state import Fit, FrameOutcome, KeyframeState, Pipeline, RunState

__all__ = ["run_odometry", "resume_state", "choose_pipeline"]


def _pose(v) -> Pose:
    return Pose.from_vector(jnp.asarray(v, jnp.float32))


def _restore_exposure(state: RunState, rows: list[dict], seq, poses: dict, pipeline: Pipeline) -> RunState:
    """The exposure estimate's samples and the raw frames kept for pairing, as the committed
    frames.csv ``rows`` record them (``poses``: stamp -> T_world_mid of tracked frames)."""
    if not hasattr(pipeline, "estimate"):
        return state
    est = pipeline.estimate(state)  # the exposure probe's samples, if any, come first
    samples = tuple((float(r["sample_s"]), float(r["sample_weight"]), float(r["sample_dt_s"])) for r in rows if r.get("sample_s"))
    if any(r.get("exposure") == "estimate" for r in rows):
        state = state.replace(exposure=dataclasses.replace(est, samples=(*est.samples, *samples)[-est.window:]))
    stamps = np.array(sorted(poses))
    raw = [r for r in rows if r.get("speed_px_s")]
    recent = []
    for i in range(max(len(raw) - pipeline.config.odometry.exposure_pair_frames, 0), len(raw)):  # the frames pairing keeps
        r, after = raw[i], raw[i + 1] if i + 1 < len(raw) else {}
        k = int(np.argmin(np.abs(stamps - float(r["timestamp"]))))
        if k == 0:
            continue
        frame = seq[int(r["index"])]
        kept = RawFrame(frame.timestamp, frame.image, frame.depth, poses[stamps[k]], poses[stamps[k - 1]],
                        frame.timestamp - stamps[k - 1], float(r["speed_px_s"]))
        if after.get("prev_speed_px_s") and k + 1 < len(stamps):  # the next raw frame completed its central speed
            kept = with_next(kept, poses[stamps[k + 1]], stamps[k + 1] - frame.timestamp, float(after["prev_speed_px_s"]))
        recent.append(kept)
    return state.replace(recent=tuple(recent))


OK_STATUSES = {s.name.lower() for s in Status if s.ok}


def _loop_counters(rows: list[dict]) -> dict:
    """What the loop counted when it committed ``rows``: drops in a row, whether the velocity was
    forgotten (a drop other than an implausible fit since the last tracked frame), and the fits
    of the tracked frames since the last reset."""
    drops, forgot, fits = 0, False, []
    for r in rows:
        if r["status"] in OK_STATUSES:
            drops, forgot = 0, False
            fits.append(Fit(float(r["rms"]), float(r["jump_px"]) if r.get("jump_px") else None))
        elif r["status"] != "keyframe":
            drops, forgot = drops + 1, forgot or r["status"] != Status.IMPLAUSIBLE.name.lower()
            if r["keyframe"] == "1":  # a reset: a new start
                drops, fits = 0, []
    return {"consecutive_drops": drops, "forgot": forgot, "fits": tuple(fits)}


def _keyframe_image(out: pathlib.Path, frame, stamp: float, pending: bool) -> np.ndarray:
    """The image the run tracked against: the raw ``frame`` while it waits to be deblurred, else the
    stored keyframe image."""
    if pending:
        return quantize16(frame.image)
    image = read_keyframe_image(out, stamp)
    if image is None:
        raise DataError(keyframe_image_path(out, stamp), "keyframe image needed for --resume is missing or unreadable "
                        "(run without --resume to start afresh)")
    return image


def _records(out: pathlib.Path, rows: list[dict]):
    """(stamps, poses) of trajectory.txt and keyframes.txt, which a run with committed ``rows`` has."""
    for name in ("trajectory.txt", "keyframes.txt"):
        if not (out / name).is_file():
            raise DataError(out / name, f"missing, but frames.csv records {len(rows)} frames: cannot --resume "
                            "(run without --resume to start afresh)")
    return read_tum_trajectory(out / "trajectory.txt"), read_tum_trajectory(out / "keyframes.txt")


def start_state(seq, pipeline: Pipeline, progress: bool = False) -> RunState:
    """The state the loop starts from (``pipeline.start_state``: e.g. an exposure probe), else a fresh one."""
    return pipeline.start_state(seq, progress) if hasattr(pipeline, "start_state") else RunState()


def checkpoints(pipeline: Pipeline) -> bool:
    """Whether ``pipeline`` resumes from a checkpoint (``folder.Checkpoint``) rather than from its records."""
    return getattr(pipeline, "checkpoints", False)


def resume_state(out, seq, pipeline: Pipeline, progress: bool = False) -> tuple[RunState, int]:
    """(state, index of the next frame) of the run in ``out``, cut back to its last committed frame
    (``folder.reconcile``), or (``start_state``, 0) when it holds none. The state is the one the
    loop had after that frame, so the resumed run goes on exactly as the uninterrupted one: rebuilt
    from the records, or, for a pipeline that ``checkpoints``, its last checkpoint (the run cut
    back to that frame)."""
    out = pathlib.Path(out)
    rows = reconcile(out)
    if not rows:
        if (out / "trajectory.txt").is_file() and len((out / "trajectory.txt").read_text().splitlines()) > 1:
            raise DataError(out / "frames.csv", "missing or empty, so the run's frames are not known: cannot --resume "
                            "(run without --resume to start afresh)")
        return start_state(seq, pipeline, progress), 0
    if checkpoints(pipeline):
        checkpoint = read_checkpoint(out)
        cut_to_checkpoint(out, checkpoint)
        return checkpoint.state, checkpoint.index + 1
    (t_done, p_done), (t_kf, p_kf) = _records(out, rows)
    start, counters = int(rows[-1]["index"]) + 1, _loop_counters(rows)
    k = int(np.argmin(np.abs(seq.timestamps - t_kf[-1])))
    # a keyframe made without an exposure path that no frame has tracked against yet is still the raw
    # image and waits to be deblurred: the first frame with nothing tracked after it, or a reset
    # after drops (later than every tracked frame)
    reset = t_kf[-1] > t_done[-1] + 1e-6
    pending = reset or (len(t_done) == 1 and abs(t_kf[-1] - t_done[0]) < 1e-6)
    cfg, frame = pipeline.config, seq[k]
    waiting = pipeline.pending_of(frame) if pending else None
    image = _keyframe_image(out, frame, float(t_kf[-1]), waiting is not None)
    kf = KeyframeState(Keyframe.create(image, frame.depth, seq.camera, cfg.tracker), _pose(p_kf[-1]), float(t_kf[-1]))
    mids = tuple((float(t), _pose(p)) for t, p in zip(t_done[-2:], p_done[-2:]))
    state = RunState(keyframe=kf, mids=mids[-1:] if counters["forgot"] or reset else mids, keyframes=len(t_kf), tracked=len(t_done),
                     triptychs=len(list(out.glob("triptych_*.png"))), consecutive_drops=counters["consecutive_drops"],
                     fits=counters["fits"][-cfg.odometry.reject_window:])
    fresh = start_state(seq, pipeline, progress)
    state = state.replace(exposure=fresh.exposure, probed_until=fresh.probed_until)
    state = _restore_exposure(state, rows, seq, {float(t): _pose(p) for t, p in zip(t_done, p_done)}, pipeline)
    return state.replace(pending=waiting), start


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


def _compilation(before: dict, startup: float | None) -> dict:
    """The run's start-up: seconds to its first tracked frame (compilation included) and the
    programs it compiled or loaded from the compilation cache."""
    now = compile_counts()
    out = {"compiled": now["compiled"] - before["compiled"], "cache_hits": now["cache_hits"] - before["cache_hits"]}
    return {**({"startup_s": startup} if startup is not None else {}), **out}


def _prepare(out: pathlib.Path, seq, config: RunConfig, resume: bool, resume_anyway: bool, pipeline: Pipeline,
             progress: bool, released: str = "") -> tuple[RunState, int, str, RunLock]:
    """The run folder made ready and locked, the loop's starting point, what the image size changes
    in the settings ('' when nothing) and the folder's lock (held: the caller releases it): checks
    (memory, image size) first, then the lock (refused while another process writes the folder),
    then, for a resume, the sequence and settings, and a fresh folder or the reconciled earlier run.
    With the progress, the notes (the size note, ``released``: the programs released before the
    run) are printed once the checks have passed: input refused there gets its one line only."""
    check_memory(config, seq.camera.height, seq.camera.width)
    note = config.tracker.size_note(seq.camera.height, seq.camera.width)  # raises on images too small to track
    prepare_out_dir(out)
    lock = RunLock(out)  # one writer per run folder: a second one is refused before it touches a file
    try:
        state, start = _ready(out, seq, config, resume, resume_anyway, pipeline, progress, (released, note), lock)
    except BaseException:
        lock.release()
        raise
    return state, start, note, lock


def _ready(out: pathlib.Path, seq, config: RunConfig, resume: bool, resume_anyway: bool, pipeline: Pipeline,
           progress: bool, notes: tuple[str, ...], lock: RunLock) -> tuple[RunState, int]:
    """The locked run folder ready (see :func:`_prepare`): the loop's state and first frame. The
    lock is signed with this process's pid once the checks of a resume have passed."""
    if resume:
        check_resume(out, seq, config, resume_anyway)
        state, start = resume_state(out, seq, pipeline, progress)
    lock.sign()  # the run goes ahead: a second writer's message names this process
    if not resume:
        state, start = start_state(seq, pipeline, progress), 0
    for line in notes if progress else ():
        if line:
            print(f"mbavo: note: {line}", file=sys.stderr)
    if start == 0:
        clear_run(out)
    record_run(out, seq, config, start, resume and resume_anyway)
    return state, start


def run_odometry(seq, out, config: RunConfig = RunConfig(), resume: bool = False, max_frames: int | None = None,
                 progress: bool = True, pipeline: Pipeline | None = None, resume_anyway: bool = False,
                 observer: Callable | None = None) -> dict:
    """Track a whole RGB-D sequence into ``out`` and return a summary (frames, tracked, dropped,
    keyframes, frame-drop rate; ``note``: what the image size changed). ``resume``: continue after
    the last committed frame of the run in ``out``, which must have been made on the same sequence
    with the same settings unless ``resume_anyway``. ``pipeline``: the per-frame step (default: the RGB-D pipeline with
    ``config``; a given pipeline brings its own config). ``observer``: called as
    ``observer(frame, state_before, outcome, state_after)`` after each frame's records are written
    (e.g. ``viewer.RunViewer``)."""
    out = pathlib.Path(out)
    if max_frames is not None and max_frames < 1:
        raise MbavoError(f"--max-frames must be at least 1, got {max_frames}")
    pipeline = pipeline or choose_pipeline(seq, config)
    config = pipeline.config
    enable_compilation_cache(config.runtime)
    released = make_room_for_programs(config.runtime)
    t_start, counts_start, startup = time.perf_counter(), compile_counts(), None
    if isinstance(pipeline, MonoPipeline) and seq.has_depth:  # monocular: the depth maps are not read
        seq = open_sequence(seq.path, seq.kind, depth=False)
    state, start, note, lock = _prepare(out, seq, config, resume, resume_anyway, pipeline, progress, released)
    first, outcome = state, None
    n_total = len(seq) if max_frames is None else min(len(seq), max_frames)
    with lock, RunOutputs(out, seq.camera, config.tracker.response_gamma, append=start > 0) as outputs, \
            bar(max(n_total - start, 0), "track", progress) as pbar:
        waiting = 0
        for index in range(start, n_total):
            frame, before = seq[index], state
            state, outcome = pipeline.step(state, frame, index)
            if config.runtime.trim_memory:
                release_free_memory()
            outputs.write(outcome)
            every = config.runtime.checkpoint_every
            if checkpoints(pipeline) and every and ((index + 1) % every == 0 or index + 1 == n_total):
                write_checkpoint(out, Checkpoint(index, state, outputs.point_count))
            if observer is not None:
                observer(frame, before, outcome, state)
            if startup is None and outcome.T_world_mid is not None and index > start:
                startup = time.perf_counter() - t_start
            waiting += outcome.status == "initialising"
            pbar.set_postfix(status=outcome.note or outcome.status, keyframes=state.keyframes, dropped=state.dropped, refresh=False)
            pbar.update()
        cloud = pipeline.final_points(state) if hasattr(pipeline, "final_points") else None
        if cloud is not None:
            outputs.write_points(cloud)
    summary = {**_summary(state, n_total - start, first, outcome), **_compilation(counts_start, startup)}
    if isinstance(pipeline, MonoPipeline):
        summary.update(mode="mono", initialising=waiting)
    return {**summary, **({"note": note} if note else {})}


def choose_pipeline(seq, config: RunConfig) -> Pipeline:
    """The RGB-D pipeline when the sequence has depth and ``odometry.mode`` allows it, else the
    monocular one."""
    mode = config.odometry.mode
    if mode == "rgbd" and not seq.has_depth:
        raise MbavoError(f"{seq.path}: odometry.mode rgbd needs depth, and this sequence has none (use --mode mono or auto)")
    mono = mode == "mono" or (mode == "auto" and not seq.has_depth)
    return (MonoPipeline if mono else RGBDPipeline)(seq.camera, config)
