"""The web HMI's hold on the OPC UA server: sessions capped and given back, a refused password, slow headers.

Each web session in use holds an OPC UA session of its own; these tests count them on the server
(what a direct OPC UA client competes with) while pages open and close, as raw event streams.
"""

from __future__ import annotations

import asyncio
import json
import logging
import time
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import wait_until
from test_web import PASSWORD, Browser

from uacell.security.pki import PkiPaths
from uacell.web.hosting import start_web, trust_hmi

pytestmark = pytest.mark.asyncio(loop_scope="module")

CAP = 2


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def stack(tmp_path_factory):
    data = tmp_path_factory.mktemp("websessions") / "data"
    app = await start_app(fast_config(data))
    app.users.add("otto", "operator", PASSWORD)
    trust_hmi(data)
    web = await start_web(
        app.endpoint,
        data,
        companions=app.companions,
        port=0,
        server_certificate=PkiPaths.in_data_dir(data).cert,
        ua_sessions=CAP,
        release_after=0.5,
        header_timeout=1.0,
    )
    try:
        yield app, web
    finally:
        await web.stop()
        await app.stop()


def _port(web) -> int:
    return int(web.url.rsplit(":", 1)[1].strip("/"))


def held(app) -> int:
    """OPC UA sessions open on the server."""
    return len(app.server.iserver._external_sessions)


class Page:
    """An open page: the event stream of browser ``b``, read as the page reads it."""

    def __init__(self, web, b: Browser) -> None:
        self.port, self.cookie, self.key = _port(web), f"{web.web.cookie}={b.cookie()}", b.csrf
        self.reader: asyncio.StreamReader | None = None
        self.writer: asyncio.StreamWriter | None = None

    async def open(self) -> Page:
        self.reader, self.writer = await asyncio.open_connection("127.0.0.1", self.port)
        self.writer.write(
            f"GET /api/events?key={self.key} HTTP/1.1\r\nHost: 127.0.0.1:{self.port}\r\n"
            f"Cookie: {self.cookie}\r\n\r\n".encode()
        )
        await self.writer.drain()
        return self

    async def until(self, want, timeout: float = 60.0) -> dict[str, Any]:
        assert self.reader is not None
        async with asyncio.timeout(timeout):
            while True:
                line = await self.reader.readline()
                assert line, "the event stream ended"
                if line.startswith(b"data: "):
                    message = json.loads(line[6:])
                    if want(message):
                        return message

    async def close(self) -> None:
        if self.writer is not None:
            self.writer.close()
            self.writer = None


async def test_web_users_hold_at_most_ua_sessions_and_give_them_back_when_their_pages_close(stack):
    app, web = stack
    await wait_until(lambda: held(app) == 0, timeout=30)
    browsers = [Browser(web.url) for _ in range(3)]
    for b in browsers:
        await b.start()
    pages = [Page(web, b) for b in browsers]
    try:
        for page in pages[:CAP]:
            await (await page.open()).until(lambda m: m.get("status") == "connected")
        assert held(app) == CAP
        # The third page finds the HMI busy, and says so; the server keeps its other sessions free.
        busy = await (await pages[2].open()).until(lambda m: m.get("status") == "busy")
        assert f"already serves {CAP} users" in busy["problem"]
        status, answer = await browsers[2].post("/api/call", {"key": "Filler1/SetMachSpeed", "args": [60.0]})
        assert status == 200 and answer["code"] == "BadTooManySessions"
        assert held(app) == CAP
        async with Client(app.endpoint, timeout=20) as direct:  # a direct OPC UA client still gets in
            assert await direct.get_node(ua.NodeId(ua.ObjectIds.Server_ServerStatus_State)).read_value() == 0
        # The first page closes: its OPC UA session goes back, and the waiting page gets it.
        await pages[0].close()
        await pages[2].until(lambda m: m.get("status") == "connected")
        assert held(app) == CAP
        # Every page closed: every OPC UA session given back soon (release_after), not after 30 minutes.
        for page in pages:
            await page.close()
        await wait_until(lambda: held(app) == 0, timeout=10)
        # The web sessions live on: the next request makes an OPC UA session again.
        status, answer = await browsers[1].post("/api/call", {"key": "Filler1/SetMachSpeed", "args": [60.0]})
        assert status == 200 and answer["code"] == "Good"
        assert held(app) == 1
    finally:
        for page in pages:
            await page.close()


