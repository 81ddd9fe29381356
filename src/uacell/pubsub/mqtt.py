"""One MQTT connection to the plant's broker, kept up by uacell: aiomqtt (on paho-mqtt) underneath.
PubSub uses ``MqttLink`` as it is; Sparkplug's link (sparkplug/link.py) is a subclass of it.

``MqttLink.send`` never blocks and never fails: a message goes into a bounded buffer, and when the
buffer is full the oldest message is dropped and counted (the sequence numbers already in the
messages let a subscriber see the gap). A task connects, registers the Will (PubSub's: the Status
message with PubSubState Error, retained, OPC 10000-14 7.3.4.7.7; when ``will`` is a function it is
called on every connect, so each Will has a MessageId of its own), subscribes to ``subscriptions``
(their messages go to ``on_message``), starts the session (``_begin``: PubSub's publishes the
retained messages ``on_connect`` returns, status Operational and every writer's metadata), then
drains the buffer in order. aiomqtt does not reconnect by itself: when the connection fails or
drops, the task waits (0.5 s, doubling to 10 s) and tries again; each new reason is logged once (one
WARNING line, tagged with ``section``), not each retry, and never with a traceback. ``leave`` ends a
session cleanly and connects again at once. ``close`` can clear retained topics (an empty retained
message, MQTT 3.1.1 §3.3.1.3).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import ssl
from collections import deque
from collections.abc import Awaitable, Callable, Sequence
from dataclasses import dataclass
from typing import Any, ClassVar

from uacell.core.extras import MissingExtra
from uacell.core.logs import exception_of, quiet_expected
from uacell.pubsub.config import Broker, BrokerConfig, broker_of, password_of

try:
    import aiomqtt
except ImportError as exc:  # the 'mqtt' extra (the 'sparkplug' extra includes it)
    raise MissingExtra.of("[pubsub] or [sparkplug]", exc) from exc

log = logging.getLogger(__name__)

PAHO_LOGGER = "mqtt"  # the logger aiomqtt hands to paho


def _broker_gone(record: logging.LogRecord) -> bool:
    """paho's ERROR when the broker dropped the connection ("failed to receive on socket: [Errno 32]
    Broken pipe"): the link reports the drop itself, in one WARNING line (decision 62)."""
    cause = record.args[0] if isinstance(record.args, tuple) and record.args else exception_of(record)
    return str(record.msg).startswith("failed to ") and isinstance(cause, OSError)


FIRST_RETRY = 0.5
LAST_RETRY = 10.0
PUBLISH_TIMEOUT = 10.0


@dataclass(frozen=True)
class Outgoing:
    topic: str
    payload: bytes
    retain: bool = False


@dataclass(frozen=True)
class LinkSettings:
    broker: Broker
    client_id: str
    qos: int
    keep_alive: int
    buffer: int
    username: str | None = None
    password: str | None = None
    ca_file: str | None = None
    cert_file: str | None = None
    key_file: str | None = None

    @classmethod
    def of(cls, cfg: BrokerConfig, client_id: str, qos: int, buffer: int) -> LinkSettings:
        """The link of a section's broker keys (URL, keep-alive, TLS files, credentials); ConfigError
        names a key that cannot work."""
        return cls(
            broker=broker_of(cfg),
            client_id=client_id,
            qos=qos,
            keep_alive=cfg.keep_alive,
            buffer=buffer,
            username=cfg.username or None,
            password=password_of(cfg),
            ca_file=str(cfg.ca_file) if cfg.ca_file else None,
            cert_file=str(cfg.cert_file) if cfg.cert_file else None,
            key_file=str(cfg.key_file) if cfg.key_file else None,
        )

    @property
    def url(self) -> str:
        return f"{'mqtts' if self.broker.tls else 'mqtt'}://{self.broker.host}:{self.broker.port}"


