"""How a process runs JAX: the persistent compilation cache and a count of what was compiled.

With the cache on (``runtime.compilation_cache``, the default), every program XLA compiles is kept in
a user cache folder, so a second run with the same settings and image size loads its programs
instead of compiling them. The folder has a subfolder per jaxlib version and processor, and the
cache has a size limit: with one, JAX locks the folder around every read and write, so that
processes sharing it (a sweep's workers, a test suite's) never load a half-written program.
:func:`compile_counts` tells how many programs came from the cache and how many were compiled since
the process started. :func:`make_room_for_programs` releases the programs a process holds before a
run when their memory maps near the system's limit (a benchmark of many settings and image sizes);
:func:`release_free_memory` hands freed heap memory back to the system after each frame.
"""

from __future__ import annotations

import ctypes
import functools
import gc
import hashlib
import os
import pathlib
import platform
import resource
import sys

import jax
import jaxlib
from jax import monitoring
from jax.experimental.compilation_cache import compilation_cache

from .config import RuntimeConfig

__all__ = ["cache_folder", "machine_key", "enable_compilation_cache", "compile_counts", "resident_mb", "release_free_memory", "memory_maps",
           "make_room_for_programs"]

_COUNTS = {"programs": 0, "cache_hits": 0, "compile_seconds": 0.0}


def _on_event(event: str, **_) -> None:
    if event == "/jax/compilation_cache/cache_hits":
        _COUNTS["cache_hits"] += 1


def _on_duration(event: str, seconds: float, **_) -> None:
    if event == "/jax/core/compile/backend_compile_duration":  # one per program: compiled or loaded from the cache
        _COUNTS["programs"] += 1
        _COUNTS["compile_seconds"] += seconds


monitoring.register_event_listener(_on_event)
monitoring.register_event_duration_secs_listener(_on_duration)


def machine_key() -> str:
    """The cache's subfolder for this process: jaxlib's version, the machine type and a short hash of
    the processor's model and instruction-set flags (``/proc/cpuinfo``), so that a cache folder shared
    by machines (a home folder on a cluster) never hands one machine's programs to another."""
    try:
        lines = pathlib.Path("/proc/cpuinfo").read_text().splitlines()
    except OSError:
        lines = []
    ident = sorted({ln for ln in lines if ln.startswith(("model name", "flags", "Features", "CPU part"))})
    ident.append(platform.processor())
    digest = hashlib.sha256("\n".join(ident).encode()).hexdigest()[:12]
    return f"jaxlib-{jaxlib.__version__}-{platform.machine()}-{digest}"


def cache_folder(config: RuntimeConfig = RuntimeConfig()) -> pathlib.Path:
    """The compilation cache's folder: :func:`machine_key` inside ``runtime.cache_dir``, else inside
    ``$XDG_CACHE_HOME/mbavo_jax/jax`` (``~/.cache/mbavo_jax/jax`` when XDG_CACHE_HOME is not set)."""
    if config.cache_dir:
        root = pathlib.Path(config.cache_dir).expanduser()
    else:
        root = pathlib.Path(os.environ.get("XDG_CACHE_HOME") or pathlib.Path.home() / ".cache") / "mbavo_jax" / "jax"
    return root / machine_key()


def enable_compilation_cache(config: RuntimeConfig = RuntimeConfig()) -> pathlib.Path | None:
    """Turn JAX's persistent compilation cache on in ``cache_folder(config)`` (every program, however
    quick to compile; at most ``runtime.cache_max_mb``, with JAX's file lock) or off, for the rest of
    this process; returns the folder, None when off or when the folder cannot be made (then one note
    on stderr and the run goes on without it)."""
    if not config.compilation_cache:
        _set_cache(None, -1)
        return None
    folder = cache_folder(config)
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        print(f"mbavo: note: no compilation cache ({folder}: {exc.strerror or exc}); compiling as usual", file=sys.stderr)
        _set_cache(None, -1)
        return None
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    _set_cache(str(folder), config.cache_max_mb * 2**20)
    return folder


def _set_cache(path: str | None, max_bytes: int) -> None:
    """Point the cache at ``path`` (None: off) with a size limit in bytes (JAX locks the folder only
    when a limit is set, i.e. not -1); JAX decides once per process whether the cache is used, so a
    change resets that decision."""
    now = (jax.config.jax_compilation_cache_dir, jax.config.jax_enable_compilation_cache, jax.config.jax_compilation_cache_max_size)
    if now == (path, path is not None, max_bytes):
        return
    jax.config.update("jax_enable_compilation_cache", path is not None)
    jax.config.update("jax_compilation_cache_dir", path)
    jax.config.update("jax_compilation_cache_max_size", max_bytes)
    compilation_cache.reset_cache()


def compile_counts() -> dict:
    """What this process has compiled so far: ``programs`` (XLA executables it needed),
    ``cache_hits`` (of those, loaded from the compilation cache), ``compiled`` (the rest) and
    ``compile_seconds`` (time spent compiling or loading them)."""
    return {**_COUNTS, "compiled": _COUNTS["programs"] - _COUNTS["cache_hits"]}


def resident_mb() -> float:
    """The process's resident memory now, in MiB (Linux ``/proc/self/statm``; elsewhere its peak)."""
    try:
        pages = int(pathlib.Path("/proc/self/statm").read_text().split()[1])
        return pages * os.sysconf("SC_PAGE_SIZE") / 2**20
    except (OSError, ValueError, IndexError):
        peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss  # KiB on Linux, bytes on macOS
        return peak / (2**20 if sys.platform == "darwin" else 2**10)


def release_free_memory() -> bool:
    """Hand the heap memory that is free back to the system (glibc's ``malloc_trim(0)``); returns
    whether it could (False where the C library is not glibc). glibc keeps freed blocks below its
    mmap threshold for reuse, so a process's resident memory otherwise stays at its largest."""
    trim = _malloc_trim()
    return bool(trim is not None and trim(0) >= 0)


@functools.lru_cache(maxsize=1)
def _malloc_trim():
    try:
        return ctypes.CDLL(None).malloc_trim if sys.platform.startswith("linux") else None
    except (OSError, AttributeError):  # not glibc (musl has no malloc_trim)
        return None


def memory_maps() -> tuple[int, int] | None:
    """(memory maps this process holds, the most the system allows it: ``vm.max_map_count``) from
    Linux's /proc; None elsewhere."""
    try:
        with open("/proc/self/maps", "rb") as fh:
            held = sum(1 for _ in fh)
        return held, int(pathlib.Path("/proc/sys/vm/max_map_count").read_text())
    except (OSError, ValueError):
        return None


def make_room_for_programs(config: RuntimeConfig = RuntimeConfig()) -> str:
    """Release every compiled program this process holds (``jax.clear_caches``) when its memory maps
    are past ``runtime.release_programs_at`` of the system's limit; returns a one-line note saying so
    ('' when nothing was released). XLA maps each program's code apart (a monocular run at one image
    size holds about 10,000 maps), and a process past the limit dies in LLVM ("Cannot allocate
    memory"). Released programs come back from the compilation cache when used again."""
    maps = memory_maps()
    if maps is None or maps[0] <= config.release_programs_at * maps[1]:
        return ""
    jax.clear_caches()
    gc.collect()  # the executables are freed, and their maps unmapped, with their last reference
    after = memory_maps() or (0, maps[1])
    return (f"released the compiled programs of earlier runs ({maps[0]} of the system's {maps[1]} memory maps held, "
            f"{after[0]} now); they load from the compilation cache, or compile again, when needed")
