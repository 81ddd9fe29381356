"""The web HMI over HTTP (no browser): discovery, sessions, cookies, CSRF, roles, HTTPS, reconnecting.

An in-process uacell server with the HMI beside it (as `uacell serve` runs it); requests go to the
HMI's real HTTP port with urllib, the answers and the server's state are checked.
"""

from __future__ import annotations

import asyncio
import json
import logging
import signal
import ssl
import subprocess
import sys
import time
import urllib.error
import urllib.request
from http.cookiejar import CookieJar
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import free_port, wait_until

from uacell.core.companion import web_views
from uacell.core.errors import ConfigError
from uacell.packml.binding import UNITS
from uacell.security.pki import PkiPaths
from uacell.web.discovery import discover
from uacell.web.guards import MAX_BODY, HostGuard, host_name
from uacell.web.hosting import start_web, trust_hmi

pytestmark = pytest.mark.asyncio(loop_scope="module")

PASSWORD = "pw-web-1"
FILLER = "Filler1.BaseStateMachine.MachineState"


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def stack(tmp_path_factory):
    data = tmp_path_factory.mktemp("web") / "data"
    app = await start_app(fast_config(data))
    app.users.add("olga", "observer", PASSWORD)
    app.users.add("otto", "operator", PASSWORD)
    trust_hmi(data)
    web = await start_web(
        app.endpoint, data, companions=app.companions, port=0, server_certificate=PkiPaths.in_data_dir(data).cert
    )
    try:
        yield app, web
    finally:
        await web.stop()
        await app.stop()


class Browser:
    """A cookie-keeping HTTP client (urllib, run in a thread)."""

    def __init__(self, base: str, context: ssl.SSLContext | None = None) -> None:
        self.base = base.rstrip("/")
        self.jar = CookieJar()
        handlers: list[Any] = [urllib.request.HTTPCookieProcessor(self.jar)]
        if context is not None:
            handlers.append(urllib.request.HTTPSHandler(context=context))
        self.opener = urllib.request.build_opener(*handlers)
        self.csrf = ""
        self.last_headers: Any = None

    def _send(self, path: str, body: dict[str, Any] | None, headers: dict[str, str]) -> tuple[int, Any]:
        data = json.dumps(body).encode() if body is not None else None
        req = urllib.request.Request(self.base + path, data=data, headers=headers, method="POST" if data else "GET")
        try:
            with self.opener.open(req, timeout=60) as res:
                self.last_headers = res.headers
                raw = res.read()
                status = res.status
        except urllib.error.HTTPError as exc:
            self.last_headers = exc.headers
            raw, status = exc.read(), exc.code
        try:
            return status, json.loads(raw)
        except ValueError:
            return status, raw.decode(errors="replace")

    async def get(self, path: str) -> tuple[int, Any]:
        """A GET as the page makes it: with the session's token beside the cookie (once it has one)."""
        return await asyncio.to_thread(self._send, path, None, {"X-CSRF-Token": self.csrf} if self.csrf else {})

    async def post(self, path: str, body: dict[str, Any], csrf: str | None = None) -> tuple[int, Any]:
        headers = {"Content-Type": "application/json", "X-CSRF-Token": self.csrf if csrf is None else csrf}
        return await asyncio.to_thread(self._send, path, body, headers)

    async def start(self) -> None:
        status, info = await self.get("/api/session")
        assert status == 200
        self.csrf = info["csrf"]

    async def login(self, user: str, password: str = PASSWORD) -> tuple[int, Any]:
        status, answer = await self.post("/api/login", {"user": user, "password": password})
        if status == 200:
            self.csrf = answer["csrf"]
        return status, answer

    def cookie(self) -> str:
        value = next(c.value for c in self.jar if c.name.startswith(("uacell_", "__Host-uacell_")))
        assert value is not None  # the HMI's cookies carry a value
        return value


async def _state(app, machine: str) -> str:
    async with Client(app.endpoint, timeout=20) as c:
        ns = await c.get_namespace_index("urn:uacell:cell")
        return (await c.get_node(ua.NodeId(f"{machine}.CurrentState", ns)).read_value()).Text


