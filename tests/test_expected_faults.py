"""Faults the docs call expected and handled log no ERROR and no traceback: one WARNING line says each
(a PLC or a robot controller killed), nothing above INFO for a client killed in the middle of a call
or a web client gone in the middle of a request;
a genuine bug in the same places still logs its ERROR with the traceback.

Every counterpart is real and its own process: node-opcua's PackTags PLC (interop/plc_packtags.js),
the Modbus PackTags PLC and the Modbus robot controller (pymodbus servers, uacell.gateway.examples),
an asyncua client killed with SIGKILL. The log is the one uacell writes (caplog at INFO, asyncua's
loggers at uacell's own level), grepped after the fault was handled."""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import signal
import socket
import struct
import subprocess
import sys
import urllib.request
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, Server, ua
from conftest import fast_config, serving, start_app
from gateway_plcs import ModbusPLC
from helpers import cell_executable, free_port, until, wait_until
from test_gateway_packml import PLC as PackTagsPLC
from test_gateway_robot import PLC as RobotController
from test_gateway_robot import cell_text as robot_cell

from uacell.config import load_cell
from uacell.core.cell_file import builtin_cell_path
from uacell.gateway import modbus, opcua_link, packml_modbus, packml_opcua
from uacell.security.pki import PkiPaths
from uacell.server import UacellServer
from uacell.web.hosting import start_web, trust_hmi

pytestmark = pytest.mark.interop
RESET = "Capper.BaseStateMachine.MachineState.Reset"
SESSION_LOG = "asyncua.client.ua_session.UaSession"


def above_info(caplog: pytest.LogCaptureFixture) -> list[tuple[str, str, str]]:
    """(level, logger, message) of every WARNING and ERROR record."""
    return [(r.levelname, r.name, r.getMessage()) for r in caplog.records if r.levelno >= logging.WARNING]


def assert_quiet(caplog: pytest.LogCaptureFixture, warnings: list[str]) -> None:
    """No ERROR, no traceback anywhere in the log, and exactly ``warnings`` (messages) as WARNINGs."""
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert not errors, [(r.name, r.getMessage()) for r in errors]
    assert not [r for r in caplog.records if r.exc_info], "a record carries a traceback"
    assert "Traceback" not in caplog.text
    # uacell serves with asyncua's loggers at ERROR: a WARNING of asyncua's (seen here only when a test
    # lowers its session logger) is not in the log
    said = [m for level, name, m in above_info(caplog) if level == "WARNING" and not name.startswith("asyncua")]
    assert said == warnings, above_info(caplog)


def capture(caplog: pytest.LogCaptureFixture, asyncua_session: bool = False) -> None:
    """From now on: the log at INFO, as uacell logs (asyncua's loggers keep uacell's ERROR), and with
    ``asyncua_session`` asyncua's session logger at DEBUG, where the demoted records show what it saw."""
    caplog.clear()
    caplog.set_level(logging.INFO)
    if asyncua_session:
        caplog.set_level(logging.DEBUG, logger=SESSION_LOG)  # restored after the test


@pytest.fixture
async def packtags_plc() -> AsyncIterator[PackTagsPLC]:
    p = PackTagsPLC(["Capper"])
    p.start()
    try:
        yield p
    finally:
        p.kill()


@contextlib.asynccontextmanager
async def serve_cell(tmp_path: Path, text: str) -> AsyncIterator[tuple[UacellServer, Client]]:
    path = tmp_path / "cell.toml"
    path.write_text(text)
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as served:
        yield served


def fail(proc: subprocess.Popen[str] | subprocess.Popen[bytes] | None, fault: str) -> None:
    """``killed``: SIGKILL, its port closes; ``frozen``: SIGSTOP, its connections stay open and nothing
    answers (the fixtures kill it in the end)."""
    assert proc is not None
    proc.send_signal(signal.SIGKILL if fault == "killed" else signal.SIGSTOP)
    if fault == "killed":
        proc.wait(10)


@pytest.mark.parametrize("fault", ["killed", "frozen"])
async def test_a_killed_opcua_plc_is_one_warning_and_no_traceback(
    tmp_path: Path, packtags_plc: PackTagsPLC, caplog: pytest.LogCaptureFixture, fault: str
) -> None:
    text = builtin_cell_path("packtags-unit").read_text().replace(":4841/", f":{packtags_plc.port}/")
    async with serve_cell(tmp_path, text) as (_app, client):
        await until(lambda: cell_executable(client, RESET), True)
        (link,) = packml_opcua.POOL.values()
        capture(caplog, asyncua_session=True)
        fail(packtags_plc.proc, fault)
        await until(lambda: cell_executable(client, RESET), False)  # CommunicationLost: handled
        before = link.attempts
        await wait_until(lambda: link.attempts >= before + 3, timeout=30)  # and reconnection tried
        assert_quiet(caplog, [f"the PLC at {packtags_plc.endpoint}: lost the connection (retrying)"])
        if fault == "frozen":
            return
        # asyncua's client did see it, and says so at DEBUG only, in one line
        said = [r for r in caplog.records if r.name == SESSION_LOG and "Publish iteration crashed" in r.getMessage()]
        assert said and {r.levelno for r in said} == {logging.DEBUG}, said
        assert "ConnectionError" in said[0].getMessage() and "an expected fault" in said[0].getMessage()
        # the reconnection attempts that meet a closed port are INFO, said once
        refused = [r for r in caplog.records if "(retrying)" in r.getMessage() and r.levelno == logging.INFO]
        assert len(refused) == 1, [r.getMessage() for r in refused]


