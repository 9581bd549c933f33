"""A run folder's bookkeeping: what a run writes there, which sequence and settings it was made with
(``run.yaml``), and reconciling its files after a kill.

A frame is committed when its frames.csv row is on disk: ``RunOutputs.write`` writes the keyframe
image first, then the trajectory, exposure and keyframe lines, and the row last. ``reconcile``
cuts the other files back to the last committed frame, so ``--resume`` continues from a state in
which every file agrees, wherever the run was stopped. A pipeline whose state cannot be rebuilt
from these files (the monocular one: its window and points) also leaves a :class:`Checkpoint`
after each committed frame (``checkpoint.npz``: arrays and a JSON header, see ``odometry.checkpoint``;
never a pickle); its resume cuts the run back to the checkpoint's frame.
"""

from __future__ import annotations

import csv
import hashlib
import io
import os
import pathlib
import shutil

import numpy as np
import yaml

from ..config import RunConfig, as_dict
from ..errors import DataError, MbavoError
from ..evaluation.runs import RUN_PLOTS
from ..io import PlyWriter, read_ply
from .checkpoint import Checkpoint, load_checkpoint, save_checkpoint

__all__ = ["RUN_FILES", "clear_run", "sequence_fingerprint", "check_resume", "record_run", "reconcile", "committed_rows",
           "Checkpoint", "write_checkpoint", "read_checkpoint", "cut_to_checkpoint"]

CHECKPOINT = "checkpoint.npz"
OLD_CHECKPOINT = "checkpoint.pkl"  # earlier versions' checkpoint (a pickle): removed with a run, refused by --resume, never read
RUN_FILES = ("trajectory.txt", "exposure.txt", "exposure_spline.txt", "keyframes.txt", "frames.csv", "config.yaml", "run.yaml",
             "points.ply", CHECKPOINT, OLD_CHECKPOINT, *RUN_PLOTS)
TEXT_RECORDS = ("trajectory.txt", "exposure.txt", "exposure_spline.txt", "keyframes.txt")  # stamped lines, cut back by ``reconcile``


def clear_run(out: pathlib.Path) -> None:
    """Remove what an earlier run wrote into ``out`` (its files, keyframe images, triptychs, resumed
    configs); anything else in the folder is left alone."""
    for name in RUN_FILES:
        (out / name).unlink(missing_ok=True)
    for stale in [*out.glob("triptych_*.png"), *out.glob("config.resumed_at_*.yaml")]:
        stale.unlink()
    if (out / "keyframes").is_dir():
        shutil.rmtree(out / "keyframes")


def sequence_fingerprint(seq) -> dict:
    """What identifies a sequence: its folder, frame count, and a digest of its timestamps, camera
    and first frame's image file."""
    h = hashlib.sha256(np.asarray(seq.timestamps, np.float64).tobytes())
    h.update(repr(sorted(seq.camera.as_dict().items())).encode())
    first = pathlib.Path(seq[0].path) if len(seq) else None
    if first is not None and first.is_file():
        h.update(first.read_bytes())
    return {"path": str(pathlib.Path(seq.path).resolve()), "frames": len(seq), "digest": h.hexdigest()[:16],
            "camera_model": seq.camera_model["model"]}


def _settings_changes(before: dict, after: dict) -> list[str]:
    """``section.key: old -> new`` for every setting that differs (but the ``runtime`` section's,
    which change how the process runs, not its results)."""
    return [f"{s}.{k}: {v} -> {after.get(s, {}).get(k)}" for s, values in before.items() for k, v in values.items()
            if s != "runtime" and after.get(s, {}).get(k) != v]


def check_resume(out: pathlib.Path, seq, config: RunConfig, force: bool) -> None:
    """Refuse (one line) to resume a run made on another sequence or with other settings, unless
    ``force``. A run folder without ``run.yaml`` (older runs) is not checked."""
    path = out / "run.yaml"
    if force or not path.is_file():
        return
    record = yaml.safe_load(path.read_text()) or {}
    first = record.get("segments", [{}])[0]
    if record.get("sequence", {}).get("digest") != sequence_fingerprint(seq)["digest"]:
        raise MbavoError(f"{out}: --resume of a run made on another sequence ({record.get('sequence', {}).get('path')}); "
                         "use another --out, or --resume-anyway to continue regardless")
    changes = _settings_changes(first.get("settings", {}), as_dict(config))
    if changes:
        raise MbavoError(f"{out}: --resume with other settings than the run's ({'; '.join(changes[:3])}"
                         f"{'; ...' if len(changes) > 3 else ''}); use the same --config/--set, or --resume-anyway")


