"""node-opcua logged in as a user of `uacell serve` while `uacell user passwd` changes that user's password
(decision 99): the open session goes on as anonymous, and activating it again with the new password gives
the user back."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from conftest import run_node, start_serve
from helpers import add_user, wait_until
from test_security_interop import node_client

pytestmark = [pytest.mark.interop, pytest.mark.asyncio]


async def test_node_opcua_session_loses_a_user_whose_password_was_changed(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    add_user(data, "tilda", "--role", "engineer", password="t1lda-secret")
    client = node_client(tmp_path, data)
    ready, new_password = tmp_path / "ready", tmp_path / "new-password"
    new_password.write_text("t1lda-secret-2")
    sp = start_serve(data)
    try:
        roles = asyncio.create_task(
            asyncio.to_thread(
                run_node,
                "identity_revoked.js",
                sp.endpoint,
                *client,
                "tilda",
                "t1lda-secret",
                str(ready),
                str(new_password),
            )
        )
        await wait_until(ready.exists, timeout=60, step=0.05)
        await asyncio.to_thread(add_user, data, "tilda", password="t1lda-secret-2", command="passwd")
        out = await asyncio.wait_for(roles, 60)
    finally:
        sp.stop()
    # anonymous on loopback is operator; the new password gives the engineer back on the same session
    # and Server/CurrentUser (decision 103) says whose the session is at each moment
    assert out == {
        "before": "engineer",
        "after": "operator",
        "again": "engineer",
        "users": ["tilda", "", "tilda"],
    }, out
