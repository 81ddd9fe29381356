"""The ``logix-packtags`` driver: a PackML unit in a Rockwell ControlLogix / CompactLogix controller
whose PackTags are Logix tags, reached over EtherNet/IP (CIP) with pylogix (docs/equipment.md,
"Gateway"; the unit itself is ``packml_plc.PackTagsUnit``).

    [[packml_units]]
    name = "Capper"
    equipment = { driver = "logix-packtags", host = "10.0.0.7", slot = 0, prefix = "Capper" }

A tag is ``<prefix>.<path>``: the unit is one controller tag of a PackTags UDT whose members are
``Command``, ``Status`` and ``Admin`` (Rockwell's PackML templates: ``Capper.Command.CntrlCmd``,
``Capper.Status.StateCurrent``, ``Capper.Command.Parameter[0].Value``, ``Capper.Admin.Alarm[2].ID``),
every tag overridable with ``map = { "Status.StateCurrent" = "Line1_State" }`` (a program tag:
``Program:Packer.State``). pylogix, not pycomm3: it reads and writes tags by symbolic name in one
Multiple Service Packet, needs no tag list upload first, and is pure Python (pycomm3's LogixDriver
insists on uploading the controller's tag list and program list when it opens, which cpppo's
simulator, the test counterpart, cannot answer). pylogix is synchronous: every request runs in a
worker thread, one at a time per connection, bounded by ``timeout``.
"""

from __future__ import annotations

import asyncio
import contextlib
import threading
from collections.abc import Callable, Mapping
from typing import Any, TypeVar

from pylogix import PLC

from uacell.gateway import DriverSettings
from uacell.gateway.errors import CommunicationError
from uacell.gateway.link import PolledLink, SharedLinks
from uacell.gateway.packml_plc import UNIT_SETTINGS, PackTagsUnit, start_unit
from uacell.gateway.packtags import PackTagsMapError, Where, resolve

SETTINGS = ("host", "port", "slot", "prefix", "interval", "timeout", *UNIT_SETTINGS)
# what a controller answers for a tag it does not have (CIP general status 0x04, 0x05)
NO_SUCH_TAG = ("Path segment error", "Path destination unknown")
T = TypeVar("T")
MOST = 20  # tags in one Multiple Service Packet (it must fit one CIP message of 500 bytes)


class LogixConnection:
    """One EtherNet/IP session to a controller (pylogix ``PLC``), its requests in a worker thread,
    one at a time."""

    def __init__(self, host: str, port: int, slot: int, timeout: float) -> None:
        self.host, self.port, self.slot, self.timeout = host, port, slot, timeout
        self._plc = PLC(host, slot=slot, timeout=timeout, port=port)
        self._lock = threading.Lock()
        self.connected = False
        # Set by close: work still queued for the thread then does nothing. pylogix reconnects by
        # itself inside Read and Write, so a request that waited for the lock behind close would
        # otherwise open a socket nobody closes.
        self._closed = False

    @property
    def name(self) -> str:
        return f"logix://{self.host}:{self.port} slot {self.slot}"

    async def connect(self) -> bool:
        def attempt() -> bool:
            ok, _status = self._plc.conn.connect()  # a new socket (pylogix closes the old one)
            return bool(ok)

        self.connected = await asyncio.to_thread(self._locked, attempt)
        return self.connected

    def _locked(self, work: Callable[[], T]) -> T:
        """``work`` in the worker thread, alone on the connection, unless the connection was closed."""
        with self._lock:
            if self._closed:
                raise CommunicationError(f"{self.name}: closed")
            return work()

    def close(self) -> None:
        with self._lock:
            self._closed = True
            self._plc.Close()
            for sock in (self._plc.conn.Socket, self._plc.conn.msg_socket):  # pylogix leaves them open
                with contextlib.suppress(OSError):
                    sock.close()
        self.connected = False

    async def read(self, names: list[str]) -> list[Any]:
        """The values of ``names`` (Multiple Service Packets of up to ``MOST`` tags)."""

        def run() -> list[Any]:
            out: list[Any] = []
            for i in range(0, len(names), MOST):
                chunk = names[i : i + MOST]
                got = self._plc.Read(chunk if len(chunk) > 1 else chunk[0])
                out += got if isinstance(got, list) else [got]
            return out

        responses = await self._run(run)
        values = []
        for name, response in zip(names, responses, strict=True):
            self._check(name, str(response.Status))
            values.append(response.Value)
        return values

    async def write(self, writes: list[tuple[str, Any]]) -> None:
        """Every write in one Multiple Service Packet, in order (the change request last)."""

        def run() -> list[Any]:
            if len(writes) == 1:
                return [self._plc.Write(*writes[0])]
            got: list[Any] = self._plc.Write([(n, v) for n, v in writes])
            return got

        for (name, _), response in zip(writes, await self._run(run), strict=True):
            self._check(name, str(response.Status))

    async def _run(self, work: Callable[[], T]) -> T:
        if not self.connected:
            raise CommunicationError(f"{self.name}: not connected")
        try:
            return await asyncio.wait_for(asyncio.to_thread(self._locked, work), self.timeout * 2)
        except (TimeoutError, OSError) as exc:
            self.connected = False
            raise CommunicationError(f"{self.name}: {exc or type(exc).__name__}") from None

    def _check(self, name: str, status: str) -> None:
        if status == "Success":
            return
        if status in NO_SUCH_TAG and self._plc.conn.SocketConnected:
            raise CommunicationError(f"{self.name}: {name}: {status}")
        self.connected = False  # anything else: the session is gone
        raise CommunicationError(f"{self.name}: {status}")