def record_run(out: pathlib.Path, seq, config: RunConfig, start: int, forced: bool) -> None:
    """Add this call's segment (first frame, settings, whether the checks were overridden) to
    ``run.yaml``; the first segment's settings also go to ``config.yaml``, a resumed segment's with
    other settings to ``config.resumed_at_<frame>.yaml``."""
    path = out / "run.yaml"
    record = yaml.safe_load(path.read_text()) if start > 0 and path.is_file() else None
    record = record or {"sequence": sequence_fingerprint(seq), "segments": []}
    settings = as_dict(config)
    record["segments"].append({"first_frame": start, "resume_anyway": forced, "settings": settings})
    if not record["segments"][1:]:
        _write_atomic(out / "config.yaml", yaml.safe_dump(settings, sort_keys=False))
    elif _settings_changes(record["segments"][0]["settings"], settings):
        _write_atomic(out / f"config.resumed_at_{start}.yaml", yaml.safe_dump(settings, sort_keys=False))
    _write_atomic(path, yaml.safe_dump(record, sort_keys=False))


def _write_atomic(path: pathlib.Path, data: str | bytes) -> None:
    """Replace ``path`` by ``data`` in one step (a kill leaves the old or the new file)."""
    tmp = path.with_name(path.name + ".tmp")
    with open(tmp, "wb") as fh:
        fh.write(data.encode() if isinstance(data, str) else data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _complete_lines(data: bytes) -> bytes:
    """``data`` up to its last newline (a line cut short by a kill is dropped)."""
    return data[: data.rfind(b"\n") + 1]


def _rows(data: bytes) -> list[dict]:
    """The complete rows of frames.csv's bytes ``data``: one per committed frame."""
    text = _complete_lines(data).decode("utf-8", errors="replace")
    return [r for r in csv.DictReader(io.StringIO(text, newline="")) if None not in r and None not in r.values()]


def committed_rows(out: pathlib.Path) -> list[dict]:
    """frames.csv's complete rows: one per committed frame."""
    path = out / "frames.csv"
    return _rows(path.read_bytes()) if path.is_file() else []


def _cut(path: pathlib.Path, last_stamp: float) -> None:
    """Keep the comment lines of ``path`` and its complete lines stamped at most ``last_stamp``."""
    if not path.is_file():
        return
    data = path.read_bytes()
    keep = []
    for line in data.splitlines(keepends=True):
        try:
            ok = line.startswith(b"#") or (line.endswith(b"\n") and float(line.split()[0]) <= last_stamp + 1e-7)
        except (ValueError, IndexError):
            ok = False
        if ok:
            keep.append(line)
    if b"".join(keep) != data:
        _write_atomic(path, b"".join(keep))


def reconcile(out: pathlib.Path, last_index: int | None = None) -> list[dict]:
    """Cut a run folder back to its last committed frame (the last complete frames.csv row), or to
    frame ``last_index`` when given: later rows, a partial row and the text records stamped later
    go. Returns the rows kept."""
    path = out / "frames.csv"
    data = path.read_bytes() if path.is_file() else b""
    rows, kept = _rows(data), _complete_lines(data)
    if last_index is not None:
        rows = [r for r in rows if int(r["index"]) <= last_index]
        kept = b"".join(kept.splitlines(keepends=True)[: 1 + len(rows)])  # the header and those rows
    if kept != data:
        _write_atomic(path, kept)
    last = float(rows[-1]["timestamp"]) if rows else -np.inf
    for name in TEXT_RECORDS:
        _cut(out / name, last)
    return rows


def write_checkpoint(out: pathlib.Path, checkpoint: Checkpoint) -> None:
    """``checkpoint`` written to the run folder (plain data), replacing the previous one in one step."""
    save_checkpoint(out / CHECKPOINT, checkpoint)


def read_checkpoint(out: pathlib.Path) -> Checkpoint:
    """The run folder's :class:`Checkpoint`, read as data only (``odometry.checkpoint``); a missing,
    foreign or malformed one is one line, and an earlier version's pickle is refused unread."""
    path = out / CHECKPOINT
    if not path.is_file() and (out / OLD_CHECKPOINT).is_file():
        raise DataError(out / OLD_CHECKPOINT, "a checkpoint of an earlier version (a pickle), which is never read: cannot --resume "
                        "(run without --resume to start afresh)")
    if not path.is_file():
        raise DataError(path, "missing, so the monocular state is not known: cannot --resume (run without --resume to start afresh)")
    return load_checkpoint(path)


def cut_to_checkpoint(out: pathlib.Path, checkpoint: Checkpoint) -> list[dict]:
    """The run folder cut back to the checkpoint's frame: the rows and stamped records after it
    (``reconcile``), the points.ply vertices and triptychs written after it. Returns the rows kept."""
    rows = reconcile(out, checkpoint.index)
    if not rows or int(rows[-1]["index"]) != checkpoint.index:
        raise DataError(out / CHECKPOINT, f"records frame {checkpoint.index}, which frames.csv does not hold: cannot --resume "
                        "(run without --resume to start afresh)")
    ply = out / "points.ply"
    if ply.is_file():
        xyz, intensity = read_ply(ply)
        if len(xyz) != checkpoint.points:
            writer = PlyWriter(ply.with_name(ply.name + ".tmp"))
            writer.write(xyz[: checkpoint.points], intensity[: checkpoint.points])
            writer.close()
            os.replace(ply.with_name(ply.name + ".tmp"), ply)
    for picture in out.glob("triptych_*.png"):
        if int(picture.stem.split("_")[1]) >= checkpoint.state.triptychs:
            picture.unlink()
    return rows
