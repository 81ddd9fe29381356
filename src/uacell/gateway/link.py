"""What a PackTags unit needs of a transport to a PLC (``TagLink``), and the listeners a link calls.
Implemented by ``opcua_link.PlcLink`` (OPC UA client) and, on ``PolledLink`` (a poll loop over
blocks of addresses), ``packml_modbus.ModbusTagLink`` (Modbus/TCP) and ``packml_s7.S7TagLink``
(Siemens S7)."""

from __future__ import annotations

import asyncio
import contextlib
import errno
import logging
from abc import ABC, abstractmethod
from collections.abc import Callable, Hashable, Mapping, Sequence
from typing import Any, Protocol

from uacell.core.background import stop_task
from uacell.gateway.errors import CommunicationError, NoAnswer
from uacell.gateway.pool import SharedPool, unit_conflict
from uacell.gateway.retry import keep_trying

log = logging.getLogger(__name__)


LOST = "lost the connection"
# a peer gone or out of reach (asyncio raises a plain OSError for a refused or failed connect)
NETWORK_ERRNOS = frozenset(
    {
        errno.ECONNREFUSED, errno.ECONNRESET, errno.ECONNABORTED, errno.EPIPE, errno.ETIMEDOUT, errno.EBADF,
        errno.EHOSTUNREACH, errno.ENETUNREACH, errno.ENETDOWN, errno.EHOSTDOWN, errno.ENOTCONN,
    }
)  # fmt: skip

ValueListener = Callable[[str, Any], None]  # (address, value)
StateListener = Callable[[bool], None]  # connected


def network_error(exc: BaseException | None) -> bool:
    """``exc`` says the peer went away or cannot be reached (not a fault of a request or of uacell)."""
    if isinstance(exc, ConnectionError | TimeoutError):
        return True
    return isinstance(exc, OSError) and exc.errno in NETWORK_ERRNOS


