"""The command line starts fast: ``mbavo --help`` and a usage error import no JAX (checked in a fresh
interpreter, the only way to see what an import pulls in)."""

from __future__ import annotations

import subprocess
import sys
import time

# ``python -c FRESH ARGS...``: mbavo's main(ARGS) in a fresh interpreter; prints which JAX modules it
# imported (on stdout, after main's own output) and exits with main's status.
FRESH = """
import sys
import mbavo_jax.cli as cli
try:
    status = cli.main(sys.argv[1:])
except SystemExit as exc:
    status = exc.code
loaded = sorted(m for m in sys.modules if m.split(".")[0] in ("jax", "jaxlib"))
print("JAX MODULES:", ",".join(loaded) or "none")
sys.exit(status)
"""


def fresh_mbavo(*args) -> tuple[subprocess.CompletedProcess, float]:
    t0 = time.perf_counter()
    r = subprocess.run([sys.executable, "-c", FRESH, *map(str, args)], capture_output=True, text=True, timeout=120)
    return r, time.perf_counter() - t0


def test_help_is_fast_and_imports_no_jax():
    # best of three: the machine may be busy; the claim is that --help does not take a second
    runs = [fresh_mbavo("--help") for _ in range(3)]
    r, _ = runs[0]
    assert r.returncode == 0, r.stderr
    assert r.stdout.startswith("usage: mbavo") and "track" in r.stdout
    assert r.stdout.strip().splitlines()[-1] == "JAX MODULES: none", r.stdout.strip().splitlines()[-1]
    best = min(seconds for _, seconds in runs)
    assert best < 1.0, f"mbavo --help took {best:.2f} s in a fresh interpreter"


def test_bad_option_is_one_line_error_without_importing_jax(tmp_path):
    for args, named in ((["track", tmp_path / "x", "--bogus"], "--out"),  # argparse names the missing --out first
                        (["track", tmp_path / "x", "--out", tmp_path / "o", "--bogus"], "--bogus"),
                        (["track", tmp_path / "x", "--out", tmp_path / "o", "--max-frames", "many"], "--max-frames"),
                        (["nonsense"], "nonsense")):
        r, _ = fresh_mbavo(*args)
        assert r.returncode == 1, (args, r.returncode, r.stderr)
        lines = r.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith("mbavo: error:") and named in lines[0], (args, r.stderr)
        assert r.stdout.strip() == "JAX MODULES: none", (args, r.stdout)
    assert not (tmp_path / "o").exists()


def test_subcommand_help_imports_no_jax():
    for command in ("track", "synth", "bench", "deblur", "eval"):
        r, _ = fresh_mbavo(command, "--help")
        assert r.returncode == 0, (command, r.stderr)
        assert r.stdout.startswith(f"usage: mbavo {command}"), (command, r.stdout[:200])
        assert r.stdout.strip().splitlines()[-1] == "JAX MODULES: none", (command, r.stdout.strip().splitlines()[-1])