class _Client(aiomqtt.Client):  # on aiomqtt 2's internals (pyproject: <3); test_pubsub_standard fails without it
    """aiomqtt's client, except that registering the socket for writing after paho closed it (the broker
    dropped the connection, e.g. on a keep-alive timeout) is a dropped connection, not an "Exception in
    callback Loop.add_writer" traceback: the reader already reports the drop."""

    def _on_socket_register_write(self, client: Any, userdata: Any, sock: Any) -> None:
        loop = self._loop

        def writable() -> None:
            try:
                client.loop_write()
            except Exception as exc:  # a broken connection: the same as aiomqtt does
                if not self._disconnected.done():
                    self._disconnected.set_exception(exc)

        def register() -> None:
            with contextlib.suppress(OSError, ValueError, KeyError):
                loop.add_writer(sock.fileno(), writable)

        loop.call_soon_threadsafe(register)

    def _on_socket_unregister_write(self, client: Any, userdata: Any, sock: Any) -> None:
        with contextlib.suppress(OSError, ValueError, KeyError):
            self._loop.remove_writer(sock.fileno())


class MqttLink:
    section: ClassVar[str] = "pubsub"  # the tag of its log lines, the config section and docs/<section>.md
    log: ClassVar[logging.Logger] = log
    keeps_buffer: ClassVar[bool] = True  # False: what a session did not send is dropped when it ends

    def __init__(
        self,
        settings: LinkSettings,
        will: Outgoing | Callable[[], Outgoing],
        on_connect: Callable[[], Sequence[Outgoing]],
        subscriptions: Sequence[str] = (),
        on_message: Callable[[str, bytes], Awaitable[None]] | None = None,
    ) -> None:
        self.settings = settings
        self._will = will
        self.on_connect = on_connect
        self.subscriptions = list(subscriptions)
        self.on_message = on_message
        self.buffer: deque[Outgoing] = deque()
        self.sent = 0  # messages the broker took
        self.dropped = 0  # messages dropped from a full buffer
        self.connects = 0  # successful connections (the first and each reconnect)
        self.failures = 0  # connections that failed or dropped
        self.connected = asyncio.Event()
        self.last_error = ""
        self._wake = asyncio.Event()
        self._closing = False
        self._leave = asyncio.Event()  # set: end this session cleanly (and connect again)
        self._task: asyncio.Task[None] | None = None
        self._last_words: Outgoing | None = None
        self._clear: tuple[str, ...] = ()
        self.session: aiomqtt.Client | None = None  # the client of the current connection, while connected

    @property
    def will(self) -> Outgoing:
        """The Will to register on the next connect (a new one each time when ``will`` is a function)."""
        return self._will() if callable(self._will) else self._will

    @will.setter
    def will(self, will: Outgoing | Callable[[], Outgoing]) -> None:
        self._will = will

    # -- what the publisher uses -----------------------------------------------------------------

    def send(self, message: Outgoing) -> None:
        if len(self.buffer) >= self.settings.buffer:
            self.buffer.popleft()
            self.dropped += 1
        self.buffer.append(message)
        self._wake.set()

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._run(), name=f"uacell-{self.section}")

    def leave(self) -> None:
        """End the session cleanly (what is buffered goes first) and connect again."""
        self._leave.set()
        self._wake.set()

    async def close(self, last_words: Outgoing | None = None, timeout: float = 3.0, clear: Sequence[str] = ()) -> None:
        """Send what is buffered and ``last_words`` (retained) if connected, clear the retained messages
        of the topics ``clear`` (an empty retained message each), then disconnect cleanly (the broker
        then does not send the Will); give up after ``timeout`` seconds."""
        self._closing = True
        self._last_words = last_words
        self._clear = tuple(clear)
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

    # -- the connection ---------------------------------------------------------------------------

    def _client(self) -> aiomqtt.Client:
        quiet_expected("broker-lost", (PAHO_LOGGER,), _broker_gone)
        s = self.settings
        tls_context = None
        if s.broker.tls:
            tls_context = ssl.create_default_context(cafile=s.ca_file)
            if s.cert_file:
                tls_context.load_cert_chain(s.cert_file, s.key_file)
        will = self.will
        return _Client(
            s.broker.host,
            s.broker.port,
            identifier=s.client_id,
            username=s.username,
            password=s.password,
            will=aiomqtt.Will(will.topic, will.payload, qos=1, retain=will.retain),
            keepalive=s.keep_alive,
            tls_context=tls_context,
            timeout=PUBLISH_TIMEOUT,
            clean_session=True,
        )

    async def _begin(self, client: aiomqtt.Client) -> None:
        """A new session, subscribed: publish ``on_connect``'s messages (retained), then say connected."""
        for retained in self.on_connect():
            await client.publish(retained.topic, retained.payload, qos=1, retain=True)
        self.connected.set()

    async def _run(self) -> None:
        delay = FIRST_RETRY
        while not self._closing:
            try:
                async with self._client() as client:
                    self.session = client
                    self.connects += 1
                    delay = FIRST_RETRY
                    again = " again" if self.last_error else ""
                    self.log.info("%s: connected to %s%s", self.section, self.settings.url, again)
                    self.last_error = ""
                    for subscription in self.subscriptions:
                        await client.subscribe(subscription, qos=1)
                    self._leave.clear()
                    try:
                        await self._begin(client)
                        await self._serve(client)
                    finally:
                        self.connected.clear()
                        self.session = None
            except aiomqtt.MqttError as exc:
                self._failed(str(exc) or type(exc).__name__)
            except (OSError, ssl.SSLError, ValueError) as exc:  # certificate files, TLS set-up
                self._failed(str(exc) or type(exc).__name__)
            finally:
                if not self.keeps_buffer:
                    self.buffer.clear()
            if self._closing:
                return
            if self._leave.is_set():
                self._leave.clear()
                continue
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self._closed(), delay)
            delay = min(delay * 2, LAST_RETRY)

    async def _closed(self) -> None:
        while not self._closing:
            self._wake.clear()
            await self._wake.wait()

    def _failed(self, reason: str) -> None:
        self.failures += 1
        if reason != self.last_error:
            self.log.warning(
                "%s: the broker %s: %s (uacell keeps serving and retries; [%s] in docs/%s.md)",
                self.section,
                self.settings.url,
                reason,
                self.section,
                self.section,
            )
        self.last_error = reason

    async def _serve(self, client: aiomqtt.Client) -> None:
        """Drain the buffer until the connection drops (MqttError), the session ends or uacell closes."""
        watcher = asyncio.ensure_future(self._watch(client))
        try:
            while True:
                while self.buffer:
                    if watcher.done():
                        watcher.result()
                    message = self.buffer[0]
                    await client.publish(message.topic, message.payload, qos=self.settings.qos, retain=message.retain)
                    if self.buffer and self.buffer[0] is message:
                        self.buffer.popleft()
                    self.sent += 1
                if self._closing:
                    if self._last_words is not None:
                        w = self._last_words
                        await client.publish(w.topic, w.payload, qos=1, retain=True)
                    for topic in self._clear:
                        await client.publish(topic, b"", qos=1, retain=True)
                    return
                if self._leave.is_set():
                    return
                self._wake.clear()
                wake = asyncio.ensure_future(self._wake.wait())
                await asyncio.wait({wake, watcher}, return_when=asyncio.FIRST_COMPLETED)
                wake.cancel()
                if watcher.done():
                    watcher.result()
                    raise aiomqtt.MqttError("disconnected")
        finally:
            watcher.cancel()
            with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
                await watcher

    async def _watch(self, client: aiomqtt.Client) -> None:
        """Hands each message to ``on_message``; returns (raising MqttError) when the connection drops:
        aiomqtt ends message iteration then."""
        async for message in client.messages:
            if self.on_message is None:
                continue
            payload = message.payload if isinstance(message.payload, bytes | bytearray) else b""
            try:
                await self.on_message(str(message.topic), bytes(payload))
            except Exception:
                self.log.exception("%s: handling a message on %s failed", self.section, message.topic)
