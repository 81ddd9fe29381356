"""The edge node's MQTT connection (aiomqtt, as PubSub's), kept up by uacell.

Each connection is one Sparkplug session: ``will()`` gives the NDEATH of a new bdSeq, registered as
the MQTT Will before connecting; once connected the link subscribes to the node's NCMD and DCMD
topics (and the primary host's STATE), then tells ``on_connect`` (which births the node when it may),
hands every message received to ``on_message`` and publishes ``send``'s messages in order. Messages
are never held across connections: a new session births everything again. When the connection
fails or drops the link waits (0.5 s, doubling to 10 s) and connects again; each new reason is
logged once, not at every retry.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import ssl
from collections import deque
from collections.abc import Awaitable, Callable

import aiomqtt

from uacell.pubsub.mqtt import FIRST_RETRY, LAST_RETRY, PUBLISH_TIMEOUT, LinkSettings
from uacell.sparkplug.node import Message

log = logging.getLogger(__name__)


class SparkplugLink:
    def __init__(
        self,
        settings: LinkSettings,
        will: Callable[[], Message],
        subscriptions: list[str],
        on_connect: Callable[[], None],
        on_message: Callable[[str, bytes], Awaitable[None]],
    ) -> None:
        self.settings = settings
        self.will = will
        self.subscriptions = subscriptions
        self.on_connect = on_connect
        self.on_message = on_message
        self.queue: deque[Message] = deque()
        self.connected = asyncio.Event()
        self.sent = 0
        self.connects = 0
        self.failures = 0
        self.last_error = ""
        self._wake = asyncio.Event()
        self._closing = False
        self._leave = asyncio.Event()  # set: end this session cleanly (and connect again)
        self._task: asyncio.Task[None] | None = None

    def send(self, message: Message) -> None:
        """Publish ``message`` in this session, after those before it; dropped when not connected."""
        if self.connected.is_set():
            self.queue.append(message)
            self._wake.set()

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name="uacell-sparkplug")

    def leave(self) -> None:
        """End the session cleanly (what is queued goes first) and connect again."""
        self._leave.set()
        self._wake.set()

    async def close(self, timeout: float = 3.0) -> None:
        """Send what is queued, disconnect cleanly; give up after ``timeout`` seconds."""
        self._closing = True
        self._wake.set()
        if self._task is None:
            return
        if not self.connected.is_set():
            self._task.cancel()
        with contextlib.suppress(asyncio.CancelledError, TimeoutError):
            await asyncio.wait_for(asyncio.shield(self._task), timeout)
        if not self._task.done():
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task

    def _client(self, will: Message) -> aiomqtt.Client:
        s = self.settings
        tls_context = None
        if s.broker.tls:
            tls_context = ssl.create_default_context(cafile=s.ca_file)
            if s.cert_file:
                tls_context.load_cert_chain(s.cert_file, s.key_file)
        return aiomqtt.Client(
            s.broker.host,
            s.broker.port,
            identifier=s.client_id,
            username=s.username,
            password=s.password,
            # Sparkplug 3.0 (NDEATH): the Will with QoS 1, not retained; a clean session
            will=aiomqtt.Will(will.topic, will.payload, qos=1, retain=False),
            keepalive=s.keep_alive,
            tls_context=tls_context,
            timeout=PUBLISH_TIMEOUT,
            clean_session=True,
        )

    async def _run(self) -> None:
        delay = FIRST_RETRY
        while not self._closing:
            try:
                async with self._client(self.will()) as client:
                    self.connects += 1
                    delay = FIRST_RETRY
                    log.info("sparkplug: connected to %s%s", self.settings.url, " again" if self.last_error else "")
                    self.last_error = ""
                    for subscription in self.subscriptions:
                        await client.subscribe(subscription, qos=1)
                    self._leave.clear()
                    self.queue.clear()
                    self.connected.set()
                    self.on_connect()
                    await self._serve(client)
            except aiomqtt.MqttError as exc:
                self.failures += 1
                self._note(str(exc) or type(exc).__name__)
            finally:
                self.connected.clear()
                self.queue.clear()
            if self._closing:
                return
            if self._leave.is_set():
                self._leave.clear()
                continue
            await asyncio.sleep(delay)
            delay = min(LAST_RETRY, delay * 2)

    def _note(self, reason: str) -> None:
        if reason != self.last_error:
            log.warning(
                "sparkplug: the broker %s: %s (uacell keeps serving and retries; [sparkplug] in docs/sparkplug.md)",
                self.settings.url,
                reason,
            )
        self.last_error = reason

    async def _serve(self, client: aiomqtt.Client) -> None:
        """Publish the queue until the connection drops (MqttError), the session ends or uacell closes."""
        reader = asyncio.ensure_future(self._read(client))
        try:
            while True:
                while self.queue:
                    if reader.done():
                        reader.result()
                    message = self.queue.popleft()
                    await client.publish(message.topic, message.payload, qos=0)
                    self.sent += 1
                if self._closing or self._leave.is_set():
                    return
                self._wake.clear()
                wake = asyncio.ensure_future(self._wake.wait())
                await asyncio.wait({wake, reader}, return_when=asyncio.FIRST_COMPLETED)
                wake.cancel()
                if reader.done():
                    reader.result()
                    raise aiomqtt.MqttError("disconnected")
        finally:
            reader.cancel()
            with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
                await reader

    async def _read(self, client: aiomqtt.Client) -> None:
        async for message in client.messages:
            payload = message.payload if isinstance(message.payload, bytes | bytearray) else b""
            try:
                await self.on_message(str(message.topic), bytes(payload))
            except Exception:
                log.exception("sparkplug: handling a message on %s failed", message.topic)
