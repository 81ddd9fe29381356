"""The one broker link, ``uacell.pubsub.mqtt.MqttLink``, with the hooks PubSub and Sparkplug both stand
on, against a real mosquitto and a plain MQTT client (aiomqtt) as the other side: the messages of its
subscriptions handed to ``on_message`` (a handler that fails is logged, the session goes on), and a
Will that the broker keeps (retained) or not as the Will message says (MQTT 3.1.1 §3.1.2.7)."""

from __future__ import annotations

import logging
import socket
from collections.abc import Iterator
from typing import cast

import aiomqtt
import pytest
from helpers import wait_until
from mqtt_broker import Broker, needs_mosquitto, running_broker

from uacell.pubsub.config import PubSubConfig
from uacell.pubsub.mqtt import LinkSettings, MqttLink, Outgoing

pytestmark = needs_mosquitto


@pytest.fixture(scope="module")
def broker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Broker]:
    with running_broker(tmp_path_factory.mktemp("broker")) as b:
        yield b


def settings(broker: Broker, client_id: str) -> LinkSettings:
    return LinkSettings.of(PubSubConfig(broker=broker.url), client_id, qos=1, buffer=100)


def drop_connection(link: MqttLink) -> None:
    """The network lost under the link: its socket shut, no DISCONNECT sent (the broker sends the Will)."""
    assert link.session is not None
    sock = link.session._client.socket()
    assert sock is not None
    cast(socket.socket, sock).shutdown(socket.SHUT_RDWR)  # paho's plain TCP socket to the test broker


async def test_subscribed_messages_reach_on_message_and_a_failing_handler_is_one_logged_error(
    broker: Broker, caplog: pytest.LogCaptureFixture
) -> None:
    got: list[tuple[str, bytes]] = []

    async def on_message(topic: str, payload: bytes) -> None:
        got.append((topic, payload))
        if payload == b"bad":
            raise RuntimeError("a bug in the handler")

    link = MqttLink(settings(broker, "link-sub"), Outgoing("link/sub/will", b""), list, ["link/cmd/#"], on_message)
    link.start()
    try:
        await wait_until(link.connected.is_set, timeout=30)
        async with aiomqtt.Client("127.0.0.1", broker.port, identifier="peer-sub") as peer:
            await peer.publish("link/other", b"not subscribed", qos=1)
            for payload in (b"bad", b"good"):
                await peer.publish("link/cmd/a", payload, qos=1)
        await wait_until(lambda: len(got) >= 2, timeout=30)
        assert got == [("link/cmd/a", b"bad"), ("link/cmd/a", b"good")]
        assert link.connects == 1 and link.failures == 0 and link.connected.is_set()
    finally:
        await link.close()
    errors = [r for r in caplog.records if r.levelno >= logging.ERROR]
    assert len(errors) == 1 and errors[0].exc_info, [r.getMessage() for r in errors]
    assert errors[0].getMessage() == "pubsub: handling a message on link/cmd/a failed"


@pytest.mark.parametrize("retain", [True, False])
async def test_the_broker_keeps_the_will_only_when_it_says_retain(broker: Broker, retain: bool) -> None:
    topic, marker = f"link/will/{retain}", f"link/marker/{retain}"
    made: list[int] = []

    def will() -> Outgoing:
        made.append(len(made))
        return Outgoing(topic, f"gone {len(made)}".encode(), retain=retain)

    link = MqttLink(settings(broker, f"link-will-{retain}"), will, list)
    link.start()
    try:
        await wait_until(link.connected.is_set, timeout=30)
        async with aiomqtt.Client("127.0.0.1", broker.port, identifier=f"watcher-{retain}") as watcher:
            await watcher.subscribe(topic, qos=1)
            drop_connection(link)
            async for message in watcher.messages:  # the broker publishes the Will of the lost connection
                assert (str(message.topic), message.payload) == (topic, b"gone 1")
                break
            await watcher.publish(marker, b"after the will", qos=1, retain=True)
        await wait_until(lambda: link.connects >= 2 and link.connected.is_set(), timeout=30)
        assert made == [0, 1]  # a new Will for the new connection
        # a newcomer: the broker sends the retained messages of each subscription as it takes it, in
        # order, so what the Will's topic holds comes before the marker
        async with aiomqtt.Client("127.0.0.1", broker.port, identifier=f"newcomer-{retain}") as newcomer:
            await newcomer.subscribe(topic, qos=1)
            await newcomer.subscribe(marker, qos=1)
            seen: list[tuple[str, bytes]] = []
            async for message in newcomer.messages:
                assert isinstance(message.payload, bytes)
                seen.append((str(message.topic), message.payload))
                if str(message.topic) == marker:
                    break
        expected = [(topic, b"gone 1")] if retain else []
        assert seen == [*expected, (marker, b"after the will")]
    finally:
        await link.close()
        async with aiomqtt.Client("127.0.0.1", broker.port, identifier=f"cleaner-{retain}") as cleaner:
            for t in (topic, marker):
                await cleaner.publish(t, b"", qos=1, retain=True)


async def test_pahos_error_for_a_dropped_broker_is_demoted_and_other_errors_are_kept(
    caplog: pytest.LogCaptureFixture,
) -> None:
    """paho logs "failed to receive on socket: [Errno 32] Broken pipe" at ERROR when the broker drops
    the connection; the link reports the drop itself, so that record becomes DEBUG. Any other ERROR of
    paho's stays an ERROR."""
    from uacell.pubsub.mqtt import PAHO_LOGGER

    config = PubSubConfig(broker="mqtt://127.0.0.1:1")  # never connected: making its client is enough
    MqttLink(LinkSettings.of(config, "quiet", qos=1, buffer=1), Outgoing("t", b""), list)._client()
    paho = logging.getLogger(PAHO_LOGGER)
    caplog.set_level(logging.DEBUG, logger=PAHO_LOGGER)
    paho.error("failed to receive on socket: %s", BrokenPipeError(32, "Broken pipe"))
    paho.error("Error: Unrecognised command %s", 99)
    above = [(r.levelname, r.getMessage()) for r in caplog.records if r.levelno >= logging.WARNING]
    assert above == [("ERROR", "Error: Unrecognised command 99")]
    assert any(r.levelno == logging.DEBUG and "Broken pipe" in r.getMessage() for r in caplog.records)
