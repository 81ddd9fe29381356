"""``uacell health``: is the server up? Used by the container image's HEALTHCHECK; exit 0 means healthy.

It asks the server for its endpoints (OPC UA discovery, open to everyone on every endpoint). Where an
unencrypted endpoint is offered (loopback), it also opens an anonymous session and requires
Server/ServerStatus/State to be Running (as the user named in the endpoint, ``opc.tcp://user:password@host:port/``,
if any: a refused login is said in plain words). Elsewhere, answering discovery is the sign of life: reading the
state would need a trusted client certificate.
"""

from __future__ import annotations

import asyncio
import logging

from asyncua import Client, ua

from uacell.core.errors import login_refusal


async def check(endpoint: str, timeout: float = 10.0) -> tuple[bool, str]:
    """(True, what was seen) when the server at ``endpoint`` is healthy; otherwise (False, why)."""
    stack_log = logging.getLogger("asyncua")
    saved = stack_log.level
    stack_log.setLevel(logging.CRITICAL)  # one line of our own says what failed
    try:
        async with asyncio.timeout(timeout):
            endpoints = await Client(endpoint, timeout=timeout).connect_and_get_server_endpoints()
            if not any(e.SecurityMode == ua.MessageSecurityMode.None_ for e in endpoints):
                return True, f"answers ({len(endpoints)} secure endpoints)"
            client = Client(endpoint, timeout=timeout)
            await client.connect()
            try:
                node = client.get_node(ua.NodeId(ua.ObjectIds.Server_ServerStatus_State))
                state = ua.ServerState(await node.read_value())
            finally:
                await client.disconnect()
    except TimeoutError:
        return False, f"no answer within {timeout:g} s"
    except ua.UaStatusCodeError as exc:
        words = login_refusal(ua.StatusCode(exc.code).name)
        if words is not None:  # user:password@ in the endpoint, refused
            return False, f"the server refused the login: {words} ({ua.StatusCode(exc.code).name})"
        return False, f"not reachable: {exc}"
    except (OSError, ua.UaError) as exc:
        return False, f"not reachable: {exc}"
    finally:
        stack_log.setLevel(saved)
    return state == ua.ServerState.Running, state.name
