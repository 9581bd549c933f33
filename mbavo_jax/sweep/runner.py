"""The harness: a sweep's sequences made ready, its runs executed (or skipped when an earlier call
finished them) on the chosen engine, its table written. ``mbavo sweep`` and ``mbavo bench
odometry`` both run through :func:`run_sweep`. JAX-free (the workers import JAX).
"""

from __future__ import annotations

import contextlib
import dataclasses
import functools
import hashlib
import json
import pathlib
import sys

from ..config import SweepConfig
from ..errors import MbavoError
from ..progress import bar
from .engine import check_engine, map_unordered
from .spec import SweepSpec, Task, check_names
from .table import format_markdown, write_tables
from .task import error_row, finished_row, prepare_sequence, run_task, sequence_ready

__all__ = ["SweepResult", "run_sweep", "tasks_of", "code_version", "summary_line", "main"]


@dataclasses.dataclass(frozen=True)
class SweepResult:
    """A sweep's rows (in sequence x method order), how many runs were executed in this call and
    how many were kept from an earlier one, and the table files."""

    rows: list[dict]
    executed: int
    kept: int
    files: dict


@functools.cache
def code_version() -> str:
    """A digest of mbavo_jax's Python sources: a run finished by other code is not kept."""
    root = pathlib.Path(__file__).resolve().parents[1]
    digest = hashlib.sha256()
    for p in sorted(root.rglob("*.py")):
        digest.update(str(p.relative_to(root)).encode() + b"\0" + p.read_bytes())
    return digest.hexdigest()[:16]


def _absolute(path: str) -> str:
    return str(pathlib.Path(path).expanduser().resolve()) if path else ""


def _data_folders(spec: SweepSpec, out: pathlib.Path) -> dict[str, str]:
    """Each sequence's folder: its own path, or ``<out>/data/<name>`` for a generated one."""
    check_names("sweep", spec)  # every name a folder name inside ``out`` (runs/<sequence>/<method> too)
    return {s.name: str(out / "data" / s.name) if s.generated else _absolute(s.path) for s in spec.sequences}


def tasks_of(spec: SweepSpec, out) -> list[Task]:
    """Every run of the sweep, sequence by sequence, methods in order; outputs in ``<out>/runs/<sequence>/<method>``."""
    out = pathlib.Path(_absolute(str(out)))
    data, config = _data_folders(spec, out), _absolute(spec.config)
    return [Task(s.name, m, data[s.name], str(out / "runs" / s.name / m), overrides=spec.configurations.get(m, spec.base),
                 config=config, peer="" if m in spec.configurations else m, peer_depth_max=spec.peer_depth_max, code=code_version())
            for s in spec.sequences for m in spec.methods]


def _prepare(spec: SweepSpec, out: pathlib.Path, settings: SweepConfig, progress: bool) -> dict[str, str]:
    """Generate the generated sequences (on the engine, skipping those made before); the error of each that failed."""
    folders = _data_folders(spec, out)
    wanted = [(dataclasses.replace(s, source=_absolute(s.source)), folders[s.name]) for s in spec.sequences if s.generated]
    jobs = [job for job in wanted if not sequence_ready(*job)]
    failed = {}
    results = map_unordered(prepare_sequence, jobs, settings, lambda job, exc: f"generating the sequence failed: {exc}")
    with bar(len(jobs), "sequences", progress and bool(jobs), unit="seq") as pbar, contextlib.closing(results):
        for i, err in results:
            if err:
                failed[jobs[i][0].name] = err
            pbar.update()
    return failed


def _execute(tasks: list[Task], settings: SweepConfig, failed: dict[str, str], progress: bool) -> tuple[list[dict], int]:
    """Every task's row: kept from an earlier call, an error (its sequence failed), or run now; how many ran."""
    rows = [None] * len(tasks)
    todo = []
    for i, task in enumerate(tasks):
        kept = None if settings.rerun else finished_row(task)
        if task.sequence in failed:
            rows[i] = error_row(task, failed[task.sequence])
        elif kept is not None:
            rows[i] = kept
        else:
            todo.append(i)
    crashed = lambda task, exc: error_row(task, f"worker failed: {type(exc).__name__}: {' '.join(str(exc).split())[:300]}")
    results = map_unordered(run_task, [tasks[i] for i in todo], settings, crashed)
    with bar(len(todo), "sweep", progress and bool(todo), unit="run") as pbar, contextlib.closing(results):
        for j, row in results:
            rows[todo[j]] = row
            pbar.set_postfix_str(f"{row['sequence']}/{row['method']}: {row['status']}")
            pbar.update()
    return rows, len(todo)


def run_sweep(spec: SweepSpec, out, settings: SweepConfig = SweepConfig(), progress: bool = True) -> SweepResult:
    """Run ``spec`` into ``out``: ``data/`` (generated sequences), ``runs/<sequence>/<method>/``
    (each run's outputs and result.json), results.csv, results.md, ate.png. Runs an earlier call
    finished with the same task are kept unless ``settings.rerun``; failures are rows. Names that
    are not safe folder names, or an engine that cannot start, are refused before ``out`` is made;
    a second sweep into the same ``out`` while this one runs is refused (the folder's lock)."""
    from ..io import prepare_out_dir
    from ..lock import RunLock

    check_names("sweep", spec)
    check_engine(settings)
    out = prepare_out_dir(out)
    with RunLock(out) as lock:  # one sweep per folder: a second one would rewrite the runs' result.json
        lock.sign()
        failed = _prepare(spec, out, settings, progress)
        tasks = tasks_of(spec, out)
        rows, executed = _execute(tasks, settings, failed, progress)
        files = write_tables(rows, out)
    return SweepResult(rows, executed, len(tasks) - executed - sum(t.sequence in failed for t in tasks), files)


def main(path, out, settings: SweepConfig, fmt: str = "table", quiet: bool = False) -> int:
    """``mbavo sweep SWEEP.yaml --out DIR``: the table (markdown, or the rows as JSON) on stdout,
    where the files are and how many runs ran, were kept or failed on stderr; MbavoError (exit 1)
    when every run failed, once the table is written."""
    from .spec import load_sweep

    spec = load_sweep(path)
    res = run_sweep(spec, out, settings, progress=not quiet)
    print(json.dumps(res.rows, indent=2) if fmt == "json" else format_markdown(res.rows))
    print(summary_line(res), file=sys.stderr)
    if not any(r.get("status") == "ok" for r in res.rows):
        raise MbavoError(f"{path}: all {len(res.rows)} runs failed (the errors are in {res.files['markdown']})")
    return 0


def summary_line(res: SweepResult) -> str:
    """How many runs ran, were kept or failed, and where the table is."""
    failed = sum(r.get("status") != "ok" for r in res.rows)
    kept = f"{res.kept} kept from an earlier call (--rerun runs them again)" if res.kept else "0 kept"
    return (f"{len(res.rows)} runs: {res.executed} executed, {kept}, {failed} failed; "
            f"{res.files['csv']}, {res.files['markdown']}, {res.files['plot']}")
