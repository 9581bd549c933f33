"""What a worker does: one run of a sweep (:func:`run_task`) or the generation of one of its
sequences (:func:`prepare_sequence`). Each writes its record when it is done, so that a sweep
started again skips it; a failure is returned as a row, never raised.
"""

from __future__ import annotations

import json
import os
import pathlib
import shutil
import time
import traceback

from ..errors import MbavoError
from .spec import SequenceSpec, Task

__all__ = ["run_task", "prepare_sequence", "sequence_ready", "finished_row", "error_row", "RESULT", "DATA_RECORD"]

RESULT = "result.json"  # in a run folder: {"task": Task.identity(), "row": row}
DATA_RECORD = "sweep_data.json"  # in a generated sequence folder: how it was made


def _write_json(path: pathlib.Path, data) -> None:
    """Write ``data`` as JSON in one step (a temporary file renamed over ``path``)."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    tmp.write_text(json.dumps(data, indent=2, default=str))
    tmp.replace(path)


def _read_json(path: pathlib.Path):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return None


def _message(exc: BaseException) -> str:
    """One line: a user error's message, else the exception's type and message."""
    text = str(exc) if isinstance(exc, MbavoError) else f"{type(exc).__name__}: {exc}"
    return " ".join(text.split()) or type(exc).__name__


def error_row(task: Task, message: str) -> dict:
    """The row of a run that failed (or never ran) with ``message``."""
    return {"sequence": task.sequence, "method": task.method, "status": "error", "error": message,
            "overrides": " ".join(task.overrides)}


def finished_row(task: Task) -> dict | None:
    """The row an earlier call recorded for this very task when it finished without error, else None."""
    record = _read_json(pathlib.Path(task.out) / RESULT)
    if not isinstance(record, dict) or record.get("task") != task.identity():
        return None
    row = record.get("row")
    return row if isinstance(row, dict) and row.get("status") == "ok" else None


def _sequence_info(seq, data: str, config) -> dict:
    """What the table says about the sequence: frames, mean blur (generated ones), depth noise used."""
    import yaml

    synth = pathlib.Path(data) / "synth.yaml"
    blur = (yaml.safe_load(synth.read_text()) or {}).get("mean_blur_px") if synth.is_file() else None
    return {"frames": len(seq), "mean_blur_px": blur, "depth_sigma": list(config.tracker.depth_sigma)}


def _score(task: Task) -> dict:
    """Run the task's method over its sequence and score it."""
    from ..methods import run_ours, run_peer
    from ..config import calibration_of, load_config
    from ..datasets import open_sequence

    seq = open_sequence(task.data)
    config = load_config(task.config or None, list(task.overrides), calibration_of(seq.meta))
    out = pathlib.Path(task.out)
    metrics = run_peer(seq, out, task.peer, config.evaluation, task.peer_depth_max) if task.peer else run_ours(seq, out, config)
    return {**_sequence_info(seq, task.data, config), **metrics}


def run_task(task: Task) -> dict:
    """One run of a sweep: its row (sequence, method, status, the benchmark's metrics, seconds),
    also written to ``<task.out>/result.json``; an exception becomes a row with ``error`` (and
    its traceback in ``error.txt``)."""
    t0 = time.perf_counter()
    out = pathlib.Path(task.out)
    out.mkdir(parents=True, exist_ok=True)
    for name in (RESULT, "error.txt"):
        (out / name).unlink(missing_ok=True)
    try:
        row = {"sequence": task.sequence, "method": task.method, "status": "ok", **_score(task),
               "overrides": " ".join(task.overrides)}
    except Exception as exc:  # one failing run is a row of the table, never the end of the sweep
        row = error_row(task, _message(exc))
        (out / "error.txt").write_text(traceback.format_exc())
    row["seconds"] = round(time.perf_counter() - t0, 2)
    _write_json(out / RESULT, {"task": task.identity(), "row": row})
    return row


def _generate(spec: SequenceSpec, out: pathlib.Path) -> None:
    from ..config import SynthConfig
    from ..datasets import open_sequence
    from ..synthetic import blur_real_sequence, generate_sequence

    if spec.source:
        blur_real_sequence(open_sequence(spec.source), out, blur_px=spec.blur_px, seed=spec.seed, progress=False)
    else:
        generate_sequence(SynthConfig(**spec.synth), out, progress=False)


def _data_record(spec: SequenceSpec) -> dict:
    return json.loads(json.dumps({"synth": spec.synth, "source": spec.source, "blur_px": spec.blur_px, "seed": spec.seed}))


def sequence_ready(spec: SequenceSpec, folder) -> bool:
    """Whether ``folder`` holds the sequence ``spec``, generated completely by an earlier call."""
    return _read_json(pathlib.Path(folder) / DATA_RECORD) == _data_record(spec)


def prepare_sequence(job: tuple[SequenceSpec, str]) -> str:
    """Generate the sequence ``spec`` into the folder ``out`` (``job``), unless a finished one made
    the same way is there; '' when it is ready, else the error (one line)."""
    spec, folder = job
    out = pathlib.Path(folder)
    record = _data_record(spec)
    if sequence_ready(spec, out):
        return ""
    shutil.rmtree(out, ignore_errors=True)  # an interrupted or different generation: start afresh
    try:
        _generate(spec, out)
    except Exception as exc:  # the sequence's runs become error rows; the others go on
        return f"generating the sequence failed: {_message(exc)}"
    _write_json(out / DATA_RECORD, record)
    return ""