async def test_a_password_changed_meanwhile_ends_the_web_session_after_one_refusal(stack, caplog):
    app, web = stack
    b = Browser(web.url)
    await b.start()
    assert (await b.login("otto"))[0] == 200
    page = await Page(web, b).open()
    try:
        await page.until(lambda m: m.get("status") == "connected")
        await page.close()
        await wait_until(lambda: held(app) == 0, timeout=10)  # released while no page is open
        app.users.set_password("otto", "a-new-password-2")
        caplog.set_level(logging.INFO)
        page = await Page(web, b).open()  # the page comes back: the HMI tries the password it had
        refused = await page.until(lambda m: m.get("status") == "login-required")
        assert "no longer accepts the password of otto" in refused["problem"]
        expired = await page.until(lambda m: m.get("type") == "expired")
        assert "no longer accepts the password of otto" in expired["reason"]
    finally:
        await page.close()
    # One refusal, no retries: the web session ended, its cookie is stale, the login box is the way.
    status, answer = await b.post("/api/call", {"key": "Filler1/SetMachSpeed", "args": [60.0]})
    assert status == 401 and answer["expired"]
    refusals = [r for r in caplog.records if "no longer accepts its password" in r.getMessage()]
    assert len(refusals) == 1
    started = time.monotonic()
    await b.start()
    status, answer = await b.login("otto", "a-new-password-2")
    assert status == 200 and answer["user"] == "otto"
    assert time.monotonic() - started < 5  # not held back by a throttle the HMI's retries built up


async def test_a_request_whose_headers_dribble_in_is_closed_with_408(stack):
    _app, web = stack
    port = _port(web)
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(b"GET /api/session HTTP/1.1\r\nHost: 127.0.0.1\r\n")
        await writer.drain()
        started = time.monotonic()

        async def dribble() -> None:
            for _ in range(100):  # a header byte every 0.1 s, never finished
                writer.write(b"X")
                await writer.drain()
                await asyncio.sleep(0.1)

        feeder = asyncio.ensure_future(dribble())
        try:
            answer = await asyncio.wait_for(reader.read(), 10)
        finally:
            feeder.cancel()
        assert answer.startswith(b"HTTP/1.1 408 ")
        assert time.monotonic() - started < 5
    finally:
        writer.close()
    # A polite client on the same HMI is served as before.
    b = Browser(web.url)
    await b.start()


async def test_concurrent_wrong_logins_are_each_refused_as_wrong(stack):
    _app, web = stack
    browsers = [Browser(web.url) for _ in range(6)]
    for b in browsers:
        await b.start()
    answers = await asyncio.gather(*(b.login("otto", f"wrong-{i}") for i, b in enumerate(browsers)))
    assert [(status, answer.get("code")) for status, answer in answers] == [(401, "BadUserAccessDenied")] * 6


async def _raw(web, request: str) -> tuple[int, dict[str, Any]]:
    """One HTTP request as another program on this host sends it (no browser): status and JSON body."""
    port = _port(web)
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(request.replace("HOST", f"127.0.0.1:{port}").encode())
        await writer.drain()
        answer = (await asyncio.wait_for(reader.read(), 30)).decode()
    finally:
        writer.close()
    head, _, body = answer.partition("\r\n\r\n")
    return int(head.split(" ", 2)[1]), json.loads(body)


async def test_a_session_cookie_replayed_by_another_local_program_is_nobodys_session(stack):
    app, web = stack
    app.users.add("rita", "operator", PASSWORD)
    b = Browser(web.url)
    await b.start()
    assert (await b.login("rita"))[0] == 200
    # Another program on this host got rita's cookie (browsers send it to every port of 127.0.0.1)
    # and replays it; it never sees the token, which the page keeps in its own origin's storage.
    cookie = f"{web.web.cookie}={b.cookie()}"
    common = f"Host: HOST\r\nCookie: {cookie}\r\nConnection: close\r\n"
    status, info = await _raw(web, f"GET /api/session HTTP/1.1\r\n{common}\r\n")
    assert status == 200 and info["fresh"] and info["user"] is None and info["csrf"] != b.csrf
    assert (await _raw(web, f"GET /api/events HTTP/1.1\r\n{common}\r\n"))[0] == 401
    assert (await _raw(web, f"GET /api/events?key=guess HTTP/1.1\r\n{common}\r\n"))[0] == 401
    assert (await _raw(web, f"GET /api/history?hours=1 HTTP/1.1\r\n{common}\r\n"))[0] == 401
    body = json.dumps({"key": "Filler1/SetMachSpeed", "args": [60.0]})
    length = f"Content-Type: application/json\r\nContent-Length: {len(body)}\r\n"
    post = f"POST /api/call HTTP/1.1\r\n{common}{length}\r\n{body}"
    assert (await _raw(web, post))[0] == 403
    # The page itself, with cookie and token, is still rita's.
    status, info = await b.get("/api/session")
    assert status == 200 and info["user"] == "rita" and not info["fresh"] and info["csrf"] == b.csrf
    page = await Page(web, b).open()
    try:
        await page.until(lambda m: m.get("status") == "connected")
    finally:
        await page.close()


