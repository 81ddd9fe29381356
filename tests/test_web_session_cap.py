"""Issue 39 point 1: the HMI's cap on OPC UA sessions holds whatever the concurrency.

200 pages open at once against ``[web] ua_sessions`` = 50. The server's own count of sessions is
watched at every change (the peak), and read from its diagnostics (ServerDiagnosticsSummary
CurrentSessionCount) once the pages settled. Every page beyond the cap says "HMI busy", never
"unreachable", and gets its session as soon as one is released.
"""

from __future__ import annotations

import asyncio
import collections
import json
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import wait_until

from uacell.security.pki import PkiPaths
from uacell.web.hosting import start_web, trust_hmi

pytestmark = pytest.mark.asyncio(loop_scope="module")

CAP = 50
PAGES = 200
SETTLED = ("connected", "busy", "unreachable")


class PeakCount(dict):  # type: ignore[type-arg]
    """The server's table of sessions, remembering the most it ever held."""

    peak = 0

    def __setitem__(self, key: Any, value: Any) -> None:
        super().__setitem__(key, value)
        self.peak = max(self.peak, len(self))


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def stack(tmp_path_factory):
    data = tmp_path_factory.mktemp("websessioncap") / "data"
    config = fast_config(data)
    # This process is the server, the HMI and the test: with 8 SignAndEncrypt handshakes at once on a
    # loaded machine, the HMI's OpenSecureChannel came after the default 5 s, the server closed the
    # connection, and the page's first status was "unreachable". The cap is what is tested here.
    config.limits.handshake_timeout = 30.0
    app = await start_app(config)
    trust_hmi(data)
    web = await start_web(
        app.endpoint,
        data,
        companions=app.companions,
        port=0,
        server_certificate=PkiPaths.in_data_dir(data).cert,
        ua_sessions=CAP,
        release_after=2.0,
    )
    sessions = PeakCount(app.server.iserver._external_sessions)
    app.server.iserver._external_sessions = sessions
    try:
        yield app, web, sessions
    finally:
        await web.stop()
        await app.stop()


def _port(web) -> int:
    return int(web.url.rsplit(":", 1)[1].strip("/"))


async def _request(port: int, head: str) -> tuple[asyncio.StreamReader, asyncio.StreamWriter]:
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(f"{head}Host: 127.0.0.1:{port}\r\n\r\n".encode())
    await writer.drain()
    return reader, writer


async def new_session(port: int) -> tuple[str, str]:
    """A fresh web session, as a page's first request makes one: the ``Cookie`` header value and the
    session's token."""
    reader, writer = await _request(port, "GET /api/session HTTP/1.1\r\nConnection: close\r\n")
    try:
        answer = (await reader.read()).decode()
    finally:
        writer.close()
    line = next(x for x in answer.split("\r\n") if x.lower().startswith("set-cookie:"))
    return line.split(":", 1)[1].strip().split(";", 1)[0], json.loads(answer.split("\r\n\r\n", 1)[1])["csrf"]


class Page:
    """One open page: its event stream, read as the page reads it."""

    def __init__(self, port: int, session: tuple[str, str]) -> None:
        self.port, (self.cookie, self.key) = port, session
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None
        self.statuses: list[str] = []

    async def open(self) -> str:
        """Open the page; the first settled status it shows."""
        head = f"GET /api/events?key={self.key} HTTP/1.1\r\nCookie: {self.cookie}\r\n"
        self.reader, self.writer = await _request(self.port, head)
        return await self.until(lambda status: status in SETTLED)

    async def until(self, want, timeout: float = 240.0) -> str:
        assert self.reader is not None
        async with asyncio.timeout(timeout):
            while True:
                line = await self.reader.readline()
                assert line, "the event stream ended"
                if not line.startswith(b"data: "):
                    continue
                status = json.loads(line[6:]).get("status")
                if status:
                    self.statuses.append(status)
                    if want(status):
                        return status

    def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


async def _current_session_count(app) -> int:
    """ServerDiagnosticsSummary.CurrentSessionCount, read by a client of its own (counted in it)."""
    node = ua.NodeId(ua.ObjectIds.Server_ServerDiagnostics_ServerDiagnosticsSummary_CurrentSessionCount)
    async with Client(app.endpoint, timeout=30) as direct:
        return int(await direct.get_node(node).read_value())


async def test_200_pages_opened_at_once_hold_at_most_ua_sessions_and_the_rest_are_told_busy(stack):
    app, web, sessions = stack
    port = _port(web)
    pages = [Page(port, await new_session(port)) for _ in range(PAGES)]
    try:
        first = await asyncio.gather(*(p.open() for p in pages))
        connected = [p for p, status in zip(pages, first, strict=True) if status == "connected"]
        busy = [p for p, status in zip(pages, first, strict=True) if status == "busy"]
        # The server never held more of the HMI's sessions than the cap, at any moment.
        assert sessions.peak <= CAP, f"the server held {sessions.peak} sessions at the peak"
        assert len(connected) == CAP, collections.Counter(first)
        assert len(busy) == PAGES - CAP  # every page beyond the cap says busy, none "unreachable"
        assert all("unreachable" not in p.statuses for p in pages)
        assert len(sessions) == CAP
        # The server's diagnostics agree (its own client is the one more).
        await wait_until(lambda: len(sessions) == CAP, timeout=30)
        assert await _current_session_count(app) == CAP + 1
        await wait_until(lambda: len(sessions) == CAP, timeout=30)
        sessions.peak = len(sessions)  # the peak from here on, without that direct client

        # Five connected pages close: five waiting pages get a session, none beyond the cap.
        for page in connected[:5]:
            page.close()
        admitted = await asyncio.wait_for(
            asyncio.gather(*(p.until(lambda s: s == "connected") for p in busy[:5])), timeout=240
        )
        assert admitted == ["connected"] * 5
        assert sessions.peak <= CAP
        await wait_until(lambda: len(sessions) == CAP, timeout=60)
    finally:
        for page in pages:
            page.close()
    await wait_until(lambda: len(sessions) == 0, timeout=120)  # every page closed: released (release_after)


async def test_slots_are_taken_in_one_step_and_given_back_once() -> None:
    from uacell.web.uasession import SessionSlots

    slots = SessionSlots(2)
    freed: list[int] = []
    slots.on_free = lambda: freed.append(slots.free)
    a, b, c = object(), object(), object()
    assert slots.take(a) and slots.take(a) and slots.take(b)
    assert not slots.take(c) and slots.free == 0
    slots.give(a)
    slots.give(a)  # a second give of the same holder frees nothing more
    assert freed == [1]
    assert await slots.wait_take(c, 0.1)
    assert not await slots.wait_take(a, 0.05)
