"""The gateway's one pool of shared connections (``gateway.pool``) and its one reconnect loop
(``gateway.retry``), pure: what every transport and driver builds on."""

from __future__ import annotations

import asyncio
from typing import Any

import pytest

from uacell.gateway.link import PolledLink
from uacell.gateway.pool import SharedPool, unit_conflict
from uacell.gateway.retry import keep_trying, poll_backoff


class Conn:
    def __init__(self, name: str) -> None:
        self.name, self.users, self.closed = name, 0, False

    async def close(self) -> None:
        self.closed = True


async def test_one_connection_per_key_closed_by_its_last_user() -> None:
    pool: SharedPool[str, Conn] = SharedPool(lambda c: c.close(), lambda c: c.name)
    a = pool.get("plc", lambda: Conn("opc://plc"), "Capper", timeout=1.0)
    assert pool.get("plc", lambda: Conn("another"), "Labeler", timeout=1.0) is a and a.users == 2
    assert pool.get("other", lambda: Conn("opc://other"), "Filler", timeout=2.5) is not a
    with pytest.raises(ValueError) as refused:
        pool.get("plc", lambda: Conn("x"), "Filler", timeout=2.5)
    assert str(refused.value) == (
        "Filler: timeout = 2.5, but Capper shares its connection to opc://plc with timeout = 1: "
        "parts on one PLC endpoint use one connection, so give them the same timeout"
    )
    assert a.users == 2 and len(pool) == 2  # the refusal counted nothing
    await pool.release(a)
    assert not a.closed and pool.get_open("plc") is a
    await pool.release(a)
    assert a.closed and pool.get_open("plc") is None and len(pool) == 1
    assert pool.get("plc", lambda: Conn("opc://plc again"), "Capper").name == "opc://plc again"  # made anew


def test_a_unit_refused_names_the_setting_and_what_the_units_before_it_set() -> None:
    pool: SharedPool[str, Conn] = SharedPool(lambda c: c.close(), lambda c: c.name, unit_conflict)
    pool.get("plc", lambda: Conn("s7://plc"), "Capper", interval=0.05)
    with pytest.raises(ValueError, match=r"^Filler: interval: another unit on s7://plc set 0\.05; units on one PLC"):
        pool.check("plc", "Filler", interval=0.2)


async def test_the_loop_backs_off_while_unanswered_and_starts_again_once_answered() -> None:
    answers = iter([False, False, False, True, False, True, True])
    waits: list[float] = []

    async def attempt() -> bool:
        return next(answers)

    async def sleep(seconds: float) -> None:
        waits.append(seconds)

    # a link: after a session that was up (and is lost) it waits the first delay again
    await keep_trying(attempt, first=0.5, last=2.0, closed=lambda: len(waits) == 7, sleep=sleep)
    assert waits == [0.5, 1.0, 2.0, 0.5, 1.0, 0.5, 0.5]
    # a poll: answered, it waits its poll; unanswered, twice the poll (at least 0.1 s) doubling to 2 s
    answers, waits = iter([True, False, False, False, False, False, True]), []
    poll = 0.05
    await keep_trying(
        attempt, first=poll_backoff(poll), last=2.0, pause=poll, closed=lambda: len(waits) == 7, sleep=sleep
    )
    assert waits == [0.05, 0.1, 0.2, 0.4, 0.8, 1.6, 0.05]
    assert poll_backoff(0.01) == 0.1 and poll_backoff(0.3) == 0.6 and poll_backoff(5.0) == 2.0


class _SwallowingConn:
    """A connection whose first connect finishes although its task was cancelled meanwhile, as a
    connection made by ``asyncio.wait_for`` just when the task is cancelled does on Python 3.11."""

    def __init__(self) -> None:
        self.connected = False
        self.connects = 0
        self.entered = asyncio.Event()

    async def connect(self) -> bool:
        self.connects += 1
        if self.connects == 1:
            self.entered.set()
            try:
                await asyncio.sleep(30)
            except asyncio.CancelledError:
                pass  # the result was ready: the cancellation is lost
        self.connected = True
        return True


class _Link(PolledLink):
    def parse(self, address: str) -> str:
        return address

    async def _read(self, addresses: list[str]) -> list[Any]:
        return [0 for _ in addresses]

    async def _write(self, writes: list[tuple[str, Any, str]]) -> None:
        pass


async def test_closing_a_link_ends_its_task_when_a_cancellation_is_lost() -> None:
    conn = _SwallowingConn()
    link = _Link(conn, "test://plc", interval=0.01)
    link.start()
    await asyncio.wait_for(conn.entered.wait(), 5.0)
    await asyncio.wait_for(link.close(), 6.0)
    assert link._task is not None and link._task.done()  # no task left polling after the close