async def test_discovery_finds_the_demo_cell_by_type_and_browse_name(stack):
    app, _ = stack
    async with Client(app.endpoint, timeout=20) as client:
        cell = await discover(client, web_views(app.companions))
        (unit,) = cell.layout["units"]
        assert unit["name"] == "Filler1"
        assert [m["name"] for m in unit["machines"]] == ["BaseStateMachine", "MachineState", "ExecuteState"]
        execute = unit["machines"][2]["methods"]
        assert set(execute) == {"Reset", "Start", "Hold", "Unhold", "Suspend", "Unsuspend", "ToComplete"}
        (robot,) = cell.layout["robots"]
        (controller,) = robot["controllers"]
        (task,) = controller["task_controls"]
        (arm,) = robot["motion_devices"]
        assert (robot["name"], controller["name"], task["name"], arm["name"]) == (
            "Robot1",
            "Controller1",
            "TaskControl1",
            "Arm1",
        )
        assert [a["name"] for a in arm["axes"]] == [f"Axis{i}" for i in range(1, 7)]
        assert {c["name"] for c in controller["conditions"]} == {"EmergencyStop", "CollisionDetected"}
        # Each key leads to the node of that BrowseName path.
        node = client.get_node(cell.variables[f"{task['key']}/CurrentState"])
        assert (await node.read_value()).Text == "Idle"
        start = client.get_node(cell.methods[execute["Start"]].method)
        assert (await start.read_browse_name()).Name == "Start"
        assert [a.Name for a in cell.methods[execute["Start"]].arguments] == ["Parameter"]


async def test_cookie_is_httponly_samesite_and_actions_need_the_csrf_token(stack):
    app, web = stack
    b = Browser(web.url)
    status, page = await b.get("/")
    assert status == 200 and "<svg" not in page and "/static/app.js" in page
    assert "content-security-policy" in {k.lower() for k in b.last_headers}
    status, _ = await b.get("/api/session")  # the page asks for its session: the cookie comes with it
    cookie = b.last_headers.get_all("set-cookie")[0].lower()
    assert "httponly" in cookie and "samesite=strict" in cookie and "secure" not in cookie
    await b.start()
    before = await _state(app, FILLER)
    key = "Filler1/MachineState/Reset"
    for token in ("", "not-the-token"):
        status, answer = await b.post("/api/call", {"key": key, "args": []}, csrf=token)
        assert status == 403 and "CSRF" in answer["error"]
    assert await _state(app, FILLER) == before == "Stopped"
    status, answer = await b.post("/api/call", {"key": key, "args": []})
    assert status == 200 and answer["good"] and answer["code"] == "Good"
    await app.settle()
    assert await _state(app, f"{FILLER}.ExecuteState") in ("Resetting", "Idle")
    # Leave the unit as found.
    status, answer = await b.post("/api/call", {"key": "Filler1/MachineState/Stop", "args": []})
    assert answer["good"]


async def test_login_rotates_the_session_and_keeps_the_password_out_of_logs(stack, caplog):
    _app, web = stack
    b = Browser(web.url)
    await b.start()
    anonymous = b.cookie()
    caplog.set_level(logging.DEBUG)
    status, answer = await b.login("otto", "wrong-password-xyz")
    assert status == 401 and answer["code"] == "BadUserAccessDenied"
    assert b.cookie() == anonymous
    status, answer = await b.login("otto")
    assert status == 200 and answer["user"] == "otto"
    assert b.cookie() != anonymous
    assert PASSWORD not in caplog.text and "wrong-password-xyz" not in caplog.text
    assert "web login of otto" in caplog.text
    # The anonymous session is gone: its cookie is refused as expired.
    stale = Browser(web.url)
    stale.opener.addheaders = [("Cookie", f"{web.web.cookie}={anonymous}")]
    status, answer = await stale.post("/api/call", {"key": "Filler1/MachineState/Reset", "args": []}, csrf="")
    assert status == 401 and answer["expired"]


async def test_the_number_of_web_sessions_is_bounded(stack, monkeypatch):
    _app, web = stack
    monkeypatch.setattr("uacell.web.app.MAX_SESSIONS", 2)
    browsers = [Browser(web.url) for _ in range(3)]
    for b in browsers:
        await b.start()
    status, answer = await browsers[0].post("/api/call", {"key": "Filler1/SetMachSpeed", "args": [60.0]})
    assert status == 401 and answer["expired"]
    for b in browsers[1:]:
        status, answer = await b.post("/api/call", {"key": "Filler1/SetMachSpeed", "args": [60.0]})
        assert status == 200 and answer["code"] == "Good"


