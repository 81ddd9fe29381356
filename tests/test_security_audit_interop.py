"""node-opcua reads the audit events of sessions from `uacell serve` (OPC 10000-4 6.5.6, decision 94):
an admin's subscription to the Server object gets the CreateSession, ActivateSession and CloseSession of
another client's session, and the refused ActivateSession of a wrong password, without the password."""

from __future__ import annotations

from pathlib import Path

import pytest
from conftest import run_node, start_serve

from uacell.core.roles import Role
from uacell.security.users import UserStore

pytestmark = pytest.mark.interop

PASSWORD = "audit-interop-pw-1"


def test_node_opcua_reads_the_session_audit_events(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    users = UserStore(data / "users.toml")
    users.add("ada", Role.ADMIN, PASSWORD)
    users.add("otto", Role.OPERATOR, PASSWORD)
    sp = start_serve(data)
    try:
        out = run_node("session_audit.js", sp.endpoint, "ada", PASSWORD, "otto")
    finally:
        sp.stop()
    other = [e for e in out["events"] if e["sessionId"] == out["otherId"]]
    assert [(e["type"], e["sourceName"], e["status"]) for e in other] == [
        ("ns=0;i=2071", "Session/CreateSession", True),
        ("ns=0;i=2075", "Session/ActivateSession", True),
        ("ns=0;i=2069", "Session/CloseSession", True),
    ]
    created, activated, _closed = other
    assert created["clientUserId"] == "System/CreateSession"
    assert activated["token"]["kind"] == "AnonymousIdentityToken"
    assert created["channel"] and created["channel"] == activated["channel"]
    assert "BadUserAccessDenied" in out["refused"]
    [refused] = [e for e in out["events"] if e["sourceName"] == "Session/ActivateSession" and e["status"] is False]
    assert refused["clientUserId"] == "otto"
    assert refused["token"] == {"kind": "UserNameIdentityToken", "userName": "otto", "password": None}
