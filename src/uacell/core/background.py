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
from asyncio.tasks import _current_tasks  # type: ignore[attr-defined]  # not in typeshed: see _CURRENT
from collections.abc import Callable, Coroutine, Generator
from typing import Any, TypeVar

T = TypeVar("T")

log = logging.getLogger(__name__)

CLOSE_GRACE = 5.0  # seconds ``Background.close`` waits before it cancels a task again, and again before it gives up


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

    async def close(self, grace: float = CLOSE_GRACE) -> None:
        """Cancel every task and wait for them to end. A task still running ``grace`` seconds after its
        cancellation is cancelled again (one can be lost, see ``stop_task``), and one still running
        ``grace`` seconds after that is named in an ERROR and left: a close is never held up for
        ever. The grace leaves a task's own clean-up (a pulse written back low) time to finish
        before it is interrupted."""
        tasks = list(self.tasks)
        for task in tasks:
            task.cancel()
        pending: set[asyncio.Task[Any]] = set(tasks)
        for last in (False, True):
            if not pending:
                break
            _done, pending = await asyncio.wait(pending, timeout=grace)
            for task in pending:
                name = task.get_name()
                if last:
                    log.error("background task %s did not end after two cancellations: left running", name)
                else:
                    log.warning(
                        "background task %s still runs %g s after its cancellation: cancelled again", name, grace
                    )
                    task.cancel()
        for task in tasks:
            if task.done() and not task.cancelled() and isinstance(task.exception(), Exception):
                log.error("a background task had failed: %r", task.exception())


async def stop_task(task: asyncio.Task[Any] | None, within: float = 5.0) -> None:
    """Cancel ``task`` until it has ended, waiting ``within`` seconds at most (a stop is never held up
    longer by what the task waits on). The cancellation is repeated because one can be lost: Python
    3.11's ``asyncio.wait_for`` returns a result that is ready when its task is cancelled (a connection
    just made, for one), and the task carries on, e.g. to connect again after its owner closed the
    connection, leaving a socket nobody closes."""
    if task is None:
        return
    loop = asyncio.get_running_loop()
    deadline = loop.time() + within
    while not task.done() and (left := deadline - loop.time()) > 0:
        task.cancel()
        await asyncio.wait({task}, timeout=min(0.2, left))


def eager(coro: Coroutine[Any, Any, T], context: contextvars.Context) -> asyncio.Task[T] | None:
    """Run ``coro`` now, in ``context``, up to its first wait; a task carries it on from there. None:
    it finished without waiting (what Python 3.12's eager tasks do; a task costs about as much as a
    short request's own work). Its result is dropped; an exception it raises before waiting is
    raised here.

    Before its first wait the coroutine is in a task all the same (decision 73): ``asyncio.current_task()``
    is an ``EagerStep`` standing for the task that will carry it on, so ``asyncio.timeout``,
    ``TaskGroup`` and a cancellation work there as in any task (a cancellation asked for then reaches
    the coroutine at its first wait). A task running ``eager`` is not the coroutine's: it is set aside
    for the step."""
    loop = asyncio.get_running_loop()
    step = EagerStep(coro, loop)
    outer = _CURRENT.get(loop)
    _CURRENT[loop] = step
    try:
        waiting = context.run(coro.send, None)
    except StopIteration:
        return None
    finally:
        if outer is None:
            del _CURRENT[loop]
        else:
            _CURRENT[loop] = outer
    task = loop.create_task(_Resumed(coro, waiting), context=context)
    step.carried_on(task)
    return task


# The running task of each loop, what ``asyncio.current_task()`` answers from (Python 3.11 to 3.13 keep it
# in this dict; ``tests/test_eager.py`` checks that it still does).
_CURRENT: dict[asyncio.AbstractEventLoop, Any] = _current_tasks


class EagerStep:
    """The current task of a coroutine ``eager`` runs, up to its first wait: the task methods a
    coroutine uses on itself (cancel, uncancel, cancelling, done, names, callbacks), answered here
    until the task that carries it on exists and by that task afterwards."""

    __slots__ = ("_cancels", "_coro", "_loop", "_message", "_task")

    def __init__(self, coro: Coroutine[Any, Any, Any], loop: asyncio.AbstractEventLoop) -> None:
        self._coro = coro
        self._loop = loop
        self._task: asyncio.Task[Any] | None = None
        self._cancels = 0
        self._message: Any = None

    def carried_on(self, task: asyncio.Task[Any]) -> None:
        self._task = task
        for _ in range(self._cancels):  # asked for before the first wait: thrown in there
            task.cancel(self._message)

    def cancel(self, msg: Any = None) -> bool:
        if self._task is not None:
            return self._task.cancel(msg)
        self._cancels += 1
        self._message = msg
        return True

    def uncancel(self) -> int:
        if self._task is not None:
            return self._task.uncancel()
        self._cancels = max(0, self._cancels - 1)
        return self._cancels

    def cancelling(self) -> int:
        return self._task.cancelling() if self._task is not None else self._cancels

    def cancelled(self) -> bool:
        return self._task is not None and self._task.cancelled()

    def done(self) -> bool:
        return self._task is not None and self._task.done()

    def get_coro(self) -> Coroutine[Any, Any, Any]:
        return self._coro

    def get_loop(self) -> asyncio.AbstractEventLoop:
        return self._loop

    def get_name(self) -> str:
        return self._task.get_name() if self._task is not None else f"eager {getattr(self._coro, '__qualname__', '')}"

    def add_done_callback(self, fn: Callable[..., Any], *, context: contextvars.Context | None = None) -> None:
        if self._task is None:
            raise RuntimeError("a coroutine run eagerly has no task to call back before its first wait")
        self._task.add_done_callback(fn, context=context)


class _Resumed(Coroutine[Any, Any, T]):
    """``coro`` from where it waits on ``waiting``, as the task that carries it on sees it: the first
    step hands the task what it waits on; what the task sends or throws (the result, a cancellation,
    also one asked for before that first step) goes to ``coro``."""

    __slots__ = ("_coro", "_waiting")

    def __init__(self, coro: Coroutine[Any, Any, T], waiting: Any) -> None:
        self._coro = coro
        self._waiting: Any = waiting

    def send(self, value: Any) -> Any:
        waiting = self._waiting
        if waiting is not _STARTED:
            self._waiting = _STARTED
            return waiting
        return self._coro.send(value)

    def throw(self, typ: Any, val: Any = None, tb: Any = None) -> Any:
        self._waiting = _STARTED
        if val is None and tb is None:
            return self._coro.throw(typ)
        return self._coro.throw(typ, val, tb)  # the old three-argument form, as a generator takes it

    def close(self) -> None:
        self._coro.close()

    def __await__(self) -> Generator[Any, None, T]:
        return self._coro.__await__()


_STARTED = object()