class TagLink(Protocol):
    """A connection to a PLC's tags by address (shared by the units on it); a lost connection makes
    every read and write raise ``CommunicationError``. Values are Python ``int``/``float``/``bool``;
    a write names the PackTags type of its tag ("Int32", "Boolean", "Float").

    A watched address the PLC does not have (it answers, but not for that tag) does not fail the
    connection: it is in ``missing`` (address -> what the PLC said) once connected, is left out of
    subscriptions and polls, and is tried again on the next connection. ``checked`` addresses are
    only tried (once a connection, for ``missing``), not followed."""

    endpoint: str
    missing: dict[str, str]

    def start(self) -> None: ...

    async def watch(
        self,
        addresses: list[str],
        listener: ValueListener,
        on_state: StateListener,
        labels: Mapping[str, str] | None = None,
        checked: Sequence[str] = (),
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
        self.attempts = 0  # failed attempts to connect (the loss itself included)
        self.log = log  # the driver's logger
        self.missing: dict[str, str] = {}  # watched addresses the PLC does not have -> what it said
        self._watched: dict[str, list[ValueListener]] = {}
        self._state_listeners: list[StateListener] = []
        self._ready = asyncio.Event()  # set once the first connection was made
        self._labels: dict[str, str] = {}
        self._checked: dict[str, None] = {}  # tried once a connection, not followed

    def _listen(
        self,
        addresses: list[str],
        listener: ValueListener,
        on_state: StateListener,
        labels: Mapping[str, str] | None,
        checked: Sequence[str] = (),
    ) -> None:
        self._checked.update(dict.fromkeys(a for a in checked if a not in addresses))
        for address in addresses:
            self._watched.setdefault(address, []).append(listener)
        self._state_listeners.append(on_state)
        self._labels.update(labels or {})

    def tried(self) -> list[str]:
        """Every address a connection tries: the watched, then the checked."""
        return [*self._watched, *(a for a in self._checked if a not in self._watched)]

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

    def _report_lost(self) -> None:
        """The connection went: one WARNING."""
        self.attempts += 1
        self.log.warning("the PLC at %s: %s (retrying)", self.endpoint, LOST)
        self.last_error = LOST

    def _report_failed(self, reason: str, unreachable: bool) -> None:
        """An attempt to connect failed: each new reason once. Not reaching the PLC while it is away
        is INFO (the WARNING was said when it went, or at the first attempt); anything else (a tag
        the PLC lacks, a refused login) is a WARNING."""
        self.attempts += 1
        if reason == self.last_error:
            return
        level = logging.INFO if unreachable and self.last_error else logging.WARNING
        self.log.log(level, "the PLC at %s: %s (retrying)", self.endpoint, reason)
        self.last_error = reason

    def _announce(self) -> None:
        """Connected (again)."""
        if self.last_error:
            self.log.info("the PLC at %s answers again", self.endpoint)
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


_UNSET = object()


class Connection(Protocol):
    """A transport's connection to one PLC, as a ``PolledLink`` uses it."""

    @property
    def connected(self) -> bool: ...

    async def connect(self) -> bool:
        """Try once; True when connected."""
        ...


class PolledLink(Listeners, ABC):
    """A ``TagLink`` that polls: every ``interval`` it reads the watched addresses the PLC has (the
    transport groups them into blocks), delivers the values that changed, and reconnects with backoff
    (0.5 s doubling to 2 s) when the PLC stops answering. A transport gives its connection and says
    how to parse an address, read addresses and write them."""

    def __init__(self, conn: Connection, endpoint: str, interval: float) -> None:
        super().__init__()
        self.conn, self.endpoint, self.interval = conn, endpoint, interval
        self.users = 0
        self._last: dict[str, Any] = {}
        self._task: asyncio.Task[None] | None = None
        self._parsed: dict[str, Any] = {}

    @property
    def link_up(self) -> bool:
        return self.conn.connected

    async def connect(self) -> bool:
        return await self.conn.connect()

    def parsed(self, address: str) -> Any:
        """``address`` as the transport parses it (once)."""
        found = self._parsed.get(address)
        if found is None:
            found = self._parsed[address] = self.parse(address)
        return found

    # -- what a transport provides ----------------------------------------------------------------

    @abstractmethod
    def parse(self, address: str) -> Any:
        """The transport's form of an address string."""

    @abstractmethod
    async def _read(self, addresses: list[str]) -> list[Any]:
        """The values of ``addresses`` (CommunicationError when the PLC refuses or does not answer)."""

    @abstractmethod
    async def _write(self, writes: list[tuple[str, Any, str]]) -> None:
        """The values, in order (the transport groups neighbours into one request)."""

    # -- TagLink ----------------------------------------------------------------------------------

    def start(self) -> None:
        if self._task is None:
            self._task = asyncio.get_running_loop().create_task(self._run(), name=f"plc {self.endpoint}")

    async def watch(
        self,
        addresses: list[str],
        listener: ValueListener,
        on_state: StateListener,
        labels: Mapping[str, str] | None = None,
        checked: Sequence[str] = (),
    ) -> None:
        self._labels.update(labels or {})
        if self.connected:  # another unit on this PLC connected it already: these values now (and the
            try:  # tags it lacks found) before the polls include them
                await self._first_read([*addresses, *checked], listener)
            except CommunicationError as exc:
                log.warning("the PLC at %s: %s", self.endpoint, exc)
        self._listen(addresses, listener, on_state, labels, checked)
        if self.connected:
            on_state(True)

    async def read(self, address: str) -> Any:
        (value,) = await self.read_many([address])
        return value

    async def read_many(self, addresses: list[str]) -> list[Any]:
        if not self.connected:
            raise CommunicationError(f"no connection to the PLC at {self.endpoint}")
        values: list[Any] = await self._io(self._read(addresses))
        return values

    async def write(self, address: str, value: Any, type_name: str) -> None:
        await self.write_many([(address, value, type_name)])

    async def write_many(self, writes: list[tuple[str, Any, str]]) -> None:
        if not self.connected:
            raise CommunicationError(f"no connection to the PLC at {self.endpoint}")
        await self._io(self._write(writes))

    async def close(self) -> None:
        await stop_task(self._task)

    # -- the loop ---------------------------------------------------------------------------------

    async def _io(self, request: Any) -> Any:
        try:
            return await request
        except CommunicationError:
            if not self.link_up:
                self._set_connected(False)
            raise

    async def _run(self) -> None:
        await keep_trying(self._session)

    async def _session(self) -> bool:
        """Connect, read every tag once, then poll until the PLC stops answering; True if it was up."""
        up = False
        try:
            if not self.link_up and not await self.connect():
                raise NoAnswer(f"{self.endpoint}: no answer")
            self.missing.clear()
            await self._first_read(self.tried(), None)
            self._announce()
            up = True
            while self.link_up:
                await asyncio.sleep(self.interval)
                await self._poll()
            self._report_lost()  # a unit's read or write found it gone
        except CommunicationError as exc:
            lost = isinstance(exc, NoAnswer) or not self.link_up
            if up and lost:
                self._report_lost()
            else:
                self._report_failed(str(exc).removeprefix(f"{self.endpoint}: "), unreachable=lost)
        self._set_connected(False)
        return up

    async def _first_read(self, addresses: list[str], listener: ValueListener | None) -> None:
        """Each of ``addresses`` once, delivered (to ``listener``, else to every part watching it). When
        the PLC refuses the block, each is read alone: one it refuses goes to ``missing`` with what it
        said (one request each, once a connection)."""
        try:
            values: list[Any] = await self._read(addresses)
        except CommunicationError:
            if not self.link_up:
                raise
            values = []
            for address in addresses:
                try:
                    values += await self._read([address])
                except CommunicationError as exc:
                    if not self.link_up:
                        raise
                    self.missing[address] = str(exc).rpartition(": ")[2]
                    values.append(_UNSET)
        for address, value in zip(addresses, values, strict=True):
            if value is _UNSET:
                continue
            self._last[address] = value
            if listener is not None:
                listener(address, value)
            else:
                self._deliver(address, value)

    async def _poll(self) -> None:
        addresses = self.present()
        try:
            values = await self._read(addresses)
        except CommunicationError:
            if not self.link_up:
                raise
            await self._first_read(addresses, None)  # the PLC refused one: it goes to ``missing``
            return
        for address, value in zip(addresses, values, strict=True):
            if self._last.get(address, _UNSET) != value:
                self._last[address] = value
                self._deliver(address, value)


class SharedLinks(SharedPool[Hashable, PolledLink]):
    """One ``PolledLink`` (one connection) per PLC, shared by its units: they must agree on the poll
    interval and the timeout (a ValueError names the part and the setting that differs)."""

    def __init__(self) -> None:
        super().__init__(lambda link: link.close(), lambda link: link.endpoint, unit_conflict)

    def link(
        self, part: str, key: Hashable, interval: float, timeout: float, make: Callable[[], PolledLink]
    ) -> PolledLink:
        return self.get(key, make, part, interval=interval, timeout=timeout)