@pytest.mark.parametrize("fault", ["killed", "frozen"])
async def test_a_killed_modbus_plc_is_one_warning_and_no_traceback(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, fault: str
) -> None:
    plc = ModbusPLC()
    plc.start()
    try:
        text = builtin_cell_path("modbus-packtags").read_text().replace("port = 5021", f"port = {plc.port}")
        async with serve_cell(tmp_path, text) as (_app, client):
            await until(lambda: cell_executable(client, RESET), True)
            (link,) = packml_modbus.POOL.values()  # the two units share it
            capture(caplog)
            fail(plc.proc, fault)
            for unit in ("Capper", "Labeler"):
                await until(lambda u=unit: cell_executable(client, f"{u}.BaseStateMachine.MachineState.Reset"), False)
            before = link.attempts
            await wait_until(lambda: link.attempts >= before + 3, timeout=30)
            assert_quiet(caplog, [f"the PLC at modbus://127.0.0.1:{plc.port}: lost the connection (retrying)"])
    finally:
        plc.kill()


@pytest.mark.parametrize("fault", ["killed", "frozen"])
async def test_a_killed_robot_controller_is_one_warning_and_no_traceback(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, fault: str
) -> None:
    controller = RobotController(free_port(), 1.0)
    controller.start()
    try:
        await controller.io()  # listening
        async with serve_cell(tmp_path, robot_cell(controller.port)) as (_app, client):
            conn = modbus.SHARED.get_open(("127.0.0.1", controller.port))
            assert conn is not None  # the cell's link to the controller
            ns = await client.get_namespace_index("urn:uacell:cell")
            lost = client.get_node(
                ua.NodeId(
                    "Palletizer.Controllers.Cabinet.SystemOperation.Conditions.CommunicationLost.ActiveState.Id", ns
                )
            )
            capture(caplog)
            fail(controller.proc, fault)
            await until(lost.read_value, True)
            before = conn.attempts + conn.unanswered
            await wait_until(lambda: conn.attempts + conn.unanswered >= before + 3, timeout=30)  # and it retried
            endpoint = f"modbus://127.0.0.1:{controller.port}"
            assert_quiet(caplog, [f"Palletizer.Controllers.Cabinet: lost the controller at {endpoint} (retrying)"])
    finally:
        controller.kill()
        for c in controller.clients:
            c.close()


CLIENT = """
import asyncio, sys
from asyncua import Client, ua

async def main():
    async with Client(sys.argv[1], timeout=30) as client:
        ns = await client.get_namespace_index("urn:uacell:cell")
        obj = "Capper.BaseStateMachine.MachineState"
        print("calling", flush=True)
        await client.get_node(ua.NodeId(obj, ns)).call_method(ua.NodeId(obj + ".Reset", ns))

asyncio.run(main())
"""


async def test_a_client_killed_in_the_middle_of_a_call_logs_nothing_above_info(
    tmp_path: Path, packtags_plc: PackTagsPLC, caplog: pytest.LogCaptureFixture
) -> None:
    """Reset waits for the PLC (frozen: it never takes the request) while its client is killed; the
    call ends with its timeout and its answer goes nowhere, quietly."""
    text = builtin_cell_path("packtags-unit").read_text().replace(":4841/", f":{packtags_plc.port}/")
    async with serve_cell(tmp_path, text) as (app, client):
        await until(lambda: cell_executable(client, RESET), True)
        async with Client(packtags_plc.endpoint, timeout=10, watchdog_intervall=30.0) as plc_client:
            packtags_plc.client = plc_client
            await packtags_plc.set("Capper", "Sim.Frozen", True, ua.VariantType.Boolean)
            capture(caplog)
            proc = subprocess.Popen(
                [sys.executable, "-c", CLIENT, app.endpoint],
                stdout=subprocess.PIPE,
                stderr=subprocess.DEVNULL,
                text=True,
            )
            try:
                await until(lambda: packtags_plc.tag("Capper", "Command.CmdChangeRequest"), True)  # in flight
                os.kill(proc.pid, signal.SIGKILL)
                await asyncio.to_thread(proc.wait, 10)
                # the call ends (its request taken back from the PLC) and is audited once it is answered
                await until(lambda: packtags_plc.tag("Capper", "Command.CmdChangeRequest"), False)

                def answered() -> bool:
                    return any(r.name == "uacell.audit" and r.getMessage() == "call" for r in caplog.records)

                await wait_until(answered, timeout=30)
            finally:
                proc.kill()
                proc.wait(10)
                assert proc.stdout is not None
                proc.stdout.close()
            packtags_plc.client = None
        assert_quiet(caplog, [])
        assert await cell_executable(client, RESET)  # and the server goes on serving


