"""``mbavo sweep``: many runs at once, sequences x configurations (and peers) from a YAML, on a local
process pool or Ray, into one results table; ``mbavo bench odometry`` is one such sweep.

``spec`` reads and checks the sweep file, ``engine`` executes items (local pool or Ray, one code
path), ``task`` is what a worker does (one run, or generating one sequence), ``table`` writes the
results, ``runner`` ties them together. Nothing here imports JAX; the workers do.
"""

from .runner import SweepResult, code_version, main, run_sweep, summary_line, tasks_of
from .spec import PEERS, SequenceSpec, SweepSpec, Task, as_overrides, load_sweep, parse_sweep
from .table import format_markdown, write_tables
from .task import prepare_sequence, run_task

__all__ = ["SweepResult", "code_version", "main", "run_sweep", "summary_line", "tasks_of", "PEERS", "SequenceSpec", "SweepSpec", "Task", "as_overrides",
           "load_sweep", "parse_sweep", "format_markdown", "write_tables", "prepare_sequence", "run_task"]
