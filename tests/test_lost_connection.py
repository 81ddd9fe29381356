"""A session with a subscription outlives its connection (OPC 10000-4 6.7: "Subscriptions ... are not
dependent on the lifetime of the Session's transport"; 5.6.3.1: the client activates the session again on
a new secure channel), through `uacell serve` as deployed (its own process, on uvloop) and a real asyncua
client that loses its connection without closing anything, as a pulled cable does.

Before decision 105 the subscription's next publication answered a Publish request the lost connection
had left waiting, on the closed transport: uvloop refused the write, asyncua logged "Exception in
subscription loop" at ERROR and the loop ended, so the session, moved to a new channel, was never
published again; and what changed meanwhile was taken from the queue for a message nobody could get."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import start_serve
from helpers import call_path, session_on_new_channel, wait_until

pytestmark = pytest.mark.asyncio

CELL = "urn:uacell:cell"


class Seen:
    def __init__(self) -> None:
        self.values: list[Any] = []

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.values.append(val)

    def status_change_notification(self, status: Any) -> None:
        pass


async def test_a_subscription_keeps_what_changed_while_its_connection_was_lost(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    sp = start_serve(data)
    second: Client | None = None
    try:
        first = Client(sp.endpoint, timeout=20)
        await first.connect()
        speed = first.get_node(ua.NodeId("Filler1.Status.MachSpeed", await first.get_namespace_index(CELL)))
        seen = Seen()
        subscription = await first.create_subscription(50, seen)
        await subscription.subscribe_data_change(speed)
        await wait_until(lambda: len(seen.values) >= 1, timeout=20, step=0.05)  # its Publish requests wait
        token, nonce = first.uaclient.protocol.authentication_token, first._server_nonce
        first.disconnect_socket()  # the cable: no CloseSession, no CloseSecureChannel
        async with Client(sp.endpoint, timeout=20) as operator:  # while it is away, the speed changes once
            changed = await call_path(operator, "Filler1", "SetMachSpeed", ua.Variant(77.5, ua.VariantType.Float))
            assert changed.StatusCode.is_good()
            # the subscription (50 ms) has had its publishing cycles meanwhile: the operator's session is
            # served after them, one read at a time
            while (await operator.get_node(speed.nodeid).read_value()) != 77.5:
                await asyncio.sleep(0.05)
            for _ in range(5):
                await operator.nodes.server_state.read_value()
                await asyncio.sleep(0.05)

        second = await session_on_new_channel(Client(sp.endpoint, timeout=20), token, nonce)
        response = await asyncio.wait_for(second.uaclient.session.publish([]), 10)
        response.ResponseHeader.ServiceResult.check()
        assert response.Parameters.SubscriptionId == subscription.subscription_id
        [notification] = response.Parameters.NotificationMessage.NotificationData
        assert [item.Value.Value.Value for item in notification.MonitoredItems] == [77.5]
    finally:
        if second is not None:
            await second.disconnect()
        sp.stop()
    errors = [line for line in "".join(sp.output).splitlines() if " ERROR " in line or "Traceback" in line]
    assert errors == [], errors
