"""The edge node's MQTT connection: PubSub's ``MqttLink`` (pubsub/mqtt.py), with a session per connection.

Each connection is one Sparkplug session: ``will()`` gives the NDEATH of a new bdSeq, registered as
the MQTT Will (QoS 1, not retained: Sparkplug 3.0, NDEATH) before connecting; once connected the link
subscribes to the node's NCMD and DCMD topics (and the primary host's STATE), then tells
``on_connect`` (which births the node when it may), hands every message received to ``on_message``
and publishes ``send``'s messages in order (QoS 0). Messages are never held across connections: a
new session births everything again. Reconnecting, TLS, credentials and the log line per new reason
are ``MqttLink``'s.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable

import aiomqtt

from uacell.pubsub.mqtt import LinkSettings, MqttLink, Outgoing
from uacell.sparkplug.node import Message


class SparkplugLink(MqttLink):
    section = "sparkplug"
    log = logging.getLogger(__name__)
    keeps_buffer = False

    def __init__(
        self,
        settings: LinkSettings,
        will: Callable[[], Message],
        subscriptions: list[str],
        on_connect: Callable[[], None],
        on_message: Callable[[str, bytes], Awaitable[None]],
    ) -> None:
        def death() -> Outgoing:
            message = will()
            return Outgoing(message.topic, message.payload)

        super().__init__(settings, death, list, subscriptions, on_message)  # no retained messages of its own
        self.on_session = on_connect  # told once connected, after the subscriptions: it births when it may

    def send(self, message: Message | Outgoing) -> None:
        """Publish ``message`` in this session, after those before it; dropped when not connected."""
        if self.connected.is_set():
            self.buffer.append(message if isinstance(message, Outgoing) else Outgoing(message.topic, message.payload))
            self._wake.set()

    async def _begin(self, client: aiomqtt.Client) -> None:
        """Connected first, so that what ``on_session`` sends (the births) goes out in this session."""
        self.connected.set()
        self.on_session()
