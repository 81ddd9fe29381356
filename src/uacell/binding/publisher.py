"""The one ordered publisher of address-space changes: every binder submits its updates here.

Changes reach the address space through one ``Publisher`` so that events and values keep the order in
which the models produced them. A method call is answered first and its changes are published right
after, before the server serves any other request (decision 56: the pipeline's ``PublishedStage``
flushes the publisher when a drain is due or under way). Free of asyncua: it runs coroutines.
"""

from __future__ import annotations

import asyncio
import collections
import contextvars
import logging
from collections.abc import Awaitable, Callable

from uacell.core.background import eager

log = logging.getLogger(__name__)


class Publisher:
    """Runs address-space updates one after another, in submission order."""

    def __init__(self) -> None:
        self._queue: collections.deque[Callable[[], Awaitable[None]]] = collections.deque()
        self._task: asyncio.Task[None] | None = None  # the drain under way, from its first wait on
        self._draining = False
        self._due: asyncio.Handle | None = None  # the drain scheduled by a submit, not yet started
        # Run whenever the queue has drained: the server refreshes Executable here, so that changes made
        # outside method calls (acting states completing, a program ending) reach it too (decision 4);
        # ``touch(machine)`` tells the touch hooks (the dispatcher) which machine changed, so that only
        # the methods whose Executable depends on it are re-evaluated.
        self.idle_hooks: list[Callable[[], Awaitable[None]]] = []
        self.touch_hooks: list[Callable[[object], None]] = []

    def touch(self, scope: object) -> None:
        for hook in self.touch_hooks:
            hook(scope)

    def submit(self, job: Callable[[], Awaitable[None]]) -> None:
        self._queue.append(job)
        self.schedule()

    def schedule(self) -> None:
        """Drain soon (on the event loop's next turn), also with nothing queued, so that the idle
        hooks run: a method call touched scopes whose Executable may have changed."""
        if not self._draining and self._due is None:
            self._due = asyncio.get_running_loop().call_soon(self._drain)

    @property
    def pending(self) -> bool:
        """Is a drain due or under way (something submitted may not be in the address space yet)?"""
        return self._due is not None or self._draining

    def _drain(self) -> None:
        """Run the queue now, in a fresh context (the jobs must not carry the request that happened to
        submit the first), up to its first wait; a task goes on from there (``background.eager``)."""
        self._due = None
        if not self._draining:
            self._draining = True
            self._task = eager(self._run(), contextvars.Context())

    async def _run(self) -> None:
        try:
            while True:
                while self._queue:
                    job = self._queue.popleft()
                    try:
                        await job()
                    except Exception:
                        log.exception("publishing a change failed")
                for hook in self.idle_hooks:
                    try:
                        await hook()
                    except Exception:
                        log.exception("publisher idle hook failed")
                if not self._queue:  # jobs submitted while the hooks ran are taken in the next round
                    return
        finally:
            self._draining = False

    async def flush(self, timeout: float | None = None) -> None:
        """Wait until everything submitted so far is in the address space, and the idle hooks have run
        after it (so ``Executable`` is current too). A drain that is due runs now, in this call (a
        method call's changes are published without a task of their own); one that waits (a job
        awaiting something) is waited for up to ``timeout`` seconds (``TimeoutError`` after: the
        drain goes on). Never call it from inside a job."""
        if self._due is not None:
            self._due.cancel()
            self._drain()
        task = self._task
        if task is not None and not task.done():
            await asyncio.wait_for(asyncio.shield(task), timeout)

    async def close(self) -> None:
        await self.flush()
