"""The HMI answers only for the names it is served under (DNS rebinding), and asks for HTTPS to stay.

A page from an attacker's host name that resolves to 127.0.0.1 reaches the HMI with that name in
its ``Host`` header; the browser treats it as the attacker's own origin, so cookies, SameSite and the
CSRF token do not stop it. The defence is the ``Host`` header: the HMI answers requests naming a
loopback name, an IP address (a literal address cannot be rebound), the address it listens on or
this machine's own names; any other name gets 421 Misdirected Request before the application sees
the request. Over HTTPS every answer carries ``Strict-Transport-Security``.
"""

from __future__ import annotations

import ipaddress
import socket
from collections.abc import Iterable

from starlette.types import ASGIApp, Message, Receive, Scope, Send

LOOPBACK_NAMES = frozenset({"localhost", "localhost.localdomain", "ip6-localhost", "ip6-loopback"})
HSTS = b"max-age=31536000"


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
    """ASGI middleware: 421 for a ``Host`` the HMI is not served under; HSTS over HTTPS."""

    def __init__(self, app: ASGIApp, *, names: Iterable[str] = (), https: bool = False) -> None:
        self.app = app
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
            body = b"This HMI is not served under that host name.\n"
            await send(
                {
                    "type": "http.response.start",
                    "status": 421,
                    "headers": [
                        (b"content-type", b"text/plain; charset=utf-8"),
                        (b"content-length", str(len(body)).encode()),
                        *self._extra(),
                    ],
                }
            )
            await send({"type": "http.response.body", "body": body})
            return
        if not self.https:
            await self.app(scope, receive, send)
            return

        async def send_with_hsts(message: Message) -> None:
            if message["type"] == "http.response.start":
                message = {**message, "headers": [*message.get("headers", ()), *self._extra()]}
            await send(message)

        await self.app(scope, receive, send_with_hsts)

    def _extra(self) -> list[tuple[bytes, bytes]]:
        return [(b"strict-transport-security", HSTS)] if self.https else []
