"""A stop announced to the clients connected (OPC 10000-5 12.10, ServerStatusDataType; decision 85).

"After the Server shut down is initiated, the state changes to SHUTDOWN and the actual shut down should
be delayed for a configurable time if Clients are connected to the Server to allow these Clients an
orderly disconnect." When a stop begins and sessions are open, ``announce_shutdown`` sets
``ServerStatus.State`` to Shutdown, ``ShutdownReason`` to why, and counts ``SecondsTillShutdown``
down to 0 once a second (the structure and its component variables alike, so a client subscribed to
either sees it), while the server goes on serving: clients may release their locks and close their
sessions. The stop goes on when ``[server] shutdown_delay`` has passed or the last session has closed,
whichever is first; with no session open, or a delay of 0, it goes on at once.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Callable
from dataclasses import replace
from typing import Any

from asyncua import Server, ua

from uacell.ua.door import connection as door_connection

log = logging.getLogger(__name__)

REASON = "uacell is stopping"
_STATUS = ua.NodeId(ua.ObjectIds.Server_ServerStatus)
_STATE = ua.NodeId(ua.ObjectIds.Server_ServerStatus_State)
_SECONDS = ua.NodeId(ua.ObjectIds.Server_ServerStatus_SecondsTillShutdown)
_REASON = ua.NodeId(ua.ObjectIds.Server_ServerStatus_ShutdownReason)


async def no_shutdown_yet(server: Server) -> None:
    """SecondsTillShutdown 0 while the server runs: a UInt32 whose value is of its DataType (asyncua
    leaves the variable null until a stop writes it)."""
    await server.get_node(_SECONDS).write_value(ua.DataValue(ua.Variant(0, ua.VariantType.UInt32)))


def open_sessions(server: Server) -> int:
    """Sessions of clients (not the server's own) that are not closed."""
    return len(door_connection.external_sessions(server.iserver))


async def announce_shutdown(
    server: Server,
    delay: float,
    session_closed: list[Callable[[Any], None]],
    *,
    reason: str = REASON,
    clock: Callable[[], float] = time.monotonic,
) -> float:
    """Announce the stop and wait for the clients (module docstring); returns the seconds waited.
    ``session_closed``: the hooks run when a session closes (``Security.on_session_closed``): one is
    added for the wait and removed after it."""
    if delay <= 0 or not open_sessions(server):
        return 0.0
    started = clock()
    deadline = started + delay
    closed = asyncio.Event()

    def on_closed(_session: Any) -> None:
        closed.set()

    session_closed.append(on_closed)
    try:
        seconds = math.ceil(delay)
        log.info("stop announced to %d session(s): ServerState Shutdown for up to %.1f s", open_sessions(server), delay)
        await _write_status(server, seconds, reason)
        while (left := deadline - clock()) > 0 and open_sessions(server):
            if math.ceil(left) != seconds:
                seconds = math.ceil(left)
                await _write_status(server, seconds, reason)
            closed.clear()
            # wake when a session closes, else when the next whole second is due
            next_second = left - (seconds - 1) if seconds > 1 else left
            try:
                await asyncio.wait_for(closed.wait(), timeout=max(next_second, 0.001))
            except TimeoutError:
                pass
        if open_sessions(server):
            await _write_status(server, 0, reason)
    finally:
        session_closed.remove(on_closed)
    return clock() - started


async def _write_status(server: Server, seconds: int, reason: str) -> None:
    """ServerStatus (the structure) and its State, SecondsTillShutdown and ShutdownReason variables. The
    State variable is written last: its change is queued after the reason's and the seconds', so a client
    that sees Shutdown has been sent why and when in the same notification or an earlier one."""
    text = ua.LocalizedText(reason, "en")
    current = await server.get_node(_STATUS).read_value()
    status = replace(current, State=ua.ServerState.Shutdown, SecondsTillShutdown=seconds, ShutdownReason=text)
    await server.get_node(_STATUS).write_value(ua.DataValue(ua.Variant(status, ua.VariantType.ExtensionObject)))
    await server.get_node(_REASON).write_value(ua.DataValue(ua.Variant(text, ua.VariantType.LocalizedText)))
    await server.get_node(_SECONDS).write_value(ua.DataValue(ua.Variant(seconds, ua.VariantType.UInt32)))
    await server.get_node(_STATE).write_value(ua.DataValue(ua.Variant(ua.ServerState.Shutdown, ua.VariantType.Int32)))
