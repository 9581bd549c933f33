"""Shared fixtures. Tests run float32 by default (the library default); tests that need float64 use
the ``x64`` fixture, which switches it on for that test only.

The test session is strict about types (set before anything imports ``mbavo_jax``):

* ``jax_numpy_dtype_promotion="strict"``: mixing array dtypes (float32 with float64, int with
  float) raises instead of silently promoting. Exported as ``JAX_NUMPY_DTYPE_PROMOTION`` so that
  ``mbavo`` subprocesses run the same way; ``JAX_NUMPY_DTYPE_PROMOTION=standard pytest`` relaxes it.
* jaxtyping's import hook with beartype: every annotated function and dataclass of ``mbavo_jax``
  checks its arguments and return values (shapes and dtypes of ``Float[Array, "h w"]`` annotations
  too) at call time; ints pass as floats (PEP 484). ``MBAVO_TYPECHECK=0`` switches the hook off (e.g. to tell a type mismatch from
  a real failure).

The suite's compilation cache is a fresh folder of its own for each run (``MBAVO_TEST_CACHE=user``
keeps ``~/.cache``).

``mbavo`` runs in-process (``mbavo_jax.cli.main``) through the ``mbavo`` fixture; only tests that
need a fresh interpreter (import-time checks, killing a run) start a subprocess.
"""

from __future__ import annotations

import dataclasses
import os
import pathlib
import sys

TYPECHECK = os.environ.get("MBAVO_TYPECHECK", "1") != "0"

if "mbavo_jax" in sys.modules:  # pragma: no cover - a plugin or sitecustomize imported it first
    raise RuntimeError("mbavo_jax was imported before tests/conftest.py: the jaxtyping import hook would not apply")
# beartype.beartype, except that an int is accepted where a float is annotated (PEP 484's numeric
# tower, as static type checkers read ``x: float``). jaxtyping evaluates this string as the decorator.
TYPECHECKER = "beartype.beartype(conf=beartype.BeartypeConf(is_pep484_tower=True))"
if TYPECHECK:
    import jaxtyping

    jaxtyping.install_import_hook("mbavo_jax", TYPECHECKER)

os.environ.setdefault("JAX_NUMPY_DTYPE_PROMOTION", "strict")  # inherited by mbavo subprocesses

# A compilation cache of this run's own (the first process, pytest's controller, makes the folder;
# xdist workers and mbavo subprocesses inherit it): the suite never loads programs that earlier runs or
# other tools left in the user's cache folder. MBAVO_TEST_CACHE=user keeps the user's folder.
if os.environ.get("MBAVO_TEST_CACHE") != "user" and "MBAVO_TEST_XDG_CACHE" not in os.environ:
    import atexit
    import shutil
    import tempfile

    os.environ["MBAVO_TEST_XDG_CACHE"] = tempfile.mkdtemp(prefix="mbavo-test-cache-")
    atexit.register(shutil.rmtree, os.environ["MBAVO_TEST_XDG_CACHE"], True)
if "MBAVO_TEST_XDG_CACHE" in os.environ:
    os.environ["XDG_CACHE_HOME"] = os.environ["MBAVO_TEST_XDG_CACHE"]

import cv2  # noqa: E402
import jax  # noqa: E402
import numpy as np  # noqa: E402
import pytest  # noqa: E402

jax.config.update("jax_numpy_dtype_promotion", os.environ["JAX_NUMPY_DTYPE_PROMOTION"])

REPO = pathlib.Path(__file__).resolve().parents[1]
SHARED_DATA = pathlib.Path(os.environ.get("MBAVO_SHARED_DATA", REPO.parent / "shared" / "data"))


@pytest.fixture
def x64():
    with jax.enable_x64(True):
        yield


@pytest.fixture
def rng():
    return np.random.default_rng(0)