class LogixTagLink(PolledLink):
    """The ``TagLink`` of one controller: polls the watched tags, reconnects with backoff."""

    conn: LogixConnection

    def __init__(self, conn: LogixConnection, interval: float) -> None:
        super().__init__(conn, conn.name, interval)

    def parse(self, address: str) -> str:
        return address

    async def _read(self, addresses: list[str]) -> list[Any]:
        return await self.conn.read(addresses)

    async def _write(self, writes: list[tuple[str, Any, str]]) -> None:
        await self.conn.write([(a, float(v) if t == "Float" else v) for a, v, t in writes])

    async def close(self) -> None:
        await super().close()
        await asyncio.to_thread(self.conn.close)


def where(part: str, settings: Mapping[str, Any]) -> Where:
    """The driver's settings, checked (a ValueError names the part and the setting)."""
    s = DriverSettings("logix-packtags", part, settings, SETTINGS)
    host = s.host("the controller")
    map_ = s.table("map", 'a table of tag = "<Logix tag name>"')
    if not all(isinstance(v, str) for v in map_.values()):
        raise ValueError(f'{part}: map: a table of tag = "<Logix tag name>", not {map_!r}')
    prefix = s.text("prefix")
    if prefix.startswith("/") or ";" in prefix:
        raise ValueError(f"{part}: prefix: {prefix!r} is not a Logix tag name (Capper, Program:Packer.Capper)")
    try:
        tags = resolve(
            part,
            prefix,
            {str(k): v for k, v in map_.items()},
            parameters=s.whole("parameters", 5, 0, 100),
            alarms=s.whole("alarms", 0, 0, 100),
        )
    except PackTagsMapError as e:
        raise ValueError(str(e)) from None
    port, slot = s.whole("port", 44818, 1, 65535), s.whole("slot", 0, 0, 31)
    return Where(f"logix://{host}:{port} slot {slot}", host, port, *s.polling(), tags, slot=slot)


POOL = SharedLinks()  # one session per controller: host, port and slot


async def logix_packtags(spec: Any) -> PackTagsUnit:
    """The equipment factory of the ``logix-packtags`` driver."""
    w = where(spec.part, spec.settings)
    link = POOL.link(
        spec.part,
        (w.host, w.port, w.slot),
        w.interval,
        w.timeout,
        lambda: LogixTagLink(LogixConnection(w.host, w.port, w.slot, w.timeout), w.interval),
    )
    return await start_unit(spec.part, link, w.tags, spec.settings, POOL.release)
