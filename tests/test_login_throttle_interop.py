"""node-opcua against `uacell serve`'s login throttle (issue 39 point 2): every throttled login is
answered, Good or Bad_UserAccessDenied, before the connection's activation deadline; the right
password after the failures gets in. The deadline is scaled down from 30 s to 6 s."""

from __future__ import annotations

import pytest
from conftest import run_node, start_serve
from test_security_interop import node_client

from uacell.core.roles import Role
from uacell.security.users import UserStore

pytestmark = pytest.mark.interop

WINDOW = 6.0


def test_node_opcua_logins_under_the_throttle_are_all_answered_within_the_deadline(tmp_path):
    data = tmp_path / "data"
    data.mkdir()
    UserStore.in_data_dir(data).add("tilda", Role.OPERATOR, "t1lda-secret")
    client = node_client(tmp_path, data)
    config = tmp_path / "uacell.toml"
    config.write_text(
        f"[limits]\nactivation_timeout = {WINDOW}\nhandshake_timeout = 1.0\nlogin_base_delay = 1.5\n"
        "login_max_delay = 3.0\nlogin_free_failures = 1\nlogin_free_failures_per_user = 1\n"
    )
    sp = start_serve(data, "--config", str(config))
    try:
        out = run_node(
            "login_throttle.js",
            sp.endpoint,
            *client,
            "tilda",
            "t1lda-secret",
            "6",
            timeout=180,
        )
    finally:
        sp.stop()
    attempts = out["attempts"]
    assert [a["answer"] for a in attempts] == ["BadUserAccessDenied"] * 6 + ["Good"], attempts
    assert all(a["seconds"] < WINDOW for a in attempts), attempts
    assert any(a["seconds"] > 1.0 for a in attempts[1:]), attempts  # the throttle did slow them down