def shared_dataset(name: str) -> pathlib.Path:
    """Path of a real clip in ../shared/data. Fails loudly (never skips) when it is missing."""
    path = SHARED_DATA / name
    if not path.is_dir():
        pytest.fail(f"shared test data missing: {path} (set MBAVO_SHARED_DATA or provide ../shared/data)")
    return path


# ------------------------------------------------------------------------ a hand-made TUM layout

W, H = 32, 24


def depth_of(k: int) -> float:
    """Depth (m) of every pixel of hand-made depth image k: each image is told apart by its value."""
    return 1.0 + 0.25 * k


def write_depth(path: pathlib.Path, metres: float) -> None:
    cv2.imwrite(str(path), np.full((H, W), round(metres * 5000), np.uint16))  # TUM scale: 5000 per metre


def make_tum(root: pathlib.Path, n=4, depth=True) -> pathlib.Path:
    """A TUM layout of n random frames; depth image k (stamped 2 ms after rgb frame k) holds depth_of(k)."""
    rng = np.random.default_rng(0)
    (root / "rgb").mkdir(parents=True)
    (root / "depth").mkdir()
    stamps = 10.0 + np.arange(n) / 30
    with open(root / "rgb.txt", "w") as f, open(root / "depth.txt", "w") as g:
        for k, t in enumerate(stamps):
            cv2.imwrite(str(root / "rgb" / f"{t:.6f}.png"), rng.integers(0, 255, (H, W, 3), dtype=np.uint8))
            write_depth(root / "depth" / f"{t:.6f}.png", depth_of(k))
            f.write(f"{t:.6f} rgb/{t:.6f}.png\n")
            g.write(f"{t + 0.002:.6f} depth/{t:.6f}.png\n")
    if not depth:
        (root / "depth.txt").unlink()
    (root / "camera.yaml").write_text(f"fx: 30\nfy: 30\ncx: 15.5\ncy: 11.5\nwidth: {W}\nheight: {H}\n")
    with open(root / "groundtruth.txt", "w") as f:
        for t in stamps:
            f.write(f"{t:.6f} 0 0 {t - 10:.4f} 0 0 0 1\n")
    return root


# ------------------------------------------------------------------------------ the command line


@dataclasses.dataclass(frozen=True)
class CliResult:
    """What ``mbavo ARGS`` did: exit status, standard output, standard error."""

    returncode: int
    stdout: str
    stderr: str


def run_cli(*args) -> int:
    """``mbavo ARGS`` in this interpreter, output not captured (for module-scoped fixtures); the exit status."""
    from mbavo_jax.cli import main

    try:
        return main([str(a) for a in args])
    except SystemExit as exc:  # argparse's --help and usage errors exit instead of returning
        return exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)


@pytest.fixture
def mbavo(capsys):
    """``mbavo(*args) -> CliResult``: the command line in-process, its stdout and stderr captured."""

    def run(*args) -> CliResult:
        capsys.readouterr()  # drop whatever the test printed before
        rc = run_cli(*args)
        out = capsys.readouterr()
        return CliResult(rc, out.out, out.err)

    return run


# ``python -c BLOCK_AT_FRAME NAME FLAG AFTER ARGS...``: ``mbavo ARGS`` in a fresh interpreter whose
# image reader, asked for rgb/NAME (any rgb image: ``*``) once the file AFTER exists (``-``: at once),
# touches FLAG and then blocks forever; so a run always stops inside the sequence, after every frame
# before NAME is finished, however fast the machine is.
BLOCK_AT_FRAME = """
import pathlib, sys, time
import cv2
name, flag, after = sys.argv[1], pathlib.Path(sys.argv[2]), sys.argv[3]
real_imread = cv2.imread

def imread(path, *args, **kwargs):
    p = pathlib.Path(str(path))
    if p.parent.name == "rgb" and name in ("*", p.name) and (after == "-" or pathlib.Path(after).exists()):
        flag.touch()
        while True:
            time.sleep(1)
    return real_imread(path, *args, **kwargs)

cv2.imread = imread
from mbavo_jax.cli import main
sys.exit(main(sys.argv[4:]))
"""
