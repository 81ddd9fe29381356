"""``uacell.core.forked.run_forked``: work on a forked copy of the process, its result or exception back
in the parent, a cancellation seen or enforced, nothing of the parent's left open in the child."""

from __future__ import annotations

import asyncio
import errno
import os
import socket
import threading
import time
from pathlib import Path

import pytest
from helpers import wait_until

from uacell.core import forked
from uacell.core.forked import Cancelled, ForkFailed, run_forked
from uacell.ua.snapshot import WriteCancelled

pytestmark = pytest.mark.skipif(not forked.forking(), reason="the platform has no fork")


async def test_the_child_sees_the_parents_data_and_its_result_comes_back() -> None:
    table = {f"node{i}": i for i in range(1000)}  # made before the fork: the child reads it, not a copy sent
    parent = os.getpid()

    def job(cancelled: Cancelled) -> tuple[int, int, bool]:
        return sum(table.values()), os.getpid(), cancelled.is_set()

    total, child, cancelled = await run_forked(job, threading.Event())
    assert total == sum(range(1000))
    assert child != parent and not cancelled


async def test_the_childs_exception_is_raised_in_the_parent() -> None:
    def job(cancelled: Cancelled) -> None:
        raise ValueError("no room on the disk")

    with pytest.raises(ValueError, match="no room on the disk"):
        await run_forked(job, threading.Event())


async def test_an_exception_that_cannot_be_pickled_comes_back_as_its_text() -> None:
    class Local(Exception):  # a local class: pickle cannot find it by name
        pass

    def job(cancelled: Cancelled) -> None:
        raise Local("odd")

    with pytest.raises(RuntimeError, match="Local: odd"):
        await run_forked(job, threading.Event())


async def test_a_cancellation_reaches_the_child(tmp_path: Path) -> None:
    cancel = threading.Event()
    running = tmp_path / "running"

    def job(cancelled: Cancelled) -> None:
        running.touch()
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            if cancelled.is_set():
                raise WriteCancelled
            time.sleep(0.01)

    task = asyncio.create_task(run_forked(job, cancel))
    await wait_until(running.exists, timeout=10, step=0.01)
    assert not task.done()
    cancel.set()
    with pytest.raises(WriteCancelled):
        await asyncio.wait_for(task, 10)


async def test_a_child_that_ignores_the_cancellation_is_killed(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(forked, "KILL_AFTER", 0.2)
    cancel = threading.Event()
    cancel.set()

    def job(cancelled: Cancelled) -> None:
        time.sleep(60)

    started = time.monotonic()
    with pytest.raises(RuntimeError, match="killed by signal 9"):
        await asyncio.wait_for(run_forked(job, cancel), 10)
    assert time.monotonic() - started < 10


async def test_the_child_holds_none_of_the_parents_descriptors() -> None:
    listener = socket.socket()
    listener.bind(("127.0.0.1", 0))
    listener.listen()
    fd = listener.fileno()
    try:

        def job(cancelled: Cancelled) -> list[int]:
            return sorted(int(fd) for fd in os.listdir("/proc/self/fd"))

        held = await run_forked(job, threading.Event())
    finally:
        listener.close()
    assert fd not in held
    assert held[:3] == [0, 1, 2]
    # beside the standard three: the two pipe ends it talks to the parent through, and the listing's own
    assert len(held) == 6, held


async def test_a_cancelled_caller_kills_the_child(tmp_path: Path) -> None:
    running = tmp_path / "running"

    def job(cancelled: Cancelled) -> None:
        running.write_text(str(os.getpid()))
        time.sleep(60)

    task = asyncio.create_task(run_forked(job, threading.Event()))
    await wait_until(lambda: running.exists() and running.read_text() != "", timeout=10, step=0.01)
    child = int(running.read_text())
    task.cancel()
    with pytest.raises(asyncio.CancelledError):
        await asyncio.wait_for(task, 10)
    with pytest.raises(ProcessLookupError):  # killed and reaped: no such process any more
        os.kill(child, 0)


async def test_a_fork_that_fails_says_so_and_leaves_no_pipe_open(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_memory() -> int:
        raise OSError(errno.ENOMEM, "Cannot allocate memory")

    before = set(os.listdir("/proc/self/fd"))
    monkeypatch.setattr(os, "fork", no_memory)
    with pytest.raises(ForkFailed) as failed:
        await run_forked(lambda cancelled: None, threading.Event())
    assert failed.value.errno == errno.ENOMEM and "cannot fork" in str(failed.value)
    assert set(os.listdir("/proc/self/fd")) == before