async def test_observer_gets_every_method_refused_by_the_server(stack):
    app, web = stack
    b = Browser(web.url)
    await b.start()
    assert (await b.login("olga"))[0] == 200
    ua_session = web.web.sessions[b.cookie()].ua
    assert ua_session is not None and ua_session.methods
    assert not any(m["user_executable"] for m in ua_session.methods.values())
    assert ua_session.methods["Filler1/MachineState/Reset"]["executable"]  # the state allows it, the role not
    status, answer = await b.post("/api/call", {"key": "Filler1/MachineState/Reset", "args": []})
    assert status == 200 and not answer["good"]
    assert answer["code"] == "BadUserAccessDenied" and "permission" in answer["meaning"].lower()
    assert await _state(app, FILLER) == "Stopped"


async def test_bad_arguments_are_refused_before_reaching_the_server(stack):
    _app, web = stack
    b = Browser(web.url)
    await b.start()
    status, answer = await b.post("/api/call", {"key": "Filler1/SetMachSpeed", "args": ["fast"]})
    assert status == 400 and "RequestedMachineSpeed" in answer["error"]
    status, answer = await b.post("/api/call", {"key": "Filler1/NoSuchMethod", "args": []})
    assert status == 404
    status, answer = await b.post("/api/call", {"key": "Filler1/SetMachSpeed", "args": [1e9]})
    assert status == 200 and answer["code"] == "BadInvalidArgument"


async def test_https_only_on_a_non_loopback_address(stack, tmp_path):
    app, _ = stack
    with pytest.raises(ConfigError, match="HTTPS only"):
        await start_web(app.endpoint, tmp_path / "d", companions=app.companions, host="0.0.0.0", port=0)
    pki = PkiPaths.in_data_dir(app.data_dir)
    web = await start_web(
        app.endpoint,
        app.data_dir,
        companions=app.companions,
        host="0.0.0.0",
        port=0,
        server_certificate=pki.cert,
        https_certificate=pki.cert,
        https_key=pki.key,
    )
    try:
        port = int(web.url.rsplit(":", 1)[1].strip("/"))
        assert web.url.startswith("https://")
        context = ssl.create_default_context()
        context.check_hostname = False
        context.verify_mode = ssl.CERT_NONE
        b = Browser(f"https://127.0.0.1:{port}", context)
        status, _ = await b.get("/api/session")
        assert status == 200
        assert "secure" in b.last_headers.get_all("set-cookie")[0].lower()
        assert b.last_headers.get_all("set-cookie")[0].startswith(f"__Host-uacell_{port}=")
        assert b.last_headers["strict-transport-security"] == "max-age=31536000"
        # The server listens on loopback only (anonymous: operator, meant for the local machine), the
        # HMI on the network: it takes logged-in users only.
        await b.start()
        first = await asyncio.to_thread(_sse_until, b, lambda m: m["type"] == "snapshot")
        assert first["status"] == "login-required" and not first["layout"]
        status, answer = await b.post("/api/call", {"key": "Filler1/MachineState/Reset", "args": []})
        assert answer["code"] == "BadUserAccessDenied"
        assert await _state(app, FILLER) == "Stopped"
        assert (await b.login("otto"))[0] == 200
        back = await asyncio.to_thread(_sse_until, b, lambda m: m["type"] == "snapshot")
        assert back["status"] == "connected" and back["user"] == "otto"
        plain = Browser(f"http://127.0.0.1:{port}")
        with pytest.raises((urllib.error.URLError, ConnectionError, OSError)):
            await asyncio.to_thread(plain.opener.open, f"http://127.0.0.1:{port}/", None, 10)
    finally:
        await web.stop()


async def test_web_section_of_the_configuration(tmp_path):
    from uacell.config import load_config

    cfg = tmp_path / "c.toml"
    cfg.write_text('[web]\nenabled = false\nport = 9090\nhost = "::1"\n')
    config = load_config(cfg)
    assert (config.web.enabled, config.web.port, config.web.host) == (False, 9090, "::1")
    cfg.write_text("[web]\nport = 70000\n")
    with pytest.raises(ConfigError, match=r"\[web\] port"):
        load_config(cfg)
    cfg.write_text('[web]\nenabled = "yes"\n')
    with pytest.raises(ConfigError, match="true or false"):
        load_config(cfg)


async def test_static_files_are_package_data() -> None:
    from importlib import resources

    static = resources.files("uacell.web") / "static"
    names = {p.name for p in static.iterdir()}
    assert {"index.html", "app.js", "style.css"} <= names
    text = (static / "index.html").read_text() + (static / "app.js").read_text()
    assert "http://" not in text.replace("http://www.w3.org/2000/svg", "") and "https://" not in text