async def test_a_page_and_a_request_of_one_session_at_once_make_one_opc_ua_session(stack):
    app, web = stack
    await wait_until(lambda: held(app) == 0, timeout=30)
    b = Browser(web.url)
    await b.start()
    page = Page(web, b)
    try:
        history, _ = await asyncio.gather(
            b.get("/api/history?hours=1"),
            (await page.open()).until(lambda m: m.get("status") == "connected"),
        )
        assert history[0] == 200
        assert held(app) == 1  # one session for both, none left over from a second connect
    finally:
        await page.close()
    await wait_until(lambda: held(app) == 0, timeout=30)


async def test_the_loopback_hardening_setting_leaves_anonymous_pages_and_local_programs_watching(tmp_path):
    """docs/security.md, "The loopback trust model": ``[server] anonymous_role = "observer"`` takes the
    anonymous operator away from local programs and from the HMI's anonymous pages; a login operates."""
    data = tmp_path / "data"
    config = fast_config(data)
    config.server.anonymous_role = "observer"
    app = await start_app(config)
    app.users.add("otto", "operator", PASSWORD)
    trust_hmi(data)
    web = await start_web(
        app.endpoint, data, companions=app.companions, port=0, server_certificate=PkiPaths.in_data_dir(data).cert
    )
    try:
        speed = {"key": "Filler1/SetMachSpeed", "args": [60.0]}
        b = Browser(web.url)
        await b.start()
        status, answer = await b.post("/api/call", speed)
        assert status == 200 and answer["code"] == "BadUserAccessDenied"
        async with Client(app.endpoint, timeout=20) as local:  # a local program, anonymous
            filler = ua.NodeId("Filler1", app.cell.instantiator.ns)
            method = app.dispatcher.method_of(filler, "SetMachSpeed")
            with pytest.raises(ua.UaStatusCodeError) as refused:
                await local.get_node(filler).call_method(method, ua.Variant(60.0, ua.VariantType.Float))
            assert refused.value.code == ua.StatusCodes.BadUserAccessDenied
        assert (await b.login("otto"))[0] == 200
        status, answer = await b.post("/api/call", speed)
        assert status == 200 and answer["code"] == "Good"
    finally:
        await web.stop()
        await app.stop()


async def test_a_login_the_server_ends_while_the_page_is_open_is_renewed_or_ended(stack):
    """Decision 103: ``users.toml`` changed under an open page makes the HMI's OPC UA session anonymous
    (decision 99). The HMI notices (Server/CurrentUser), activates the session again with the password
    the web user gave: a new role is shown at once; a password that no longer works ends the web session
    with one refusal, and the page asks for a login. (Last in this module: its refused activation
    counts as a failed login from 127.0.0.1, which the server's throttle remembers.)"""
    app, web = stack
    app.users.add("tilda", "operator", "t1lda-web-pw")
    b = Browser(web.url)
    await b.start()
    assert (await b.login("tilda", "t1lda-web-pw"))[0] == 200
    page = await Page(web, b).open()
    try:
        first = await page.until(lambda m: m.get("type") == "snapshot" and m.get("status") == "connected")
        assert (first["user"], first["role"]) == ("tilda", "operator")
        app.users.set_role("tilda", "engineer")  # as `uacell user role` does from another process
        renewed = await page.until(lambda m: m.get("type") == "snapshot" and m.get("role") == "engineer")
        assert renewed["status"] == "connected" and renewed["user"] == "tilda"
        status, answer = await b.post("/api/call", {"key": "Filler1/SetMachSpeed", "args": [61.0]})
        assert status == 200 and answer["code"] == "Good"

        def tildas_call() -> bool:  # the audit trail is written by its own thread
            lines = (app.data_dir / "audit.log").read_text().splitlines()
            calls = [
                e for e in map(json.loads, lines) if e.get("event") == "call" and e.get("method") == "SetMachSpeed"
            ]
            return bool(calls) and (calls[-1]["user"], calls[-1]["role"]) == ("tilda", "engineer")

        await wait_until(tildas_call, timeout=20)  # the call is the user's again, not anonymous's

        app.users.set_password("tilda", "t1lda-web-pw-2")
        refused = await page.until(lambda m: m.get("status") == "login-required")
        assert "no longer accepts the password of tilda" in refused["problem"]
        await page.until(lambda m: m.get("type") == "expired")
    finally:
        await page.close()
    status, answer = await b.post("/api/call", {"key": "Filler1/SetMachSpeed", "args": [60.0]})
    assert status == 401 and answer["expired"]
    # nothing held: the server's session went with the web session
    await wait_until(lambda: held(app) == 0, timeout=10)
    assert not web.web.places.slots.holders
