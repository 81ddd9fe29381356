"""node-opcua connected to `uacell serve` with a trusted certificate while `uacell cert remove` takes it out
of the trust list from another process (decision 100): its channel is closed, and a new one is refused;
its token renewals are verified and audited, and its own reconnection does not bring its session back
(decision 104)."""

from __future__ import annotations

import asyncio
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import run_node, start_serve
from cryptography import x509
from cryptography.hazmat.primitives import serialization
from helpers import Collector, wait_until
from test_security_interop import node_client

from uacell.core.roles import Role
from uacell.security.users import UserStore

pytestmark = [pytest.mark.interop, pytest.mark.asyncio]


PASSWORD = "renewal-audit-pw-1"


def trusted_node_client(tmp_path: Path, data: Path) -> list[str]:
    """node_client's arguments; its certificate also as ``node.der``, for ``uacell cert remove``."""
    client = node_client(tmp_path, data)
    der = x509.load_pem_x509_certificate(Path(client[0]).read_bytes()).public_bytes(serialization.Encoding.DER)
    (tmp_path / "node.der").write_bytes(der)
    return client


async def remove_certificate(tmp_path: Path, data: Path) -> None:
    """``uacell cert remove node.der`` from another process, as an administrator runs it."""
    removed = await asyncio.to_thread(
        subprocess.run,
        [sys.executable, "-m", "uacell", "cert", "remove", str(tmp_path / "node.der"), "--data-dir", str(data)],
        capture_output=True,
        text=True,
        timeout=60,
        check=False,
    )
    assert removed.returncode == 0 and "removed" in removed.stdout, removed.stderr


async def test_node_opcua_channel_closes_when_its_certificate_is_removed(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    client, ready = trusted_node_client(tmp_path, data), tmp_path / "ready"
    sp = start_serve(data)
    try:
        outcome = asyncio.create_task(asyncio.to_thread(run_node, "trust_removed.js", sp.endpoint, *client, str(ready)))
        await wait_until(ready.exists, timeout=60, step=0.05)
        await remove_certificate(tmp_path, data)
        out = await asyncio.wait_for(outcome, 90)
    finally:
        sp.stop()
    assert out == {"before": 0, "lost": True, "reconnected": False}, out  # 0: ServerState Running


async def test_node_opcua_renews_its_token_and_cannot_reconnect_once_removed(tmp_path: Path) -> None:
    """node-opcua's renewals (a 2 s token) pass the check decision 104 makes at each and fire
    AuditOpenSecureChannelEvents with RequestType Renew for its channel; removed, it stays out, though its
    subscription keeps its session alive for a reconnection."""
    data = tmp_path / "data"
    data.mkdir()
    UserStore(data / "users.toml").add("ada", Role.ADMIN, PASSWORD)
    client, ready = trusted_node_client(tmp_path, data), tmp_path / "ready"
    sp = start_serve(data)
    admin = Client(sp.endpoint, timeout=20)
    admin.set_user("ada")
    admin.set_password(PASSWORD)
    try:
        await admin.connect()
        seen = Collector()
        subscription = await admin.create_subscription(0, seen)
        await subscription.subscribe_events(
            admin.nodes.server, [admin.get_node(ua.NodeId(ua.ObjectIds.AuditOpenSecureChannelEventType))]
        )
        outcome = asyncio.create_task(
            asyncio.to_thread(run_node, "renew_and_return.js", sp.endpoint, *client, str(ready))
        )
        await wait_until(ready.exists, timeout=60, step=0.05)
        channel = ready.read_text()

        def renewals() -> list[Any]:
            renew = ua.SecurityTokenRequestType.Renew
            return [e for e in seen.events if e.RequestType == renew and e.SecureChannelId == channel]

        await wait_until(lambda: len(renewals()) >= 2, timeout=20, step=0.05)
        while_trusted = renewals()
        await remove_certificate(tmp_path, data)
        out = await asyncio.wait_for(outcome, 120)
    finally:
        await admin.disconnect()
        sp.stop()
    assert out["reads"] >= 10 and out["failed"] == 0, out  # every read over 5 s, across its renewals
    assert out["renewed"] >= 2, out
    assert all(e.Status is True for e in while_trusted), while_trusted
    # a renewal between the removal and the watch's next look is refused: a certificate trusted by itself
    # and taken out is told Bad_CertificateUntrusted (decision 92's table); one before the removal passes
    codes = {e.StatusCodeId.value for e in renewals()}
    assert codes <= {ua.StatusCodes.Good, ua.StatusCodes.BadCertificateUntrusted}, codes
    assert out["lost"] is True, out
    assert out["after"] != "Good", out  # neither its session on a new channel nor a new session
