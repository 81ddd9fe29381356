"""What a PackTags unit needs of a transport to a PLC (``TagLink``), and the listeners a link calls.
Implemented by ``opcua_link.PlcLink`` (OPC UA client) and ``packml_modbus.ModbusTagLink`` (Modbus/TCP)."""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Callable, Mapping
from typing import Any, Protocol

log = logging.getLogger(__name__)

FIRST_RETRY, LAST_RETRY = 0.5, 2.0  # seconds between reconnection attempts: doubling, at most LAST_RETRY

ValueListener = Callable[[str, Any], None]  # (address, value)
StateListener = Callable[[bool], None]  # connected


class TagLink(Protocol):
    """A connection to a PLC's tags by address (shared by the units on it); a lost connection makes
    every read and write raise ``CommunicationError``. Values are Python ``int``/``float``/``bool``;
    a write names the PackTags type of its tag ("Int32", "Boolean", "Float").

    A watched address the PLC does not have (it answers, but not for that tag) does not fail the
    connection: it is in ``missing`` (address -> what the PLC said) once connected, is left out of
    subscriptions and polls, and is tried again on the next connection."""

    endpoint: str
    missing: dict[str, str]

    def start(self) -> None: ...

    async def watch(
        self,
        addresses: list[str],
        listener: ValueListener,
        on_state: StateListener,
        labels: Mapping[str, str] | None = None,
    ) -> None:
        """``labels``: what each address is ("Capper: Status.StateCurrent"), for messages."""
        ...

    async def wait_connected(self, timeout: float) -> bool: ...

    async def read(self, address: str) -> Any: ...

    async def read_many(self, addresses: list[str]) -> list[Any]: ...

    async def write(self, address: str, value: Any, type_name: str) -> None: ...

    async def write_many(self, writes: list[tuple[str, Any, str]]) -> None: ...


class Listeners:
    """What both links keep alike: the listeners of each watched address and of the connection."""

    def __init__(self) -> None:
        self.endpoint = ""
        self.connected = False
        self.last_error = ""  # why the last attempt to connect failed, said once
        self.missing: dict[str, str] = {}  # watched addresses the PLC does not have -> what it said
        self._watched: dict[str, list[ValueListener]] = {}
        self._state_listeners: list[StateListener] = []
        self._ready = asyncio.Event()  # set once the first connection was made
        self._labels: dict[str, str] = {}

    def _listen(
        self,
        addresses: list[str],
        listener: ValueListener,
        on_state: StateListener,
        labels: Mapping[str, str] | None,
    ) -> None:
        for address in addresses:
            self._watched.setdefault(address, []).append(listener)
        self._state_listeners.append(on_state)
        self._labels.update(labels or {})

    def present(self) -> list[str]:
        """The watched addresses the PLC has (as far as the last connection found)."""
        return [a for a in self._watched if a not in self.missing]

    def named(self, address: str) -> str:
        """The address with what it is, for messages: ``Capper: Admin.StopReason (ns=1;s=Nope)``."""
        label = self._labels.get(address)
        return f"{label} ({address})" if label else address

    async def wait_connected(self, timeout: float) -> bool:
        with contextlib.suppress(TimeoutError):
            await asyncio.wait_for(self._ready.wait(), timeout)
        return self.connected

    def _deliver(self, address: str, value: Any) -> None:
        for listener in self._watched.get(address, []):
            try:
                listener(address, value)
            except Exception:
                log.exception("a PLC tag listener failed")

    def _announce(self) -> None:
        """Connected (again)."""
        if self.last_error:
            log.info("the PLC at %s answers again", self.endpoint)
        self.last_error = ""
        self._set_connected(True)

    def _set_connected(self, connected: bool) -> None:
        if connected:
            self._ready.set()
        if connected == self.connected:
            return
        self.connected = connected
        for listener in self._state_listeners:
            try:
                listener(connected)
            except Exception:
                log.exception("a PLC state listener failed")
