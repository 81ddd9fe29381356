"""Running work at once, with a task only from its first wait on (uacell.core.background.eager), and the
address-space publisher that uses it (uacell.binding.publisher.Publisher). Pure asyncio."""

from __future__ import annotations

import asyncio
import contextvars
from collections.abc import Awaitable, Callable

import pytest

from uacell.binding.publisher import Publisher
from uacell.core.background import eager

WHO: contextvars.ContextVar[str] = contextvars.ContextVar("who", default="nobody")


async def test_work_that_never_waits_finishes_at_once_in_its_own_context() -> None:
    seen: list[str] = []

    async def work() -> None:
        WHO.set("worker")
        seen.append(WHO.get())

    WHO.set("caller")
    assert eager(work(), contextvars.copy_context()) is None
    assert seen == ["worker"] and WHO.get() == "caller"  # done before eager returned, caller's context kept


async def test_work_that_waits_goes_on_in_a_task_with_results_and_cancellation() -> None:
    gate: asyncio.Future[int] = asyncio.get_running_loop().create_future()
    seen: list[object] = []

    async def work() -> str:
        WHO.set("worker")
        seen.append(await gate)
        await asyncio.sleep(0)  # a bare yield, then more
        seen.append(WHO.get())
        return "done"

    task = eager(work(), contextvars.copy_context())
    assert task is not None and not task.done() and seen == []
    gate.set_result(7)
    assert await asyncio.wait_for(task, 5) == "done"
    assert seen == [7, "worker"] and WHO.get() == "nobody"

    cancelled: list[bool] = []

    async def waits_forever() -> None:
        try:
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            cancelled.append(True)
            raise

    forever = eager(waits_forever(), contextvars.copy_context())
    assert forever is not None
    await asyncio.sleep(0)
    forever.cancel()
    with pytest.raises(asyncio.CancelledError):
        await forever
    assert cancelled == [True]


async def test_an_error_before_the_first_wait_is_raised_by_eager_after_it_by_the_task() -> None:
    async def fails_at_once() -> None:
        raise ValueError("at once")

    with pytest.raises(ValueError, match="at once"):
        eager(fails_at_once(), contextvars.copy_context())

    async def fails_later() -> None:
        await asyncio.sleep(0)
        raise ValueError("later")

    task = eager(fails_later(), contextvars.copy_context())
    assert task is not None
    with pytest.raises(ValueError, match="later"):
        await task


async def test_publisher_runs_jobs_in_order_in_a_fresh_context_and_flush_runs_them_now() -> None:
    publisher = Publisher()
    done: list[tuple[str, str]] = []
    idle: list[int] = []

    def job(name: str) -> Callable[[], Awaitable[None]]:
        async def run() -> None:
            done.append((name, WHO.get()))

        return run

    async def hook() -> None:
        idle.append(len(done))

    publisher.idle_hooks.append(hook)
    WHO.set("a caller")
    publisher.submit(job("one"))
    publisher.submit(job("two"))
    assert done == []  # due, not run: a submit only schedules
    await publisher.flush()  # runs them here, now, without waiting for the loop
    assert done == [("one", "nobody"), ("two", "nobody")] and idle == [2]


async def test_publisher_flush_waits_for_a_job_that_waits_and_takes_jobs_submitted_meanwhile() -> None:
    publisher = Publisher()
    gate = asyncio.Event()
    done: list[str] = []

    async def slow() -> None:
        await gate.wait()
        done.append("slow")
        publisher.submit(fast)  # submitted by a job: taken by the same drain

    async def fast() -> None:
        done.append("fast")

    publisher.submit(slow)
    await asyncio.sleep(0)  # the drain starts on its own and waits in the first job
    assert done == []
    flushing = asyncio.ensure_future(publisher.flush())
    await asyncio.sleep(0)
    assert not flushing.done()
    gate.set()
    await asyncio.wait_for(flushing, 5)
    assert done == ["slow", "fast"]


async def test_before_its_first_wait_a_coroutine_is_in_a_task_that_timeout_and_cancel_use() -> None:
    seen: list[object] = []
    gate: asyncio.Future[None] = asyncio.get_running_loop().create_future()

    async def quick() -> None:
        async with asyncio.timeout(5):  # no wait inside: the step's task is entered and left
            seen.append(asyncio.current_task() is not None)

    async def times_out() -> None:
        try:
            async with asyncio.timeout(0.01):  # entered before the first wait, expires after it
                await gate
        except TimeoutError:
            seen.append("timed out")
        seen.append(asyncio.current_task().cancelling())  # type: ignore[union-attr]

    assert eager(quick(), contextvars.copy_context()) is None
    assert seen == [True]
    task = eager(times_out(), contextvars.copy_context())
    assert task is not None
    await asyncio.wait_for(task, 10)
    assert seen == [True, "timed out", 0]


async def test_a_cancellation_asked_for_before_the_first_wait_reaches_the_coroutine_there() -> None:
    seen: list[str] = []

    async def work() -> None:
        asyncio.current_task().cancel()  # type: ignore[union-attr]
        try:
            await asyncio.sleep(10)
        except asyncio.CancelledError:
            seen.append("cancelled at its first wait")
            raise

    task = eager(work(), contextvars.copy_context())
    assert task is not None
    with pytest.raises(asyncio.CancelledError):
        await asyncio.wait_for(task, 10)
    assert seen == ["cancelled at its first wait"] and task.cancelled()


async def test_eager_from_inside_a_task_sets_that_task_aside_for_the_step() -> None:
    outer = asyncio.current_task()
    inside: list[object] = []

    async def work() -> None:
        inside.append(asyncio.current_task())
        async with asyncio.timeout(5):
            inside.append("timed")

    assert eager(work(), contextvars.copy_context()) is None
    assert inside[0] is not outer and inside[0] is not None and inside[1] == "timed"
    assert asyncio.current_task() is outer  # the caller's task is current again


async def test_the_running_task_table_eager_uses_is_the_one_current_task_reads() -> None:
    from uacell.core.background import _CURRENT

    assert _CURRENT.get(asyncio.get_running_loop()) is asyncio.current_task()