def _sse_until(b: Browser, want, timeout: float = 90.0) -> dict[str, Any]:
    """Read the page's event stream until a message satisfies ``want``; return it."""
    deadline = time.monotonic() + timeout
    with b.opener.open(urllib.request.Request(f"{b.base}/api/events?key={b.csrf}"), timeout=30) as res:
        while time.monotonic() < deadline:
            line = res.readline()
            assert line, "the event stream ended"
            if line.startswith(b"data: "):
                message = json.loads(line[6:])
                if want(message):
                    return message
    raise AssertionError("no such message in time")


async def test_the_page_learns_who_caused_a_transition_and_the_current_line(stack):
    app, web = stack
    unit = app.registry(UNITS)["Filler1"].unit
    await wait_until(lambda: unit.state == "Stopped")  # after an earlier test's Stop
    b = Browser(web.url)
    await b.start()
    assert (await b.login("otto"))[0] == 200
    status, answer = await b.post("/api/call", {"key": "Filler1/MachineState/Reset", "args": []})
    assert status == 200 and answer["good"]

    seen: list[dict[str, Any]] = []  # the page's list of last transitions, as the stream keeps it

    def attributed(message: dict[str, Any]) -> bool:
        if "events" in message:  # a snapshot, or the list again after an entry learnt its user
            seen[:] = message["events"]
        elif message.get("type") == "event":
            seen.insert(0, message["event"])
        return sum(e["user"] == "otto" for e in seen) >= 2

    await asyncio.to_thread(_sse_until, b, attributed)
    caused = next(e for e in seen if e["user"] == "otto" and e["machine"] == "Filler1/MachineState")
    assert (caused["machine"], caused["from"], caused["to"], caused["method"]) == (
        "Filler1/MachineState",
        "Stopped",
        "Running",
        "Reset",
    )
    # Resetting -> Idle completed after the Reset returned: still otto's Reset (decision 38).
    completed = next(e for e in seen if e["to"] == "Idle")
    assert (completed["user"], completed["method"], completed["from"]) == ("otto", "Reset", "Resetting")
    # The layout says the server audits, and names the task control's current line.
    layout = web.web.sessions[b.cookie()].ua.cell.layout
    assert layout["auditing"] is True
    (task,) = layout["robots"][0]["controllers"][0]["task_controls"]
    assert task["variables"]["CurrentLine"] == "Robot1/Controller1/TaskControl1/CurrentLine"
    status, answer = await b.post("/api/call", {"key": "Filler1/MachineState/Stop", "args": []})
    assert answer["good"]


async def test_uacell_web_standalone_until_the_server_trusts_its_certificate(stack, tmp_path):
    app, _ = stack
    port = free_port()
    hmi = tmp_path / "hmi"
    log_file = (tmp_path / "web.log").open("w")
    proc = subprocess.Popen(
        [sys.executable, "-m", "uacell", "web", "--server", app.endpoint, "--port", str(port), "--data-dir", str(hmi)],
        stdout=subprocess.PIPE,
        stderr=log_file,
        text=True,
    )
    assert proc.stdout is not None
    try:
        line = await asyncio.to_thread(proc.stdout.readline)
        assert line.strip() == f"uacell web on http://127.0.0.1:{port}/"
        assert len(list((hmi / "web" / "pki" / "server").glob("*.der"))) == 1  # the server's, pinned
        b = Browser(f"http://127.0.0.1:{port}")
        await b.start()
        refused = await asyncio.to_thread(_sse_until, b, lambda m: "BadCertificateUntrusted" in m.get("problem", ""))
        assert refused["status"] == "unreachable"
        # As docs/security.md says for any client: trust it with `uacell cert trust` (the HMI's is the
        # only certificate the server refused).
        pki = PkiPaths.in_data_dir(app.data_dir)
        (rejected,) = list(pki.rejected.iterdir())
        trust = await asyncio.create_subprocess_exec(
            sys.executable, "-m", "uacell", "cert", "trust", rejected.stem, "--data-dir", str(app.data_dir)
        )
        assert await trust.wait() == 0
        assert (pki.trusted / rejected.name).exists()
        back = await asyncio.to_thread(_sse_until, b, lambda m: m.get("status") == "connected")
        assert back["type"] == "snapshot" and back["layout"]["units"][0]["name"] == "Filler1"
    finally:
        proc.send_signal(signal.SIGTERM)
        assert await asyncio.to_thread(proc.wait, 30) == 0
        proc.stdout.close()
        log_file.close()


