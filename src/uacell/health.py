"""``uacell health``: is the server up? It connects, reads Server/ServerStatus/State and disconnects.

Used by the container image's HEALTHCHECK and usable by any monitoring; exit 0 means Running.
"""

from __future__ import annotations

import asyncio
import logging

from asyncua import Client, ua


async def check(endpoint: str, timeout: float = 10.0) -> tuple[bool, str]:
    """(True, "Running") when the server at ``endpoint`` answers and runs; otherwise (False, why)."""
    logging.getLogger("asyncua").setLevel(logging.CRITICAL)  # one line of our own says what failed
    client = Client(endpoint, timeout=timeout)
    try:
        async with asyncio.timeout(timeout):
            await client.connect()
            try:
                state = await client.get_node(ua.NodeId(ua.ObjectIds.Server_ServerStatus_State)).read_value()
            finally:
                await client.disconnect()
    except TimeoutError:
        return False, f"no answer within {timeout:g} s"
    except (OSError, ua.UaError) as exc:
        return False, f"not reachable: {exc}"
    name = ua.ServerState(state).name
    return state == ua.ServerState.Running, name
