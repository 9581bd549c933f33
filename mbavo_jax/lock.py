"""One writer per run folder: an exclusive lock on the folder itself for a run's life.

The lock is the operating system's (``flock`` on the folder), so it ends with the process however
the process ends (return, exception, Ctrl-C, SIGTERM, kill -9), and taking it writes nothing: a run
refused by its checks leaves the folder as it was. Once the run goes ahead it writes its pid to
``<out>/.mbavo.pid`` (removed when it gives the folder back), for the message a second writer gets;
a file left by a killed process names a pid that is gone and blocks nothing.
"""

from __future__ import annotations

import os
import pathlib

from .errors import MbavoError

__all__ = ["PID_FILE", "RunLock"]

PID_FILE = ".mbavo.pid"  # in a run folder while a run writes it; clear_run and reconcile never touch it

try:
    import fcntl
except ImportError:  # pragma: no cover - not POSIX (Windows): filelock's lock file beside the pid
    fcntl = None


class RunLock:
    """An exclusive lock on the run folder ``out`` (which must exist), held from construction to
    :meth:`release` (or the end of a ``with`` block); refused in one line while another process
    holds it. :meth:`sign` writes this process's pid into the folder."""

    def __init__(self, out):
        self.out = pathlib.Path(out)
        self._held, self._signed = _acquire(self.out), False

    def sign(self) -> None:
        """Write this process's pid to ``<out>/.mbavo.pid`` (once the run is going to write anyway)."""
        path = self.out / PID_FILE
        tmp = path.with_name(f"{PID_FILE}.{os.getpid()}.tmp")
        tmp.write_text(f"{os.getpid()}\n")
        os.replace(tmp, path)
        self._signed = True

    def release(self) -> None:
        """Give the folder back (idempotent): the pid file removed, the lock ended."""
        held, self._held = getattr(self, "_held", None), None
        if held is None:
            return
        try:
            if self._signed:
                (self.out / PID_FILE).unlink(missing_ok=True)
        finally:
            _unlock(held)

    def __enter__(self) -> "RunLock":
        return self

    def __exit__(self, *exc) -> None:
        self.release()

    def __del__(self):  # dropped unreleased (e.g. an exception before its ``with``): give the folder back
        try:
            self.release()
        except (OSError, TypeError, AttributeError):  # pragma: no cover - interpreter shutdown
            pass


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process
        return True
    return True


def holder(out: pathlib.Path) -> str:
    """The pid in ``out``'s pid file when that process is alive, else 'unknown' (the holder has not
    written it yet)."""
    try:
        text = (out / PID_FILE).read_text(encoding="ascii").strip()
    except (OSError, UnicodeDecodeError):
        return "unknown"
    return text if text.isdigit() and _alive(int(text)) else "unknown"


def _busy(out: pathlib.Path) -> MbavoError:
    return MbavoError(f"{out}: another mbavo process (pid {holder(out)}) is writing to this run folder; wait for it to "
                      "end, or choose another --out")


def _acquire(out: pathlib.Path):
    """The folder ``out`` locked: its open descriptor (filelock's lock where there is no flock)."""
    if fcntl is None:  # pragma: no cover
        import filelock

        lock = filelock.FileLock(str(out / ".mbavo.lock"), timeout=0)
        try:
            lock.acquire()
        except filelock.Timeout:
            raise _busy(out) from None
        return lock
    try:
        fd = os.open(out, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError as exc:
        raise MbavoError(f"{out}: cannot lock the run folder ({exc.strerror})") from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        os.close(fd)
        raise _busy(out) from None
    except BaseException:
        os.close(fd)
        raise
    return fd


def _unlock(handle) -> None:
    if fcntl is None:  # pragma: no cover
        handle.release()
        return
    try:
        fcntl.flock(handle, fcntl.LOCK_UN)
    finally:
        os.close(handle)