async def test_json_arguments_become_the_variants_the_method_declares():
    from uacell.web.uasession import jsonable, to_variant

    def arg(name: str, data_type: int, rank: int = -1) -> ua.Argument:
        return ua.Argument(Name=name, DataType=ua.NodeId(data_type), ValueRank=rank)

    v = to_variant(arg("Speed", ua.ObjectIds.Float), 42)
    assert (v.Value, v.VariantType) == (42.0, ua.VariantType.Float)
    v = to_variant(arg("EventId", ua.ObjectIds.ByteString), "00ff")
    assert (v.Value, v.VariantType) == (b"\x00\xff", ua.VariantType.ByteString)
    v = to_variant(arg("Comment", ua.ObjectIds.LocalizedText), "done")
    assert v.Value == ua.LocalizedText("done")
    v = to_variant(arg("Modes", ua.ObjectIds.Int32, 1), [1, 2.0])
    assert (v.Value, v.VariantType, v.is_array) == ([1, 2], ua.VariantType.Int32, True)
    for bad in (
        (arg("Mode", ua.ObjectIds.Int32), "two"),
        (arg("Mode", ua.ObjectIds.Int32), 1.5),
        (arg("Active", ua.ObjectIds.Boolean), "yes"),
        (arg("Modes", ua.ObjectIds.Int32, 1), 3),
        (arg("Mode", ua.ObjectIds.Int32), 1e30),
        (arg("Mode", ua.ObjectIds.Int32), 2**31),
        (arg("Count", ua.ObjectIds.UInt32), -1),
        (arg("Mode", ua.ObjectIds.Int64), float("inf")),
        (arg("Speed", ua.ObjectIds.Float), 1e39),
    ):
        with pytest.raises(ValueError, match=bad[0].Name):
            to_variant(*bad)
    assert jsonable([ua.LocalizedText("Idle"), ua.NodeId(5, 2), b"\x01", float("nan")]) == [
        "Idle",
        "ns=2;i=5",
        "01",
        None,
    ]


async def _raw_http(port: int, request: bytes) -> tuple[int, str]:
    """Send one hand-built HTTP/1.1 request; the status and the whole answer (headers and body)."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    try:
        writer.write(request)
        await writer.drain()
        answer = (await asyncio.wait_for(reader.read(), 30)).decode(errors="replace")
    finally:
        writer.close()
    return int(answer.split(" ", 2)[1]), answer


async def test_a_page_under_a_rebound_host_name_gets_421_and_drives_nothing(stack):
    """DNS rebinding: an attacker's name resolving to 127.0.0.1 reaches the port with its own Host."""
    app, web = stack
    port = int(web.url.rsplit(":", 1)[1].strip("/"))
    state = await _state(app, FILLER)
    status, answer = await _raw_http(
        port, f"GET /api/session HTTP/1.1\r\nHost: rebind.attacker.example:{port}\r\nConnection: close\r\n\r\n".encode()
    )
    assert status == 421
    assert "set-cookie" not in answer.lower() and "csrf" not in answer
    body = b'{"key": "Filler1/MachineState/Abort", "args": []}'
    status, _ = await _raw_http(
        port,
        b"POST /api/call HTTP/1.1\r\nHost: rebind.attacker.example\r\nContent-Type: application/json\r\n"
        + f"Content-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode()
        + body,
    )
    assert status == 421
    assert await _state(app, FILLER) == state
    for name in (f"127.0.0.1:{port}", f"localhost:{port}", f"[::1]:{port}", "LOCALHOST."):
        status, answer = await _raw_http(
            port, f"GET /api/session HTTP/1.1\r\nHost: {name}\r\nConnection: close\r\n\r\n".encode()
        )
        assert status == 200, name
        assert f"uacell_{port}=" in answer
    status, _ = await _raw_http(port, b"GET / HTTP/1.0\r\n\r\n")
    assert status == 421  # no Host at all: no name the HMI is served under


async def test_host_names_are_compared_without_port_case_or_brackets():
    guard = HostGuard(lambda *a: None, names=["hmi.plant.example"])  # type: ignore[arg-type]  # an app never called
    assert host_name("HMI.Plant.Example:8443") == "hmi.plant.example"
    assert host_name("[::1]:8080") == "::1"
    assert guard.allows("hmi.plant.example:8080") and guard.allows("10.1.2.3:80") and guard.allows("localhost")
    assert not guard.allows("hmi.plant.example.attacker.example") and not guard.allows("") and not guard.allows("[x")


