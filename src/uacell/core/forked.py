"""Run CPU-bound work on a copy-on-write image of this process, so that the event loop does not share
the interpreter with it (the pattern of a database's background save).

``run_forked(job, cancel)`` forks; the child runs ``job`` at a lower priority (nice 10) and exits, and
the parent's event loop goes on at full speed meanwhile: a thread running Python code would hold the
interpreter lock half the time and make every turn of the loop wait for it. The child sees the
parent's memory as it was at the fork (the data ``job`` closes over needs no copy and no lock) and
nothing else: it closes every inherited file descriptor but standard error (no listening socket,
client connection or database handle of the server stays open in it), restores the default signal
handlers and never runs the parent's exit handlers. What ``job`` returns or raises comes back to the
parent through a pipe (pickled; an exception that cannot be pickled comes back as a RuntimeError
with its text).

``job`` gets a ``Cancelled`` to look at between steps: it reads True once the parent set ``cancel``
(or went away). A child still running ``KILL_AFTER`` seconds after that is killed.

``forking()`` says whether this platform can (POSIX with ``os.fork``); callers fall back to a thread
where it cannot, and when the fork itself fails (``ForkFailed``).
"""

from __future__ import annotations

import asyncio
import contextlib
import gc
import os
import pickle
import select
import signal
import sys
import threading
import warnings
from collections.abc import Callable
from typing import Any, TypeVar

T = TypeVar("T")

KILL_AFTER = 5.0  # seconds a cancelled child may take to stop before it is killed
NICE = 10  # the child's priority below the server's
_POLL = 0.05  # seconds between the parent's looks at ``cancel``
_MAX_RESULT = 1 << 15  # bytes the child sends back at most: within a pipe's buffer (64 KiB on Linux), as the
# parent reads only once the child has exited


class ForkFailed(OSError):
    """The fork itself failed (no memory for the child's page tables under strict overcommit, a
    process limit): the caller may do the work another way."""


class Cancelled:
    """What the child's ``job`` asks between its steps: has the parent asked it to stop?"""

    def __init__(self, fd: int) -> None:
        self._fd = fd

    def is_set(self) -> bool:
        # the parent closes its end of the pipe to cancel (or by exiting): the read end turns readable
        readable, _, _ = select.select([self._fd], [], [], 0)
        return bool(readable)


def forking() -> bool:
    return hasattr(os, "fork") and sys.platform != "win32"


async def run_forked(job: Callable[[Cancelled], T], cancel: threading.Event) -> T:
    """``job(cancelled)`` in a forked child; its result, or its exception raised here."""
    stop_r, stop_w = os.pipe()
    result_r, result_w = os.pipe()
    try:
        with warnings.catch_warnings():  # Python 3.12 warns of fork in a threaded process; see the module doc
            warnings.simplefilter("ignore", DeprecationWarning)
            pid = os.fork()
    except BaseException as exc:
        for fd in (stop_r, stop_w, result_r, result_w):
            os.close(fd)
        if isinstance(exc, OSError):
            raise ForkFailed(exc.errno, f"cannot fork: {exc.strerror or exc}") from exc
        raise
    if pid == 0:  # pragma: no cover - the child's coverage is not collected (it never returns)
        _child(job, stop_r, result_w)
    os.close(stop_r)
    os.close(result_w)
    try:
        result: T = await _parent(pid, cancel, stop_w, result_r)
        return result
    finally:
        with contextlib.suppress(OSError):
            os.close(stop_w)
        os.close(result_r)


def _child(job: Callable[[Cancelled], Any], stop_r: int, result_w: int) -> None:  # pragma: no cover
    code = 1
    try:
        gc.disable()  # a collection would touch (and so copy) every page of the parent's heap
        with contextlib.suppress(ValueError):
            signal.set_wakeup_fd(-1)  # the parent's event loop's wake-up pipe is not the child's
        for sig in (signal.SIGTERM, signal.SIGINT, signal.SIGHUP):
            signal.signal(sig, signal.SIG_DFL)
        _close_inherited({stop_r, result_w})
        with contextlib.suppress(OSError):
            os.nice(NICE)
        try:
            payload = pickle.dumps((True, job(Cancelled(stop_r))))
        except BaseException as exc:  # sent back to the parent, raised there
            try:
                payload = pickle.dumps((False, exc))
            except Exception:
                payload = pickle.dumps((False, RuntimeError(f"{type(exc).__name__}: {exc}")))
        if len(payload) > _MAX_RESULT:
            payload = pickle.dumps((False, RuntimeError(f"the result is larger than {_MAX_RESULT} bytes")))
        view = memoryview(payload)
        while view:
            view = view[os.write(result_w, view) :]
        code = 0
    finally:
        os._exit(code)


def _close_inherited(keep: set[int]) -> None:  # pragma: no cover - runs in the child
    """Every descriptor but standard error and ``keep`` closed; standard input and output on /dev/null
    (a supervisor reading the server's output sees it end when the server's ends)."""
    devnull = os.open(os.devnull, os.O_RDWR)
    os.dup2(devnull, 0)
    os.dup2(devnull, 1)
    low = 3
    for fd in sorted(keep):
        os.closerange(low, fd)
        low = fd + 1
    os.closerange(low, os.sysconf("SC_OPEN_MAX"))


async def _parent(pid: int, cancel: threading.Event, stop_w: int, result_r: int) -> Any:
    loop = asyncio.get_running_loop()
    exited = loop.run_in_executor(None, os.waitpid, pid, 0)
    cancelled_at: float | None = None
    try:
        while not exited.done():
            if cancel.is_set() and cancelled_at is None:
                cancelled_at = loop.time()
                os.close(stop_w)  # the child's Cancelled reads True
            elif cancelled_at is not None and loop.time() - cancelled_at > KILL_AFTER:
                with contextlib.suppress(ProcessLookupError):
                    os.kill(pid, signal.SIGKILL)
            await asyncio.wait({exited}, timeout=_POLL)
    except BaseException:
        with contextlib.suppress(ProcessLookupError):
            os.kill(pid, signal.SIGKILL)  # the caller went away: so does the child
        await asyncio.shield(exited)
        raise
    _pid, status = exited.result()
    data = _read_all(result_r)
    if not data:
        raise RuntimeError(f"the forked child ended without a result ({_describe(status)})")
    ok, value = pickle.loads(data)
    if not ok:
        raise value
    return value


def _read_all(fd: int) -> bytes:
    chunks = []
    while chunk := os.read(fd, 1 << 16):
        chunks.append(chunk)
    return b"".join(chunks)


def _describe(status: int) -> str:
    if os.WIFSIGNALED(status):
        return f"killed by signal {os.WTERMSIG(status)}"
    return f"exit status {os.waitstatus_to_exitcode(status)}"
