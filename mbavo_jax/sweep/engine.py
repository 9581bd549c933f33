"""Where a sweep's runs execute: a local process pool (spawn: JAX and fork do not mix) or Ray
tasks. Both call the same function on the same items through :func:`call_limited`, and yield
``(index, result)`` as results come in. On a Ray cluster every node needs mbavo_jax installed and
sees the sweep's folders at the same paths (a shared filesystem). Local workers end with the
sweep's process, however it ends (Ctrl-C, SIGTERM, kill -9). JAX-free.
"""

from __future__ import annotations

import collections
import os
import signal
import sys
import threading
import time
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from concurrent.futures.process import BrokenProcessPool
from typing import Any, Callable, Iterator

from ..config import SweepConfig
from ..errors import MbavoError

__all__ = ["map_unordered", "worker_env", "call_limited", "check_engine", "MAX_TRIES"]

MAX_TRIES = 2  # a run whose worker process died is tried again once, in a fresh pool
PR_SET_PDEATHSIG = 1  # linux/prctl.h: the signal a process gets when its parent dies
NO_RAY = "--engine ray needs Ray: pip install -e '.[ray]' (or pip install ray)"


def check_engine(settings: SweepConfig) -> None:
    """Refuse in one line, before any work and without connecting anywhere, an engine that cannot
    start: Ray not installed, or a Ray Client address (``ray://``) without ``ray[client]``."""
    if settings.engine != "ray":
        return
    try:
        import ray  # noqa: F401
    except ImportError:
        raise MbavoError(NO_RAY) from None
    if settings.address.startswith("ray://"):
        try:
            import grpc  # noqa: F401  # what Ray Client needs (ray[client]); Ray checks the same import
        except ImportError:
            raise MbavoError(f"--address {settings.address}: a ray:// address needs Ray Client: pip install 'ray[client]' "
                             "(or run on a node of the cluster with --address auto)") from None


