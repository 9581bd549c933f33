"""JAX's environment variables checked before a command starts JAX's backend.

``JAX_PLATFORMS`` naming a backend this machine does not have, and ``XLA_FLAGS`` holding a flag XLA
does not know or a value it cannot read, otherwise end in JAX's traceback or in XLA's own fatal
error (a C++ abort no Python code can catch). :func:`check_jax_environment` turns each into one
line naming the variable: ``XLA_FLAGS`` (only when it is set) is tried in a short child process
first, so that an abort happens there; ``JAX_PLATFORMS`` is tried by starting the backend here (or,
for commands whose own process must leave the backend to its workers, in the child too). JAX-free
until the backend is started.
"""

from __future__ import annotations

import functools
import os
import re
import subprocess
import sys

from .errors import MbavoError

__all__ = ["check_jax_environment", "child_start", "available_backends"]

PROBE_TIMEOUT_S = 300.0  # a backend start on a busy machine (a GPU's driver) may take a while
BACKEND_FAILED = 3  # the probe's exit status when JAX raised starting the backend (not an abort)
# the probe: start the backend as a command would; a Python error is reported in one line, an
# abort by XLA leaves its own log lines on stderr
PROBE = f"""
import sys
import jax
try:
    jax.devices()
except Exception as exc:
    print(str(exc).splitlines()[0] if str(exc) else type(exc).__name__, file=sys.stderr)
    sys.exit({BACKEND_FAILED})
"""
LISTING = """
import jax
from jax._src import xla_bridge
jax.devices()
print(" ".join(sorted(xla_bridge.backends())))
"""
XLA_LOG = re.compile(r"^[EF]\d{4} [\d:.]+\s+\d+ [\w.-]+:\d+\] (.*)$")  # an XLA error or fatal log line: its message


def _backend_started() -> bool:
    """Whether this process has started JAX's backend already (XLA_FLAGS was then read without harm)."""
    if "jax" not in sys.modules:
        return False
    try:
        from jax._src import xla_bridge

        return bool(xla_bridge.backends_are_initialized())
    except (ImportError, AttributeError):  # another JAX: assume not
        return False


def _probe(script: str, env: dict[str, str]) -> subprocess.CompletedProcess | None:
    """``script`` run in a child Python with ``env``; None when it could not run or took too long."""
    try:
        return subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=PROBE_TIMEOUT_S)
    except (OSError, subprocess.TimeoutExpired):
        return None


def _xla_reason(stderr: str) -> str | None:
    """What XLA said when it stopped the process: its first error or fatal log line about a flag,
    else its first such line; None when ``stderr`` holds none (not XLA's doing)."""
    messages = [m.group(1).strip() for line in stderr.splitlines() if (m := XLA_LOG.match(line.strip()))]
    about_flags = [m for m in messages if "flag" in m.lower()]
    return (about_flags or messages)[0][:300] if messages else None


@functools.lru_cache(maxsize=8)
def child_start(flags: str, platforms: str | None) -> tuple[bool, str] | None:
    """Start JAX's backend in a child process with XLA_FLAGS ``flags`` and JAX_PLATFORMS
    ``platforms`` (None: unset): None when it starts (or cannot be tried), else (whether XLA
    stopped it (an abort: a log line of its own), what it or JAX said). A child that ended otherwise
    tells nothing about the variables (None)."""
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "JAX_PLATFORMS")}
    env.update({"XLA_FLAGS": flags, **({"JAX_PLATFORMS": platforms} if platforms is not None else {})})
    done = _probe(PROBE, env)
    if done is None or done.returncode == 0:
        return None
    if done.returncode == BACKEND_FAILED:
        return False, (done.stderr.strip().splitlines() or ["no message"])[-1]
    reason = _xla_reason(done.stderr)
    return None if reason is None else (True, reason)


@functools.lru_cache(maxsize=1)
def available_backends() -> tuple[str, ...]:
    """The backends JAX starts on this machine when JAX_PLATFORMS (and XLA_FLAGS) are not set (a
    child process); () when that cannot be told."""
    env = {k: v for k, v in os.environ.items() if k not in ("JAX_PLATFORMS", "XLA_FLAGS")}
    done = _probe(LISTING, env)
    if done is None or done.returncode != 0:
        return ()
    return tuple(done.stdout.split())


def _served(name: str, available: tuple[str, ...]) -> bool:
    """Whether the backend ``name`` (a JAX_PLATFORMS entry) is among ``available`` ('gpu': CUDA or ROCm)."""
    return name in available or (name == "gpu" and bool({"cuda", "rocm"} & set(available)))


def _platforms_error(platforms: str, reason: str) -> MbavoError:
    """The one line for a JAX_PLATFORMS whose backend did not start (JAX's ``reason``)."""
    available = available_backends()
    listed = ", ".join(available) if available else "unknown"
    missing = [n for n in (n.strip() for n in platforms.split(",")) if n and not _served(n, available)]
    if available and missing:
        return MbavoError(f"JAX_PLATFORMS={platforms}: no such backend here: {', '.join(missing)} (available: {listed}); "
                          "unset JAX_PLATFORMS or name one of those")
    return MbavoError(f"JAX_PLATFORMS={platforms}: JAX cannot start it here ({reason}; available: {listed}); unset JAX_PLATFORMS")


def _start_backend() -> str | None:
    """Start JAX's backend in this process; why it failed, or None."""
    import jax

    try:
        jax.devices()
    except Exception as exc:  # RuntimeError, or JAX's own AssertionError for a backend without its plugin
        return str(exc).splitlines()[0] if str(exc) else type(exc).__name__
    return None


def check_jax_environment(in_process: bool = True) -> None:
    """One line (MbavoError) naming the variable when ``XLA_FLAGS`` or ``JAX_PLATFORMS`` stops JAX's
    backend from starting. A set XLA_FLAGS is tried in a child process first (an abort by XLA
    happens there). ``in_process``: then the backend is started here (the command uses JAX in this
    process); else a set JAX_PLATFORMS is tried in the child too (a sweep, whose workers use the
    device). Nothing is tried once this process has started the backend."""
    if _backend_started():
        return
    flags, platforms = os.environ.get("XLA_FLAGS", ""), os.environ.get("JAX_PLATFORMS") or None
    failed = child_start(flags, platforms) if flags.strip() or (platforms and not in_process) else None
    if failed is not None and failed[0]:
        if flags.strip():
            raise MbavoError(f"XLA_FLAGS={flags!r}: XLA refuses it: {failed[1]} (fix or unset XLA_FLAGS)")
        raise MbavoError(f"JAX_PLATFORMS={platforms}: XLA stopped starting it: {failed[1]}")
    reason = _start_backend() if in_process else (failed[1] if failed is not None else None)
    if reason is None:
        return
    if platforms:
        raise _platforms_error(platforms, reason)
    raise MbavoError(f"JAX cannot start a backend{f' with XLA_FLAGS={flags!r}' if flags.strip() else ''}: {reason}")
