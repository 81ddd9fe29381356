"""One OPC UA client connection to a PLC, shared by every part on that endpoint (asyncua ``Client``).

The link connects in the background and reconnects with backoff (0.5 s doubling to 2 s) whenever
the connection is lost, so uacell serves whether or not the PLC is there. Parts register the tags
they watch; on every (re)connection the link reads them once and subscribes to them (one
subscription per link, ``publishing_interval``), and calls each part's listener with every new
value and with the connection state. Reads and writes go straight to the PLC (no queue, no replay):
a lost connection raises ``CommunicationError``.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable
from typing import Any

from asyncua import Client, ua

from uacell.gateway.modbus import CommunicationError

log = logging.getLogger(__name__)

FIRST_RETRY, LAST_RETRY = 0.5, 2.0

ValueListener = Callable[[str, Any], None]  # (NodeId string, value)
StateListener = Callable[[bool], None]  # connected


class PlcLink:
    def __init__(self, endpoint: str, publishing_interval: float = 0.02, timeout: float = 2.0) -> None:
        self.endpoint = endpoint
        self.publishing_interval = publishing_interval
        self.timeout = timeout
        self.users = 0
        self.connected = False
        self.last_error = ""
        self._watched: dict[str, list[ValueListener]] = {}
        self._state_listeners: list[StateListener] = []
        self._client: Client | None = None
        self._subscription: Any = None
        self._watchdog: asyncio.Task[None] | None = None
        self._task: asyncio.Task[None] | None = None
        self._lost = asyncio.Event()
        self._ready = asyncio.Event()

    # -- what parts use ---------------------------------------------------------------------------

    async def watch(self, node_ids: list[str], listener: ValueListener, on_state: StateListener) -> None:
        """Call ``listener`` with each value of ``node_ids`` (on every connection, then on change)."""
        for nid in node_ids:
            self._watched.setdefault(nid, []).append(listener)
        self._state_listeners.append(on_state)
        if self.connected and self._client is not None and self._subscription is not None:
            try:  # connected already (another part on this PLC): read and subscribe these too
                nodes = [self._client.get_node(ua.NodeId.from_string(n)) for n in node_ids]
                for nid, node in zip(node_ids, nodes, strict=True):
                    dv = await node.read_data_value(raise_on_bad_status=False)
                    if not dv.StatusCode.is_good():
                        raise CommunicationError(f"{self.endpoint}: {nid}: {dv.StatusCode.name}")
                    listener(nid, dv.Value.Value if dv.Value is not None else None)
                await self._subscription.subscribe_data_change(nodes, queuesize=100)
                on_state(True)
            except CommunicationError as exc:
                log.warning("the PLC at %s: %s", self.endpoint, exc)
                self._lost.set()
            except Exception as exc:
                self._lost.set()
                log.warning("the PLC at %s: %s (reconnecting)", self.endpoint, exc)

    def start(self) -> None:
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run(), name=f"plc {self.endpoint}")

    async def wait_connected(self, timeout: float) -> bool:
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._ready.wait(), timeout)
        return self.connected

    async def read(self, node_id: str) -> Any:
        client = self._usable()
        try:
            return await client.get_node(ua.NodeId.from_string(node_id)).read_value()
        except (OSError, TimeoutError, ua.UaError, ConnectionError) as exc:
            raise self._failed(exc) from None

    async def read_many(self, node_ids: list[str]) -> list[Any]:
        """Several values in one Read request (the PLC answers them from one scan)."""
        client = self._usable()
        try:
            values: list[Any] = await client.read_values([client.get_node(ua.NodeId.from_string(n)) for n in node_ids])
            return values
        except (OSError, TimeoutError, ua.UaError, ConnectionError) as exc:
            raise self._failed(exc) from None

    async def write(self, node_id: str, value: Any, vtype: ua.VariantType) -> None:
        client = self._usable()
        try:
            await client.get_node(ua.NodeId.from_string(node_id)).write_value(ua.DataValue(ua.Variant(value, vtype)))
        except ua.UaStatusCodeError as exc:
            raise CommunicationError(f"{self.endpoint}: writing {node_id}: {exc}") from None
        except (OSError, TimeoutError, ua.UaError, ConnectionError) as exc:
            raise self._failed(exc) from None

    async def write_many(self, writes: list[tuple[str, Any, ua.VariantType]]) -> None:
        """Several values in one Write request, in order (the PLC takes them between two scans)."""
        client = self._usable()
        nodes = [client.get_node(ua.NodeId.from_string(n)) for n, _, _ in writes]
        values = [ua.DataValue(ua.Variant(v, t)) for _, v, t in writes]
        try:
            await client.write_values(nodes, values)
        except ua.UaStatusCodeError as exc:
            raise CommunicationError(f"{self.endpoint}: writing {[n for n, _, _ in writes]}: {exc}") from None
        except (OSError, TimeoutError, ua.UaError, ConnectionError) as exc:
            raise self._failed(exc) from None

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            await asyncio.wait({self._task}, timeout=5.0)
        await self._disconnect()

    # -- the connection ---------------------------------------------------------------------------

    def _usable(self) -> Client:
        if not self.connected or self._client is None:
            raise CommunicationError(f"no connection to the PLC at {self.endpoint}")
        return self._client

    def _failed(self, exc: BaseException) -> CommunicationError:
        self._lost.set()
        return CommunicationError(f"{self.endpoint}: {exc or type(exc).__name__}")

    async def _run(self) -> None:
        delay = FIRST_RETRY
        while True:
            try:
                await self._connect()
                delay = FIRST_RETRY
                await self._lost.wait()
            except asyncio.CancelledError:
                raise
            except Exception as exc:
                reason = str(exc) or type(exc).__name__
                if reason != self.last_error:
                    log.warning("the PLC at %s: %s (retrying)", self.endpoint, reason)
                self.last_error = reason
            self._set_connected(False)
            await self._disconnect()
            await asyncio.sleep(delay)
            delay = min(delay * 2, LAST_RETRY)

    async def _connect(self) -> None:
        self._lost.clear()
        client = Client(self.endpoint, timeout=self.timeout)
        client.session_timeout = 30_000
        self._client = client
        await client.connect()
        nodes = {nid: client.get_node(ua.NodeId.from_string(nid)) for nid in self._watched}
        # a first read of everything (a missing tag or a wrong type is named here, once)
        for nid, node in nodes.items():
            dv = await node.read_data_value(raise_on_bad_status=False)
            if not dv.StatusCode.is_good():
                raise CommunicationError(f"{self.endpoint}: {nid}: {dv.StatusCode.name}")
            self._deliver(nid, dv.Value.Value if dv.Value is not None else None)
        link = self

        class Handler:
            def datachange_notification(self, node: Any, val: Any, data: Any) -> None:
                link._deliver(node.nodeid.to_string(), val)

            def status_change_notification(self, status: Any) -> None:
                link._lost.set()

        subscription = await client.create_subscription(self.publishing_interval * 1000, Handler())
        if nodes:
            await subscription.subscribe_data_change(list(nodes.values()), queuesize=100)
        self._subscription = subscription
        if self.last_error:
            log.info("the PLC at %s answers again", self.endpoint)
        self.last_error = ""
        self._set_connected(True)
        self._watchdog = asyncio.get_running_loop().create_task(self._keepalive(client))

    async def _keepalive(self, client: Client) -> None:
        """asyncua notices a dead server only when a request fails: ask every second."""
        while not self._lost.is_set():
            await asyncio.sleep(1.0)
            try:
                await asyncio.wait_for(client.get_node(ua.ObjectIds.Server_ServerStatus_State).read_value(), 2.0)
            except Exception:
                self._lost.set()

    def _deliver(self, nid: str, value: Any) -> None:
        for listener in self._watched.get(nid, []):
            try:
                listener(nid, value)
            except Exception:
                log.exception("a PLC tag listener failed")

    def _set_connected(self, connected: bool) -> None:
        if connected == self.connected:
            if connected:
                self._ready.set()
            return
        self.connected = connected
        if connected:
            self._ready.set()
        for listener in self._state_listeners:
            try:
                listener(connected)
            except Exception:
                log.exception("a PLC state listener failed")

    async def _disconnect(self) -> None:
        if self._watchdog is not None:
            self._watchdog.cancel()
        self._subscription = None
        client, self._client = self._client, None
        if client is not None:
            with contextlib.suppress(Exception):
                await asyncio.wait_for(client.disconnect(), 2.0)


class LinkPool:
    """Links shared per endpoint: fifty units on one PLC use one connection."""

    def __init__(self) -> None:
        self._links: dict[str, PlcLink] = {}

    def get(self, endpoint: str, publishing_interval: float = 0.02) -> PlcLink:
        link = self._links.get(endpoint)
        if link is None:
            link = self._links[endpoint] = PlcLink(endpoint, publishing_interval)
        link.users += 1
        return link

    async def release(self, link: PlcLink) -> None:
        link.users -= 1
        if link.users <= 0:
            self._links.pop(link.endpoint, None)
            await link.close()