def threads_per_run(settings: SweepConfig) -> int:
    """``settings.threads``, else this machine's cores shared by the local jobs (1 on Ray)."""
    if settings.threads:
        return settings.threads
    return 1 if settings.engine == "ray" else max(1, (os.cpu_count() or 1) // settings.jobs)


def worker_env(threads: int) -> dict[str, str]:
    """Environment that holds a worker to ``threads`` threads: OpenMP/BLAS pools and XLA's CPU
    intra-op pool (single-threaded Eigen when 1)."""
    flags = [f for f in os.environ.get("XLA_FLAGS", "").split() if "intra_op_parallelism" not in f and "multi_thread_eigen" not in f]
    flags.append(f"--xla_cpu_multi_thread_eigen={'false' if threads == 1 else 'true'}")
    flags.append(f"intra_op_parallelism_threads={threads}")
    return {"OMP_NUM_THREADS": str(threads), "OPENBLAS_NUM_THREADS": str(threads), "MKL_NUM_THREADS": str(threads),
            "XLA_FLAGS": " ".join(flags)}


def call_limited(fn: Callable, env: dict[str, str], item) -> Any:
    """``fn(item)`` in a worker, after ``env`` is set (before the worker's first JAX call)."""
    os.environ.update(env)
    try:
        import cv2

        cv2.setNumThreads(int(env["OMP_NUM_THREADS"]))
    except ImportError:  # pragma: no cover - cv2 is a dependency
        pass
    return fn(item)


def _watch_parent(parent: int) -> None:
    """End this process once its parent is gone (it is then adopted: another parent pid)."""
    while os.getppid() == parent:
        time.sleep(0.5)
    os._exit(1)


def _exit_with_parent(parent: int) -> None:
    """A pool worker's initializer: the worker ends when the sweep's process ``parent`` does (Linux:
    the kernel kills it, PR_SET_PDEATHSIG; everywhere: a thread watching the parent pid), and
    ignores Ctrl-C, on which the sweep's process ends its workers itself. Its (silent) progress
    bars lock with a thread lock: tqdm's default, a multiprocessing semaphore, would be reported as
    leaked when the worker is ended."""
    from tqdm import tqdm

    signal.signal(signal.SIGINT, signal.SIG_IGN)
    tqdm.set_lock(threading.RLock())
    if sys.platform.startswith("linux"):
        import ctypes

        try:
            ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
        except (OSError, AttributeError):  # pragma: no cover - a libc without prctl: the watcher remains
            pass
    if os.getppid() != parent:  # the parent died before the line above
        os._exit(1)
    threading.Thread(target=_watch_parent, args=(parent,), name="mbavo-parent-watch", daemon=True).start()


def _stop(pool: ProcessPoolExecutor) -> None:
    """End a pool's workers now (their runs are cut short, as by a kill) and cancel what waits."""
    for proc in list((getattr(pool, "_processes", None) or {}).values()):
        if proc.is_alive():
            proc.terminate()
    pool.shutdown(wait=False, cancel_futures=True)


def _alone(queue, running: dict, tries) -> bool:
    """Whether the next item, or one in flight, is a retry: retries run alone, so that a worker that
    dies again breaks no other item's pool."""
    return tries[queue[0][0]] > 0 or any(tries[i] > 0 for i, _ in running.values())


def _local(fn, items: list, jobs: int, env: dict, fallback) -> Iterator[tuple[int, Any]]:
    """At most ``jobs`` items in flight on a spawn process pool; a pool broken by a dying worker
    is replaced and its in-flight items queued again (at the end), up to MAX_TRIES each, each retry
    alone in the pool. Interrupted (Ctrl-C, SIGTERM as KeyboardInterrupt) or closed, it ends its
    workers before it returns; they also end when this process is killed."""
    import multiprocessing

    queue, tries = collections.deque(enumerate(items)), collections.Counter()
    while queue:
        with ProcessPoolExecutor(jobs, mp_context=multiprocessing.get_context("spawn"), initializer=_exit_with_parent,
                                 initargs=(os.getpid(),)) as pool:
            try:
                yield from _pool_round(pool, fn, queue, tries, jobs, env, fallback)
            except BaseException:  # interrupted, or the caller stopped listening
                _stop(pool)
                raise


def _pool_round(pool, fn, queue, tries, jobs: int, env: dict, fallback) -> Iterator[tuple[int, Any]]:
    """Items from ``queue`` on ``pool`` until it is empty or the pool breaks (then the items in
    flight go back to the queue, or to ``fallback`` after MAX_TRIES)."""
    running, broken = {}, False
    while running or (queue and not broken):
        while queue and not broken and len(running) < jobs and not (running and _alone(queue, running, tries)):
            i, item = queue.popleft()
            running[pool.submit(call_limited, fn, env, item)] = (i, item)
        done, _ = wait(running, return_when=FIRST_COMPLETED)
        for fut in done:
            i, item = running.pop(fut)
            try:
                yield i, fut.result()
            except BrokenProcessPool as exc:
                broken, tries[i] = True, tries[i] + 1
                if tries[i] < MAX_TRIES:
                    queue.append((i, item))
                else:
                    yield i, fallback(item, exc)
            except Exception as exc:  # e.g. an item that cannot be pickled
                yield i, fallback(item, exc)


def _ray_session(settings: SweepConfig):
    """Ray, connected: the caller's session when one is up, else ``settings.address`` or a local
    one with CPUs for ``settings.jobs`` runs at once; whether this call started it (and must shut it down)."""
    check_engine(settings)
    import ray

    if ray.is_initialized():
        return ray, False
    if settings.address:
        try:
            ray.init(address=settings.address)
        except ConnectionError as exc:
            raise MbavoError(f"--address {settings.address}: cannot connect to the Ray cluster ({str(exc).splitlines()[0]})") from None
    else:
        ray.init(num_cpus=settings.jobs * threads_per_run(settings), include_dashboard=False)
    return ray, True


def _ray(fn, items: list, settings: SweepConfig, env: dict, fallback) -> Iterator[tuple[int, Any]]:
    """Every item as a Ray task of ``threads`` CPUs; results in the order they finish."""
    ray, started = _ray_session(settings)
    try:
        remote = ray.remote(call_limited).options(num_cpus=threads_per_run(settings), max_retries=MAX_TRIES - 1)
        refs = {remote.remote(fn, env, item): i for i, item in enumerate(items)}
        pending = list(refs)
        while pending:
            done, pending = ray.wait(pending, num_returns=1)
            i = refs[done[0]]
            try:
                yield i, ray.get(done[0])
            except Exception as exc:  # the worker died, or the task could not run
                yield i, fallback(items[i], exc)
    finally:
        if started:
            ray.shutdown()


def map_unordered(fn: Callable, items: list, settings: SweepConfig, fallback: Callable) -> Iterator[tuple[int, Any]]:
    """``(index, fn(item))`` for every item, as they finish, on ``settings.engine``; an item whose
    call raised outside ``fn`` (its worker died, Ray failed) gives ``(index, fallback(item, exc))``.
    ``fn`` and the items must be importable/picklable (module-level function, dataclasses). A
    generator: closing it (``contextlib.closing``) ends the local workers at once."""
    if not items:
        return (x for x in ())
    env = worker_env(threads_per_run(settings))
    if settings.engine == "ray":
        return _ray(fn, items, settings, env, fallback)
    return _local(fn, items, settings.jobs, env, fallback)
