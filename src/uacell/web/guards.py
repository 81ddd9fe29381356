"""What every HTTP request passes before the HMI's routes: a header deadline, its Host, its size, HSTS.

The HMI answers only for the names it is served under (DNS rebinding), reads at most ``max_body``
bytes of any request body (before anything parses it), and asks browsers to stay on HTTPS.

A page from an attacker's host name that resolves to 127.0.0.1 reaches the HMI with that name in
its ``Host`` header; the browser treats it as the attacker's own origin, so cookies, SameSite and the
CSRF token do not stop it. The defence is the ``Host`` header: the HMI answers requests naming a
loopback name, an IP address (a literal address cannot be rebound), the address it listens on or
this machine's own names; any other name gets 421 Misdirected Request before the application sees
the request. A body longer than ``max_body`` gets 413 as soon as its ``Content-Length`` says so, or,
without one, once that many bytes have arrived; nothing past the cap is kept. Over HTTPS every answer
carries ``Strict-Transport-Security``.
"""

from __future__ import annotations

import asyncio
import ipaddress
import logging
import socket
from collections.abc import Iterable

import h11
from starlette.types import ASGIApp, Message, Receive, Scope, Send
from uvicorn.protocols.http.h11_impl import H11Protocol

from uacell.ua import door

log = logging.getLogger(__name__)

LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback"})
HSTS = b"max-age=31536000"
MAX_BODY = 4_200_000  # an upload of 1,000,000 characters, JSON-encoded as UTF-8, with room to spare


def host_name(header: str) -> str:
    """The name part of a ``Host`` header value, lower case, without port or IPv6 brackets."""
    value = header.strip().lower()
    if value.startswith("["):
        return value[1 : value.find("]")] if "]" in value else ""
    name, _, _port = value.partition(":")
    return name.rstrip(".")


def _is_address(name: str) -> bool:
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def machine_names() -> frozenset[str]:
    """This machine's own host names (short and fully qualified)."""
    names = {socket.gethostname()}
    try:
        names.add(socket.getfqdn())
    except OSError:  # pragma: no cover - resolver trouble: the short name still counts
        pass
    return frozenset(n.lower().rstrip(".") for n in names if n)


class HostGuard:
    """ASGI middleware: 421 for a ``Host`` the HMI is not served under, 413 for a body over
    ``max_body``; HSTS over HTTPS."""

    def __init__(
        self, app: ASGIApp, *, names: Iterable[str] = (), https: bool = False, max_body: int = MAX_BODY
    ) -> None:
        self.app = app
        self.max_body = max_body
        self.names = LOOPBACK_NAMES | frozenset(host_name(n) for n in names if n)
        self.https = https

    def allows(self, header: str) -> bool:
        name = host_name(header)
        return bool(name) and (name in self.names or _is_address(name))

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        host = next((v.decode("latin-1") for k, v in scope.get("headers", ()) if k == b"host"), "")
        if not self.allows(host):
            await self._refuse(send, 421, "This HMI is not served under that host name.")
            return
        buffered = await self._read_body(scope, receive)
        if buffered is None:
            await self._refuse(send, 413, f"The request body is larger than {self.max_body} bytes.")
            return
        if buffered:
            pending = list(buffered)

            async def replay() -> Message:
                return pending.pop(0) if pending else await receive()

            receive = replay
        if not self.https:
            await self.app(scope, receive, send)
            return

        async def send_with_hsts(message: Message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", ()), *self._extra()]}
            await send(message)

        await self.app(scope, receive, send_with_hsts)

    async def _read_body(self, scope: Scope, receive: Receive) -> list[Message] | None:
        """The body's messages when it fits (read ahead, so nothing parses an oversized one), or None."""
        headers = dict(scope.get("headers", ()))
        length = headers.get(b"content-length")
        if length is not None:
            try:
                if int(length) > self.max_body:
                    return None
            except ValueError:
                return None
            if int(length) == 0:
                return []
        elif b"chunked" not in headers.get(b"transfer-encoding", b"").lower():
            return []
        messages: list[Message] = []
        size = 0
        while True:
            message = await receive()
            messages.append(message)
            if message["type"] != "http.request":
                return messages
            size += len(message.get("body", b""))
            if size > self.max_body:
                return None
            if not message.get("more_body", False):
                return messages

    async def _refuse(self, send: Send, status: int, text: str) -> None:
        body = (text + "\n").encode()
        headers = [(b"content-type", b"text/plain; charset=utf-8"), (b"content-length", str(len(body)).encode())]
        await send({"type": "http.response.start", "status": status, "headers": [*headers, *self._extra()]})
        await send({"type": "http.response.body", "body": body})

    def _extra(self) -> list[tuple[bytes, bytes]]:
        return [(b"strict-transport-security", HSTS)] if self.https else []


HEADER_TIMEOUT = 10.0  # seconds a connection may take to send a request's headers ([web] header_timeout)


def timed_headers(header_timeout: float) -> type[H11Protocol]:
    """uvicorn's HTTP/1.1 protocol with a deadline on each request's headers.

    uvicorn closes a connection idle between requests, but a client that keeps sending a header a byte
    at a time holds it (and a file descriptor) forever. Here the clock runs from the connection's
    start, and again from each answer, until a request's headers are complete; past ``header_timeout``
    the connection gets ``408`` and is closed. Bodies are not timed here (the body cap bounds them)."""

    @door.subclass("uvicorn.protocols.http.h11_impl.H11Protocol")
    class TimedHeaders(H11Protocol):
        _timer: asyncio.TimerHandle | None = None

        def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
            super().connection_made(transport)
            self._arm()

        def connection_lost(self, exc: Exception | None) -> None:
            self._disarm()
            super().connection_lost(exc)

        def data_received(self, data: bytes) -> None:
            super().data_received(data)
            if self.conn.their_state is not h11.IDLE:
                self._disarm()  # the headers are in

        def on_response_complete(self) -> None:
            super().on_response_complete()
            if not self.transport.is_closing() and self.conn.their_state is h11.IDLE:
                self._arm()

        def _arm(self) -> None:
            self._disarm()
            self._timer = self.loop.call_later(header_timeout, self._late)

        def _disarm(self) -> None:
            if self._timer is not None:
                self._timer.cancel()
                self._timer = None

        def _late(self) -> None:
            self._timer = None
            if self.transport.is_closing() or self.conn.their_state is not h11.IDLE:
                return
            client = self.client[0] if self.client else "?"
            log.info(
                "web: closed a connection from %s that sent no complete request within %g s", client, header_timeout
            )
            self.transport.write(b"HTTP/1.1 408 Request Timeout\r\ncontent-length: 0\r\nconnection: close\r\n\r\n")
            self.transport.close()

    return TimedHeaders
