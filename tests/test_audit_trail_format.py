"""The audit trail's lines are stable, documented JSON a SIEM can parse (docs/operations.md, "The
audit trail"): real lines of a server, written through a login, a session's open and close and
calls, each field of the documented JSON type; NodeIds in the standard string form."""

from __future__ import annotations

import datetime as dt
import json
import re
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import wait_until

from uacell.security.audit import audit_line
from uacell.security.users import UserStore
from uacell.server import UacellServer

module_loop = pytest.mark.asyncio(loop_scope="module")

PASSWORD = "pw-siem-check-1"
CTRL = "Robot1.Controllers.Controller1"
SO = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
NODE_ID = re.compile(r"^(ns=\d+;)?(i=\d+|s=.+|g=[0-9A-Fa-f-]{36}|b=[A-Za-z0-9+/=]*)$")
STATUS = re.compile(r"^(Good|Uncertain|Bad)[A-Za-z]*$")

# event -> field -> what its value is (docs/operations.md); "nodeid": the standard NodeId string
SCHEMA: dict[str, dict[str, Any]] = {
    "login": {
        "user": str, "session": "nodeid", "session_name": str, "application_uri": str, "address": str,
        "result": "status",
    },
    "session_open": {"session": "nodeid", "session_name": str, "user": str, "application_uri": str, "address": str},
    "session_close": {"session": "nodeid", "session_name": str, "user": str, "application_uri": str, "address": str},
    "call": {
        "user": str, "role": str, "session": "nodeid", "object": "nodeid", "method": str, "result": "status",
    },
}  # fmt: skip


def conforms(entry: dict[str, Any]) -> None:
    assert set(entry) >= {"time", "event"}
    assert dt.datetime.fromisoformat(entry["time"]).utcoffset() == dt.timedelta(0)
    fields = SCHEMA[entry["event"]]
    for name, kind in fields.items():
        assert name in entry, (name, entry)
        value = entry[name]
        if kind == "nodeid":
            assert isinstance(value, str) and NODE_ID.match(value), (name, value)
        elif kind == "status":
            assert isinstance(value, str) and STATUS.match(value), (name, value)
        else:
            assert isinstance(value, kind), (name, value)


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def app(tmp_path_factory: pytest.TempPathFactory):
    data = tmp_path_factory.mktemp("audit-format") / "data"
    UserStore.in_data_dir(data).add("siem", "operator", PASSWORD)
    server = await start_app(fast_config(data))
    yield server
    await server.stop()


def lines(app: UacellServer) -> list[dict[str, Any]]:
    path = app.data_dir / "audit.log"
    return [json.loads(line) for line in path.read_text().splitlines()] if path.exists() else []


@module_loop
async def test_audit_lines_of_a_session_parse_as_documented(app: UacellServer) -> None:
    client = Client(app.endpoint, timeout=30, watchdog_intervall=5.0)
    client.description = "siem-check"  # asyncua names the session "<description> Session<n>"
    client.application_uri = "urn:test:siem-check"
    client.set_user("siem")
    client.set_password(PASSWORD)
    await client.connect()
    try:
        ns = await client.get_namespace_index("urn:uacell:cell")
        node = client.get_node(ua.NodeId(SO, ns))
        await node.call_method(ua.NodeId(f"{SO}.GetReady", ns))
    finally:
        await client.disconnect()
    mine: list[dict[str, Any]] = []

    def arrived() -> bool:
        logins = [e for e in lines(app) if e["event"] == "login" and e.get("user") == "siem"]
        session = logins[-1]["session"] if logins else None
        mine[:] = [e for e in lines(app) if e.get("session") == session]
        return {"login", "session_open", "call", "session_close"} <= {e["event"] for e in mine}

    await wait_until(arrived, timeout=30)
    for entry in mine:
        conforms(entry)
    by_event = {e["event"]: e for e in mine}
    session = by_event["session_open"]["session"]
    assert all(e["session"] == session for e in mine), mine  # one session, one text for it
    for event in ("session_open", "login", "session_close"):  # the name the client gave, a string
        assert re.fullmatch(r"siem-check Session\d+", by_event[event]["session_name"]), by_event[event]
    assert by_event["session_open"]["user"] == "anonymous"  # opened before the login activates it
    assert by_event["session_close"]["user"] == "siem" and by_event["call"]["role"] == "operator"
    assert by_event["login"]["address"] == "127.0.0.1" and by_event["login"]["result"] == "Good"
    call = by_event["call"]
    assert (call["object"], call["method"], call["result"]) == (f"ns={ns};s={SO}", "GetReady", "Good")


def test_values_without_a_json_type_are_written_in_their_documented_form() -> None:
    """A NodeId of each kind as its standard string, a status code by its name, a tuple as a list."""
    guid = ua.NodeId(ua.uuid.UUID("72962b91-fa75-4ae6-8d28-b404dc7daf63"), 1)
    entry = json.loads(
        audit_line(
            0.0,
            "call",
            {
                "session": ua.NodeId(11, 1),
                "object": ua.NodeId("Robot1.Controllers", 6),
                "guid": guid,
                "result": ua.StatusCode(ua.StatusCodes.BadUserAccessDenied),
                "pair": ("127.0.0.1", 4840),
            },
        )
    )
    assert entry["time"] == "1970-01-01T00:00:00.000+00:00" and entry["event"] == "call"
    assert entry["session"] == "ns=1;i=11"
    assert entry["object"] == "ns=6;s=Robot1.Controllers"
    assert entry["guid"] == "ns=1;g=72962b91-fa75-4ae6-8d28-b404dc7daf63"
    assert entry["result"] == "BadUserAccessDenied"
    assert entry["pair"] == ["127.0.0.1", 4840]
