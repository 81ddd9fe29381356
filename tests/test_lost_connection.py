"""A session with a subscription outlives its connection (OPC 10000-4 6.7: "Subscriptions ... are not
dependent on the lifetime of the Session's transport"; 5.6.3.1: the client activates the session again on
a new secure channel), through `uacell serve` as deployed (its own process, on uvloop) and a real asyncua
client that loses its connection without closing anything, as a cable pulled out does.

Before decision 105 the subscription's loop answered a Publish request the lost connection had left
waiting, on the closed transport: uvloop refused the write, asyncua logged "Exception in subscription
loop" at ERROR and the loop ended, so the session, moved to a new channel, was never published again."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import start_serve
from helpers import wait_until

pytestmark = pytest.mark.asyncio

CURRENT_TIME = ua.NodeId(ua.ObjectIds.Server_ServerStatus_CurrentTime)  # the server writes it every second


class Seen:
    def __init__(self) -> None:
        self.values: list[Any] = []

    def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
        self.values.append(val)

    def status_change_notification(self, status: Any) -> None:
        pass


async def on_new_channel(endpoint: str, token: ua.NodeId, nonce: bytes) -> Client:
    """A new connection and secure channel on which the session of AuthenticationToken ``token`` is
    activated again (asyncua's client steps; anonymous on SecurityPolicy None, as the session was created;
    ``nonce`` the last one the server gave it)."""
    client = Client(endpoint, timeout=20)
    await client.connect_socket()
    await client.send_hello()
    await client.open_secure_channel()
    client.uaclient.protocol.authentication_token = token
    client._server_nonce = nonce
    await client.activate_session()
    return client


async def test_a_subscription_goes_on_when_its_session_comes_back_on_a_new_connection(tmp_path: Path) -> None:
    data = tmp_path / "data"
    data.mkdir()
    sp = start_serve(data)
    second: Client | None = None
    try:
        first = Client(sp.endpoint, timeout=20)
        await first.connect()
        seen = Seen()
        subscription = await first.create_subscription(100, seen)
        await subscription.subscribe_data_change(first.get_node(CURRENT_TIME))
        await wait_until(lambda: len(seen.values) >= 2, timeout=20, step=0.05)  # its Publish requests wait
        token, nonce = first.uaclient.protocol.authentication_token, first._server_nonce
        first.disconnect_socket()  # the cable: no CloseSession, no CloseSecureChannel
        await asyncio.sleep(2.5)  # CurrentTime changes twice while nobody is connected

        second = await on_new_channel(sp.endpoint, token, nonce)
        response = await asyncio.wait_for(second.uaclient.session.publish([]), 10)
        response.ResponseHeader.ServiceResult.check()
        assert response.Parameters.SubscriptionId == subscription.subscription_id
        [notification] = response.Parameters.NotificationMessage.NotificationData
        [item] = notification.MonitoredItems
        assert isinstance(item.Value.Value.Value, type(seen.values[-1]))  # a time, newer than the last seen
        assert item.Value.Value.Value > seen.values[-1]
    finally:
        if second is not None:
            await second.disconnect()
        sp.stop()
    errors = [line for line in "".join(sp.output).splitlines() if " ERROR " in line or "Traceback" in line]
    assert errors == [], errors
