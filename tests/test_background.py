"""``Background.close`` (pure asyncio): a clean-up finishes, a lost cancellation is repeated, and a task
that never ends does not hold the close up for ever."""

from __future__ import annotations

import asyncio
import logging

import pytest

from uacell.core.background import Background

GRACE = 0.2


async def test_a_task_finishes_its_clean_up_before_close_returns(caplog: pytest.LogCaptureFixture) -> None:
    bg = Background()
    cleaned = asyncio.Event()
    entered = asyncio.Event()

    async def pulse() -> None:
        try:
            entered.set()
            await asyncio.Event().wait()
        finally:
            await asyncio.sleep(0.02)  # the pulse written back low: awaited, not interrupted
            cleaned.set()

    bg.spawn(pulse(), name="pulse")
    await entered.wait()
    with caplog.at_level(logging.WARNING, logger="uacell.core.background"):
        await bg.close(grace=5.0)
    assert cleaned.is_set()
    assert not bg.tasks
    assert not caplog.records


async def test_a_lost_cancellation_is_repeated(caplog: pytest.LogCaptureFixture) -> None:
    bg = Background()
    entered = asyncio.Event()
    cancellations = 0

    async def swallows_one() -> None:
        nonlocal cancellations
        entered.set()
        while True:
            try:
                await asyncio.Event().wait()
            except asyncio.CancelledError:
                cancellations += 1
                if cancellations == 2:
                    raise
                # the first one lost, as Python 3.11's wait_for can lose it: carry on waiting

    task = bg.spawn(swallows_one(), name="swallows-one")
    await entered.wait()
    with caplog.at_level(logging.WARNING, logger="uacell.core.background"):
        await asyncio.wait_for(bg.close(grace=GRACE), 10 * GRACE)
    assert task.cancelled() and cancellations == 2
    assert [r.levelname for r in caplog.records] == ["WARNING"]
    assert "swallows-one" in caplog.records[0].getMessage()


async def test_a_task_that_never_ends_is_named_and_left(caplog: pytest.LogCaptureFixture) -> None:
    bg = Background()
    entered = asyncio.Event()
    release = asyncio.Event()

    async def stubborn() -> None:
        entered.set()
        while not release.is_set():
            try:
                await release.wait()
            except asyncio.CancelledError:
                continue

    task = bg.spawn(stubborn(), name="stubborn")
    await entered.wait()
    try:
        with caplog.at_level(logging.WARNING, logger="uacell.core.background"):
            await asyncio.wait_for(bg.close(grace=GRACE), 10 * GRACE)
        assert not task.done()
        assert [r.levelname for r in caplog.records] == ["WARNING", "ERROR"]
        assert "stubborn" in caplog.records[1].getMessage() and "left running" in caplog.records[1].getMessage()
    finally:
        release.set()
        await asyncio.wait_for(task, 5.0)


async def test_a_task_that_had_failed_is_reported(caplog: pytest.LogCaptureFixture) -> None:
    bg = Background()
    entered = asyncio.Event()

    async def fails_on_cancel() -> None:
        try:
            entered.set()
            await asyncio.Event().wait()
        except asyncio.CancelledError:
            raise RuntimeError("broken clean-up") from None

    bg.spawn(fails_on_cancel(), name="fails")
    await entered.wait()
    with caplog.at_level(logging.ERROR, logger="uacell.core.background"):
        await bg.close(grace=GRACE)
    assert [r.getMessage() for r in caplog.records] == ["a background task had failed: RuntimeError('broken clean-up')"]
