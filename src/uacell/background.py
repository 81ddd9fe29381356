"""Background coroutines owned by one object, cancelled and awaited together: the one way uacell runs
them (models, bindings and the server alike). Pure asyncio.

Each task runs in a fresh ``contextvars.Context``: a task spawned while a client's request runs (a
program run started by a method call, a robot powering up) does not inherit that request's context,
so what it does later is never taken for the caller's (``uacell.ua.context.current_call``), unless
the spawner passes ``context``: a task that completes what a call asked for (drives powering down
after StandDown) runs in a copy of the call's context and so is the caller's (decision 38)."""

from __future__ import annotations

import asyncio
import contextvars
import logging
import types
from collections.abc import Coroutine, Generator
from typing import Any, TypeVar

T = TypeVar("T")

log = logging.getLogger(__name__)


class Background:
    """Spawn coroutines with ``spawn``; ``close`` cancels every one still running and waits for them."""

    def __init__(self) -> None:
        self.tasks: set[asyncio.Task[Any]] = set()

    def spawn(
        self, coro: Coroutine[Any, Any, Any], name: str | None = None, context: contextvars.Context | None = None
    ) -> asyncio.Task[Any]:
        loop = asyncio.get_running_loop()
        ctx = context if context is not None else contextvars.Context()
        task: asyncio.Task[Any] = loop.create_task(coro, name=name, context=ctx)
        self.tasks.add(task)
        task.add_done_callback(self.tasks.discard)
        return task

    async def close(self) -> None:
        tasks = list(self.tasks)
        for task in tasks:
            task.cancel()
        for result in await asyncio.gather(*tasks, return_exceptions=True):
            if isinstance(result, Exception):
                log.error("a background task had failed: %r", result)


def eager(coro: Coroutine[Any, Any, T], context: contextvars.Context) -> asyncio.Task[T] | None:
    """Run ``coro`` now, in ``context``, up to its first wait; a task carries it on from there. None:
    it finished without waiting (what Python 3.12's eager tasks do; a task costs about as much as a
    short request's own work). Its result is dropped; an exception it raises before waiting is
    raised here."""
    try:
        waiting = context.run(coro.send, None)
    except StopIteration:
        return None
    return asyncio.get_running_loop().create_task(_resumed(coro, waiting), context=context)


@types.coroutine
def _resumed(coro: Coroutine[Any, Any, T], waiting: Any) -> Generator[Any, Any, T]:
    """``coro`` from where it waits on ``waiting``: what it waits on goes to the task, what the task
    sends or throws (the result, a cancellation) goes to it."""
    while True:
        try:
            value = yield waiting
        except BaseException as exc:
            try:
                waiting = coro.throw(exc)
            except StopIteration as stop:
                return stop.value  # type: ignore[no-any-return]
        else:
            try:
                waiting = coro.send(value)
            except StopIteration as stop:
                return stop.value  # type: ignore[no-any-return]
