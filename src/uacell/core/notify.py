"""systemd's readiness protocol (sd_notify) without a dependency: a datagram to ``$NOTIFY_SOCKET``.

``uacell serve`` sends ``READY=1`` once clients can connect and ``STOPPING=1`` when it begins to shut
down, so a ``Type=notify`` unit knows when the service is up. Without ``$NOTIFY_SOCKET`` (not started by
systemd) nothing is sent. The socket may be a path or an abstract name starting with ``@``.
"""

from __future__ import annotations

import logging
import os
import socket

log = logging.getLogger(__name__)

NOTIFY_SOCKET = "NOTIFY_SOCKET"


def notify(state: str, environ: dict[str, str] | None = None) -> bool:
    """Send ``state`` (e.g. ``"READY=1"``); True when it was sent, False without a socket or on failure."""
    address = (environ if environ is not None else os.environ).get(NOTIFY_SOCKET, "")
    if not address:
        return False
    if address.startswith("@"):
        address = "\0" + address[1:]  # Linux abstract namespace
    elif not address.startswith("/"):
        log.warning("ignoring %s=%r: neither a path nor an abstract socket name", NOTIFY_SOCKET, address)
        return False
    try:
        with socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC) as sock:
            sock.connect(address)
            sock.sendall(state.encode())
    except OSError as exc:
        log.warning("could not tell systemd %r: %s", state.split("\n", 1)[0], exc)
        return False
    return True
