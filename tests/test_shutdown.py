"""A stop announced to connected clients (OPC 10000-5 12.10; decision 85): ServerStatus.State Shutdown,
SecondsTillShutdown counting down and ShutdownReason, seen by an asyncua client's subscription, the
server serving meanwhile; the stop goes on when the last client has gone or the delay has passed."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import raw_call, wait_until

from uacell.config import Config, validate
from uacell.core.errors import ConfigError
from uacell.server import UacellServer
from uacell.services.shutdown import REASON, announce_shutdown

pytestmark = pytest.mark.asyncio

STATE = ua.NodeId(ua.ObjectIds.Server_ServerStatus_State)
SECONDS = ua.NodeId(ua.ObjectIds.Server_ServerStatus_SecondsTillShutdown)
REASON_NODE = ua.NodeId(ua.ObjectIds.Server_ServerStatus_ShutdownReason)
STATUS = ua.NodeId(ua.ObjectIds.Server_ServerStatus)


class Seen:
    """Every value a subscription delivered, per node."""

    def __init__(self) -> None:
        self.values: dict[ua.NodeId, list[Any]] = {}

    def datachange_notification(self, node: Any, value: Any, data: Any) -> None:
        self.values.setdefault(node.nodeid, []).append(value)

    def of(self, nodeid: ua.NodeId) -> list[Any]:
        return self.values.get(nodeid, [])


async def served(tmp_path: Path, delay: float) -> UacellServer:
    config = fast_config(tmp_path / "data")
    config.server.shutdown_delay = delay
    return await start_app(config)


async def watching(app: UacellServer) -> tuple[Client, Seen]:
    client = Client(app.endpoint, timeout=30)
    await client.connect()
    seen = Seen()
    sub = await client.create_subscription(0, seen)
    nodes = [client.get_node(n) for n in (STATE, SECONDS, REASON_NODE, STATUS)]
    await sub.subscribe_data_change(nodes, queuesize=10)
    await wait_until(lambda: ua.ServerState.Running in seen.of(STATE))
    return client, seen


async def test_connected_clients_see_the_stop_coming_and_may_leave_first(tmp_path: Path) -> None:
    app = await served(tmp_path, 30.0)
    client, seen = await watching(app)
    stopping = asyncio.create_task(app.stop())
    try:
        # three monitored items, each notified on its own: the state, and then when and why (the server
        # writes the state last, but a client may not count on the order of different items' changes)
        reason = ua.LocalizedText(REASON, "en")
        await wait_until(lambda: ua.ServerState.Shutdown in seen.of(STATE), timeout=20)
        await wait_until(lambda: reason in seen.of(REASON_NODE) and 30 in seen.of(SECONDS), timeout=20)
        assert seen.of(SECONDS)[1] == 30  # whole seconds, rounded up: the first value after 0
        await wait_until(lambda: any(s.State == ua.ServerState.Shutdown for s in seen.of(STATUS)), timeout=20)
        status = [s for s in seen.of(STATUS) if s.State == ua.ServerState.Shutdown][-1]
        assert status.ShutdownReason.Text == REASON and 0 < status.SecondsTillShutdown <= 30
        # still served meanwhile: a read, and a call with its effect
        assert await client.get_node(STATE).read_value() == ua.ServerState.Shutdown
        ns = await client.get_namespace_index("urn:uacell:cell")
        speed = ua.Variant(42.0, ua.VariantType.Float)
        result = await raw_call(client, ua.NodeId("Filler1", ns), ua.NodeId("Filler1.SetMachSpeed", ns), speed)
        assert result.StatusCode.is_good()
        assert await client.get_node(ua.NodeId("Filler1.Status.MachSpeed", ns)).read_value() == 42.0
        assert not stopping.done()
        await client.disconnect()  # the last client gone: the stop goes on, not waiting out its 30 s
        await asyncio.wait_for(stopping, timeout=15)
    finally:
        if not stopping.done():
            stopping.cancel()
            await client.disconnect()
            await app.stop()


async def test_the_countdown_reaches_zero_for_a_client_that_stays(tmp_path: Path) -> None:
    app = await served(tmp_path, 2.0)
    client, seen = await watching(app)
    hooks = list(app.security.on_session_closed)
    try:
        waited = await announce_shutdown(app.server, 2.0, app.security.on_session_closed)
        assert waited >= 2.0
        await wait_until(lambda: seen.of(SECONDS)[1:][-1:] == [0], timeout=20)  # the countdown's end
        assert seen.of(SECONDS)[0] == 0  # while running (asyncua left it null)
        assert seen.of(SECONDS)[1:] == [2, 1, 0]  # each whole second once, in order
        assert app.security.on_session_closed == hooks  # its hook is gone again
    finally:
        await client.disconnect()
        await app.stop()


async def test_without_clients_nothing_is_announced_and_nobody_waits(tmp_path: Path) -> None:
    app = await served(tmp_path, 30.0)
    try:
        hooks = list(app.security.on_session_closed)
        assert await announce_shutdown(app.server, 30.0, app.security.on_session_closed) == 0.0
        assert app.security.on_session_closed == hooks
        assert await app.server.get_node(STATE).read_value() == ua.ServerState.Running
    finally:
        await asyncio.wait_for(app.stop(), timeout=15)  # 30 s of delay, no session: no wait


@pytest.mark.parametrize("delay", [-1.0, 61.0])
async def test_the_delay_is_bounded(tmp_path: Path, delay: float) -> None:
    config = Config()
    config.server.data_dir = tmp_path
    config.server.shutdown_delay = delay
    with pytest.raises(ConfigError, match=r"\[server\] shutdown_delay: must be 0 to 60 seconds"):
        validate(config)