def test_a_genuine_fault_in_the_same_loggers_keeps_its_error_and_traceback(caplog: pytest.LogCaptureFixture) -> None:
    """The filters take the expected faults only: an exception that is not a lost connection, logged
    where asyncua's client and pymodbus log theirs, stays an ERROR with its traceback."""
    opcua_link.quiet_client()
    modbus.quiet_pymodbus()
    caplog.set_level(logging.DEBUG)
    caplog.set_level(logging.DEBUG, logger="asyncua")
    session = logging.getLogger(SESSION_LOG)
    for exc in (
        ConnectionError("Connection is closed"),
        KeyError("SubscriptionId"),
        PermissionError(13, "Permission denied"),
    ):
        try:
            raise exc
        except Exception:
            session.exception("Publish iteration crashed; retrying in 1s")
    closing = logging.getLogger("asyncua.client.client")
    try:
        raise ua.UaStatusCodeError(ua.StatusCodes.BadSecureChannelClosed)
    except ua.UaError:
        closing.exception("close_secure_channel raised during disconnect; continuing teardown")
    try:
        raise ua.UaStatusCodeError(ua.StatusCodes.BadNodeIdUnknown)
    except ua.UaError:
        closing.exception("close_session raised during disconnect; continuing teardown")
    pymodbus_log = logging.getLogger("pymodbus.logging")
    pymodbus_log.warning("Failed to connect [Errno 111] Connect call failed ('127.0.0.1', 502)")
    pymodbus_log.warning("Repeating....")
    pymodbus_log.error("Invalid Modbus protocol id: 7")
    pymodbus_log.error("Repeating....")
    kept = [(r.levelname, r.getMessage(), type(r.exc_info[1]).__name__ if r.exc_info else None) for r in caplog.records]
    assert [k for k in kept if k[0] != "DEBUG"] == [
        ("ERROR", "Publish iteration crashed; retrying in 1s", "KeyError"),
        ("ERROR", "Publish iteration crashed; retrying in 1s", "PermissionError"),
        ("ERROR", "close_session raised during disconnect; continuing teardown", "BadNodeIdUnknown"),
        ("ERROR", "Invalid Modbus protocol id: 7", None),
        ("ERROR", "Repeating....", None),
    ]
    quiet = [m for level, m, _ in kept if level == "DEBUG"]
    assert len(quiet) == 4, quiet  # the lost connections: one line each, without a traceback
    assert quiet[0].startswith("Publish iteration crashed; retrying in 1s (ConnectionError: Connection is closed)")
    assert "BadSecureChannelClosed" in quiet[1] and quiet[2].startswith("Failed to connect") and "Repeating" in quiet[3]
    assert all(not r.exc_info for r in caplog.records if r.levelno == logging.DEBUG)


async def _http(port: int, request: bytes, until_data: bool) -> None:
    """Send ``request`` and drop the connection (RST) at once, or once the answer's first bytes came."""
    reader, writer = await asyncio.open_connection("127.0.0.1", port)
    writer.write(request)
    await writer.drain()
    if until_data:
        await asyncio.wait_for(reader.read(1), 30)
    sock = writer.get_extra_info("socket")
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    writer.transport.abort()


