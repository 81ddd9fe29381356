"""The gateway's one reconnect loop: every link to a PLC and every robot driver keeps its equipment in
reach with ``keep_trying``, and backs off alike while it does not answer (docs/equipment.md, "Gateway")."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

FIRST_RETRY, LAST_RETRY = 0.5, 2.0  # a link's seconds between reconnection attempts: doubling, at most LAST_RETRY


def _never() -> bool:
    return False


async def keep_trying(
    attempt: Callable[[], Awaitable[bool]],
    *,
    first: float = FIRST_RETRY,
    last: float = LAST_RETRY,
    pause: float | None = None,
    closed: Callable[[], bool] = _never,
    sleep: Callable[[float], Awaitable[None]] = asyncio.sleep,
) -> None:
    """Call ``attempt`` again and again until ``closed()`` (or the task is cancelled). After an attempt
    that reached the equipment (it returns True) the wait is ``pause`` when given (a poll that was
    answered), else ``first`` (a connection that was up and is lost); after one that did not, the wait
    doubles, from ``first`` up to ``last``."""
    delay = first
    while not closed():
        if await attempt():
            delay = first
            if pause is not None:
                await sleep(pause)
                continue
        await sleep(delay)
        delay = min(delay * 2, last)


def poll_backoff(poll: float, most: float = LAST_RETRY) -> float:
    """The first wait of a poll that was not answered: twice the poll, at least 0.1 s, at most ``most``."""
    return min(most, max(poll * 2, 0.1))
