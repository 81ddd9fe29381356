"""What uacell reads of asyncua's connection objects: the door's (``uacell.ua.door.connection``),
under the names the rest of uacell has used."""

from __future__ import annotations

from uacell.ua.door.connection import (
    attach,
    attached,
    channel_policy,
    peer_address,
    peer_certificate,
    permits,
    send_error,
    send_response,
    session_count,
)

__all__ = [
    "attach",
    "attached",
    "channel_policy",
    "peer_address",
    "peer_certificate",
    "permits",
    "send_error",
    "send_response",
    "session_count",
]