async def test_a_body_over_the_cap_is_refused_before_it_is_read_or_parsed(stack):
    _app, web = stack
    port = int(web.url.rsplit(":", 1)[1].strip("/"))
    b = Browser(web.url)
    await b.start()
    head = (
        f"POST /api/call HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nCookie: uacell_{port}={b.cookie()}\r\n"
        f"X-CSRF-Token: {b.csrf}\r\nContent-Type: application/json\r\nConnection: close\r\n"
    )
    # 200 MB announced, a few bytes sent: the answer comes at once, from the header alone.
    status, answer = await _raw_http(port, (head + "Content-Length: 200000000\r\n\r\n{").encode())
    assert status == 413 and f"larger than {MAX_BODY} bytes" in answer
    # No length announced: the chunks are counted as they arrive and refused past the cap.
    # (MAX_BODY + 1 bytes in all: the server has read everything when it answers, so no reset.)
    sizes = [1_000_000] * (MAX_BODY // 1_000_000) + [MAX_BODY % 1_000_000 + 1]
    chunks = b"".join(b"%x\r\n%s\r\n" % (n, b"x" * n) for n in sizes) + b"0\r\n\r\n"
    status, answer = await _raw_http(port, (head + "Transfer-Encoding: chunked\r\n\r\n").encode() + chunks)
    assert status == 413
    # Under the cap, chunked or not, the request reaches the route (here: refused as not JSON).
    small = b'{"key": "Filler1/MachineState/Reset", "args": [1'
    status, answer = await _raw_http(port, (head + f"Content-Length: {len(small)}\r\n\r\n").encode() + small)
    assert status == 400 and "must be JSON" in answer
    status, answer = await _raw_http(
        port, (head + "Transfer-Encoding: chunked\r\n\r\n").encode() + b"%x\r\n%s\r\n0\r\n\r\n" % (len(small), small)
    )
    assert status == 400 and "must be JSON" in answer


async def test_malformed_inputs_get_a_plain_4xx_and_change_nothing(stack):
    app, web = stack
    b = Browser(web.url)
    await b.start()
    state = await _state(app, FILLER)
    status, answer = await b.post("/api/call", {"key": "Filler1/SetUnitMode", "args": [1e30]})
    assert status == 400 and "outside -2147483648..2147483647 (Int32)" in answer["error"]
    deep = (
        json.dumps({"key": "Filler1/SetMachSpeed", "args": [60.0]})[:-1]
        + ', "x": '
        + "[" * 100_000
        + "]" * 100_000
        + "}"
    )
    port = int(web.url.rsplit(":", 1)[1].strip("/"))
    status, text = await _raw_http(
        port,
        (
            f"POST /api/call HTTP/1.1\r\nHost: 127.0.0.1\r\nCookie: uacell_{port}={b.cookie()}\r\n"
            f"X-CSRF-Token: {b.csrf}\r\nContent-Type: application/json\r\nConnection: close\r\n"
            f"Content-Length: {len(deep)}\r\n\r\n{deep}"
        ).encode(),
    )
    assert status == 400 and "nested too deeply" in text
    assert await _state(app, FILLER) == state


async def test_two_hmis_on_one_host_keep_their_own_sessions_in_one_browser(stack):
    """Browsers send a host's cookies to all its ports: each HMI's cookie has a name of its own."""
    app, web = stack
    other = await start_web(
        app.endpoint,
        app.data_dir,
        companions=app.companions,
        port=0,
        server_certificate=PkiPaths.in_data_dir(app.data_dir).cert,
    )
    try:
        jar = CookieJar()
        first, second = Browser(web.url), Browser(other.url)
        second.jar = jar
        second.opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(jar))
        first.jar = jar
        first.opener = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(jar))
        await first.start()
        assert (await first.login("otto"))[0] == 200
        await second.start()  # the other HMI's session: a cookie of its own name, in the same jar
        names = sorted(c.name for c in jar)
        assert names == sorted({web.web.cookie, other.web.cookie}) and web.web.cookie != other.web.cookie
        first_session = next(c.value for c in jar if c.name == web.web.cookie)
        status, info = await first.get("/api/session")
        assert status == 200 and info["user"] == "otto" and not info["fresh"]
        # The first HMI's cookie replayed to the second under the second's name is nobody's session there.
        replay = Browser(other.url)
        replay.opener.addheaders = [("Cookie", f"{other.web.cookie}={first_session}")]
        status, info = await replay.get("/api/session")
        assert status == 200 and info["fresh"] and info["user"] is None
    finally:
        await other.stop()