async def test_a_web_client_gone_in_the_middle_of_a_request_logs_nothing_above_info(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """A page's event stream dropped, a history request and a call dropped before their answer: the HMI
    lets them go (the stream's end is seen at its next write) and logs nothing above INFO."""
    data = tmp_path / "data"
    app = await start_app(fast_config(data))
    trust_hmi(data)
    web = await start_web(
        app.endpoint, data, companions=app.companions, port=0, server_certificate=PkiPaths.in_data_dir(data).cert
    )
    try:
        port = int(web.url.rstrip("/").rsplit(":", 1)[1])

        def open_session() -> tuple[str, str]:
            with urllib.request.urlopen(web.url.rstrip("/") + "/api/session", timeout=60) as res:
                return res.headers["Set-Cookie"].split(";", 1)[0], json.loads(res.read())["csrf"]

        cookie, csrf = await asyncio.to_thread(open_session)
        (session,) = web.web.sessions.values()
        capture(caplog)
        head = f"Host: 127.0.0.1:{port}\r\nCookie: {cookie}\r\n"
        await _http(port, f"GET /api/events HTTP/1.1\r\n{head}\r\n".encode(), until_data=True)
        await _http(port, f"GET /api/history?hours=8 HTTP/1.1\r\n{head}\r\n".encode(), until_data=False)
        body = json.dumps({"key": "Filler1/SetMachSpeed", "args": [70.0]}).encode()
        call = f"POST /api/call HTTP/1.1\r\n{head}X-CSRF-Token: {csrf}\r\nContent-Type: application/json\r\n"
        await _http(port, call.encode() + f"Content-Length: {len(body)}\r\n\r\n".encode() + body, until_data=False)
        async with Client(app.endpoint, timeout=30) as client:  # changes the stream has to write
            ns = await client.get_namespace_index("urn:uacell:cell")
            speed = ua.Variant(80.0, ua.VariantType.Float)
            obj = client.get_node(ua.NodeId("Filler1", ns))
            deadline = asyncio.get_running_loop().time() + 60
            while session.streams:
                assert asyncio.get_running_loop().time() < deadline, "the HMI never noticed the stream went"
                await obj.call_method(ua.NodeId("Filler1.SetMachSpeed", ns), speed)
                await asyncio.sleep(0.2)
        await wait_until(lambda: any(r.name == "uacell.audit" and r.getMessage() == "call" for r in caplog.records))
        assert_quiet(caplog, [])
    finally:
        await web.stop()
        await app.stop()


class _Broken(dict[Any, str]):
    """A lookup that fails the way a bug would (not a lost connection)."""

    def get(self, key: Any, default: Any = None) -> str:
        raise KeyError(key)


async def test_a_bug_under_asyncua_s_client_still_logs_its_error_and_traceback(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """A real PLC link to an asyncua server whose subscription handler breaks: asyncua's client logs
    "Exception calling subscription handler" at ERROR with the traceback, through the filter."""
    server = Server()
    await server.init()
    port = free_port()
    server.set_endpoint(f"opc.tcp://127.0.0.1:{port}/")
    ns = await server.register_namespace("urn:test:plc")
    tag = await server.nodes.objects.add_variable(ua.NodeId("Count", ns), "Count", ua.Variant(0, ua.VariantType.Int32))
    link = opcua_link.PlcLink(opcua_link.LinkOptions(f"opc.tcp://127.0.0.1:{port}/"))
    seen: list[Any] = []
    async with server:
        await link.watch([f"ns={ns};s=Count"], lambda _a, v: seen.append(v), lambda _c: None)
        link.start()
        try:
            assert await link.wait_connected(30)
            caplog.set_level(logging.INFO)
            link._address_of = _Broken()  # the handler now fails on every data change
            await tag.write_value(ua.Variant(1, ua.VariantType.Int32))

            def reported() -> bool:
                return any("Exception calling subscription handler" in r.getMessage() for r in caplog.records)

            await wait_until(reported, timeout=30)
        finally:
            await link.close()
    (bug,) = [r for r in caplog.records if "Exception calling subscription handler" in r.getMessage()]
    assert bug.levelno == logging.ERROR and bug.exc_info is not None and isinstance(bug.exc_info[1], KeyError)
    assert bug.name == "asyncua.common.subscription"


async def test_a_plc_that_stalls_for_less_than_the_link_timeout_keeps_its_link(packtags_plc: PackTagsPLC) -> None:
    """node-opcua's PLC frozen (SIGSTOP) for 2.5 s, then going on, under a link whose timeout is 5 s: the
    link stays connected and never reconnects (asyncua's own health probe would give up after 1 s).
    The timeout is the driver setting's (docs/equipment.md, ``timeout``).
    The make-test flake of 2026-11-28: a PLC link lost on a loaded machine."""
    link = opcua_link.PlcLink(opcua_link.link_options("Capper", {"endpoint": packtags_plc.endpoint, "timeout": 5}))
    tag = "ns=1;s=Capper.PackTags.Status.StateCurrent"
    states: list[bool] = []
    await link.watch([tag], lambda _a, _v: None, states.append)
    link.start()
    try:
        assert await link.wait_connected(30)
        assert packtags_plc.proc is not None
        packtags_plc.proc.send_signal(signal.SIGSTOP)
        try:
            await asyncio.sleep(2.5)  # the stall itself (the fault), not a wait for a result
        finally:
            packtags_plc.proc.send_signal(signal.SIGCONT)
        assert isinstance(await link.read(tag), int)
        assert link.connected and link.attempts == 0 and False not in states, (states, link.attempts)
    finally:
        await link.close()
