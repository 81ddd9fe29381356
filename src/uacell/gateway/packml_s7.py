"""The ``s7-packtags`` driver: a PackML unit in a Siemens S7 PLC (S7-300/400/1200/1500) whose PackTags
sit in a data block, reached over S7 communication (ISO-on-TCP, port 102) with python-snap7's
asyncio client (docs/equipment.md, "Gateway"; the unit itself is ``packml_plc.PackTagsUnit``).

    [[packml_units]]
    name = "Capper"
    equipment = { driver = "s7-packtags", host = "10.0.0.5", rack = 0, slot = 1, db = 10, start = 0 }

Each unit's PackTags sit in data block ``db`` from byte ``start`` (``LAYOUT``, 200 bytes a unit), by
absolute address: the block's optimized block access must be off. Every tag is overridable with
``map = { "Status.StateCurrent" = "DB7.DBD20" }``. One connection per PLC (host, port, rack, slot),
shared by every unit on it; the link polls what the units watch every ``interval`` (one read per
block of nearby bytes); a command's tags go in one S7 write job (``s7.write_job``), each bit as a
bit item, the change request last. The driver reads nothing but the data block (not the CPU's
run/stop state: a PLC in STOP stops scanning, and its requests are not taken: Bad_Timeout).
"""

from __future__ import annotations

import asyncio
import contextlib
from collections.abc import Mapping
from typing import Any

from snap7.async_client import AsyncClient
from snap7.error import S7Error, S7ProtocolError

from uacell.gateway import DriverSettings
from uacell.gateway.errors import CommunicationError
from uacell.gateway.link import PolledLink, SharedLinks
from uacell.gateway.packml_plc import UNIT_SETTINGS, PackTagsUnit, start_unit
from uacell.gateway.packtags import DEFAULT_MAP, ResolvedTag, Where
from uacell.gateway.s7 import S7Address, S7AddressError, byte_spans, write_items, write_job, write_results

SETTINGS = ("host", "port", "rack", "slot", "db", "start", "interval", "timeout", *UNIT_SETTINGS)
UNIT_BYTES = 200  # a unit's bytes in the default layout
# tag -> (byte offset from start, bit, S7 type): the default layout of one unit
LAYOUT: dict[str, tuple[int, int, str]] = {
    "Status.StateCurrent": (0, 0, "DINT"),
    "Status.UnitModeCurrent": (4, 0, "DINT"),
    "Status.CurMachSpeed": (8, 0, "REAL"),
    "Status.MachSpeed": (12, 0, "REAL"),
    "Admin.ProdProcessedCount": (16, 0, "DINT"),
    "Admin.ProdDefectiveCount": (20, 0, "DINT"),
    "Admin.StopReason": (24, 0, "DINT"),
    "Command.CntrlCmd": (28, 0, "DINT"),
    "Command.UnitMode": (32, 0, "DINT"),
    "Command.MachSpeed": (36, 0, "REAL"),
    "Command.CmdChangeRequest": (40, 0, "BOOL"),
    "Command.UnitModeChangeRequest": (40, 1, "BOOL"),
}
ALARMS_AT, ALARM_ROOM = 42, 8  # Admin.Alarm[i].ID: DINT at start + 42 + 4i
PARAMETERS_AT, PARAMETER_ROOM = 74, 20  # Command.Parameter[i].Value: REAL at start + 74 + 4i
# bytes start + 154 .. start + 199 are the PLC's own (the example PLC keeps its test switches there)
# the S7 types a PackTags type may be kept in
FITS = {"Int32": ("DINT", "INT", "BYTE"), "Float": ("REAL", "DINT", "INT"), "Boolean": ("BOOL",)}
PREFERRED = {"Int32": "DINT", "Float": "REAL", "Boolean": "BOOL"}  # what a DBD holds unless said


def resolve_s7(
    part: str,
    db: int,
    start: int = 0,
    overrides: Mapping[str, Any] | None = None,
    parameters: int = 5,
    alarms: int = 0,
) -> dict[str, ResolvedTag]:
    """Every tag of the map as an absolute address: ``LAYOUT`` in ``db`` from byte ``start``, then
    ``overrides`` (tag -> "DB7.DBD20", "DB7.DBD20 DINT", "DB7.DBX3.0"). A ValueError names the part,
    the tag and what is wrong."""
    if not 0 <= parameters <= PARAMETER_ROOM or not 0 <= alarms <= ALARM_ROOM:
        raise ValueError(
            f"{part}: the layout has room for {PARAMETER_ROOM} parameters and {ALARM_ROOM} alarms, "
            f"not {parameters} and {alarms}"
        )
    types = {k: t for k, (_, t) in DEFAULT_MAP.items()}
    entries = {k: S7Address(db, start + offset, bit, kind) for k, (offset, bit, kind) in LAYOUT.items()}
    for i in range(parameters):
        entries[f"Command.Parameter[{i}].Value"] = S7Address(db, start + PARAMETERS_AT + 4 * i, 0, "REAL")
    for i in range(alarms):
        entries[f"Admin.Alarm[{i}].ID"] = S7Address(db, start + ALARMS_AT + 4 * i, 0, "DINT")
    out = {}
    for key, address in entries.items():
        type_name = types.get(key, "Float" if key.startswith("Command.Parameter[") else "Int32")
        given = (overrides or {}).get(key)
        if given is not None:
            if not isinstance(given, str):
                raise ValueError(f'{part}: map: {key} = {given!r}: needs an address such as "DB7.DBD20"')
            try:
                address = S7Address.parse(given, PREFERRED[type_name] if ".DBD" in given.upper() else "")
            except S7AddressError as e:
                raise ValueError(f"{part}: map: {key}: {e}") from None
            if address.kind not in FITS[type_name]:
                raise ValueError(f"{part}: map: {key}: a {address.kind} cannot hold the {type_name} the tag is")
        out[key] = ResolvedTag(key, str(address), type_name)
    unknown = sorted(set(overrides or {}) - set(entries))
    if unknown:
        raise ValueError(f"{part}: map: {unknown[0]}: not a PackTags tag of the map")
    return out


def _stream(client: AsyncClient) -> asyncio.StreamWriter | None:
    """The stream python-snap7's client writes to, if it opened one."""
    writer: asyncio.StreamWriter | None = getattr(getattr(client, "connection", None), "_writer", None)
    return writer


def _close_stream(client: AsyncClient) -> None:
    writer = _stream(client)
    if writer is not None:
        writer.close()


async def _disconnect(client: AsyncClient) -> None:
    """snap7's disconnect (at most a second), then its stream closed whatever happened: snap7 forgets
    the stream without closing it when its disconnect is cut short (by the timeout, or by a
    cancellation of the task closing the link), and a stream nobody closed is a leaked socket."""
    writer = _stream(client)
    try:
        with contextlib.suppress(Exception):
            await asyncio.wait_for(client.disconnect(), 1.0)
    finally:
        if writer is not None:
            writer.close()


class S7Connection:
    """One S7 connection (python-snap7's ``AsyncClient``): reads of data block bytes and write jobs,
    each bounded by ``timeout``; a failure other than a refused address drops the connection."""

    def __init__(self, host: str, port: int, rack: int, slot: int, timeout: float) -> None:
        self.host, self.port, self.rack, self.slot, self.timeout = host, port, rack, slot, timeout
        self._client: AsyncClient | None = None

    @property
    def name(self) -> str:
        return f"s7://{self.host}:{self.port} rack {self.rack} slot {self.slot}"

    @property
    def connected(self) -> bool:
        return self._client is not None

    async def connect(self) -> bool:
        client = AsyncClient()
        try:
            await asyncio.wait_for(client.connect(self.host, self.rack, self.slot, self.port), self.timeout)
        except (S7Error, OSError, TimeoutError):
            await _disconnect(client)
            return False
        except BaseException:
            # Cancelled while connecting (the link closing): snap7 closes its stream on errors only, so
            # the socket it opened is closed here, or it would stay open until collected.
            _close_stream(client)
            raise
        self._client = client
        return True

    async def close(self) -> None:
        client, self._client = self._client, None
        if client is not None:
            await _disconnect(client)

    async def read(self, db: int, start: int, count: int) -> bytearray:
        client = self._usable()
        try:
            data: bytearray = await asyncio.wait_for(client.db_read(db, start, count), self.timeout)
            return data
        except S7ProtocolError as exc:
            raise await self._failed(exc, f"DB{db} bytes {start}..{start + count - 1}") from None
        except (S7Error, OSError, TimeoutError, ConnectionError) as exc:
            raise await self._failed(exc, "") from None

    async def write(self, writes: list[tuple[S7Address, object]]) -> None:
        """One write job with every write, in order (a bit item for each BOOL)."""
        client = self._usable()
        try:
            items = write_items(writes)
        except S7AddressError as exc:
            raise CommunicationError(f"{self.name}: {exc}") from None
        try:
            framing = client.protocol  # snap7's S7Protocol: the PDU references of the client's own jobs
            reference = framing._next_sequence()
            response = await asyncio.wait_for(client._send_receive(write_job(reference, items)), self.timeout)
        except (S7Error, OSError, TimeoutError, ConnectionError) as exc:
            raise await self._failed(exc, "") from None
        if response.get("error_code"):
            raise CommunicationError(f"{self.name}: the write job was refused (error 0x{response['error_code']:04x})")
        for item, result in zip(items, write_results(bytes(response.get("raw_data", b"")), len(items)), strict=True):
            if result:
                where = (
                    f"DB{item.db}.DBX{item.byte}.{item.bit}"
                    if item.bit is not None
                    else f"DB{item.db} byte {item.byte}"
                )
                raise CommunicationError(f"{self.name}: {where}: {result}")

    def _usable(self) -> AsyncClient:
        if self._client is None:
            raise CommunicationError(f"{self.name}: not connected")
        return self._client

    async def _failed(self, exc: BaseException, where: str) -> CommunicationError:
        """A refused address leaves the connection up (the PLC answered); anything else drops it."""
        text = str(exc) or type(exc).__name__
        if isinstance(exc, S7ProtocolError) and "operation failed" in text:
            return CommunicationError(f"{self.name}: {where}: {text.rpartition(': ')[2]}")
        await self.close()
        return CommunicationError(f"{self.name}: {text}")


class S7TagLink(PolledLink):
    """The ``TagLink`` of one S7 PLC: polls the watched addresses, reconnects with backoff."""

    conn: S7Connection

    def __init__(self, conn: S7Connection, interval: float) -> None:
        super().__init__(conn, conn.name, interval)

    def parse(self, address: str) -> S7Address:
        return S7Address.parse(address)

    def address(self, text: str) -> S7Address:
        a: S7Address = self.parsed(text)
        return a

    async def _read(self, addresses: list[str]) -> list[Any]:
        """The values of ``addresses``, one read per block of nearby bytes of a data block."""
        wanted = [self.address(a) for a in addresses]
        values: dict[S7Address, Any] = {}
        for span in byte_spans(wanted):
            block = await self.conn.read(span.db, span.start, span.count)
            for a in wanted:
                if a.db == span.db and span.start <= a.byte < span.start + span.count:
                    values[a] = a.decode(block, span.start)
        return [values[a] for a in wanted]

    async def _write(self, writes: list[tuple[str, Any, str]]) -> None:
        await self.conn.write([(self.address(a), v) for a, v, _ in writes])

    async def close(self) -> None:
        await super().close()
        await self.conn.close()


POOL = SharedLinks()  # one connection per PLC: host, port, rack and slot


def where(part: str, settings: Mapping[str, Any]) -> Where:
    """The driver's settings, checked (a ValueError names the part and the setting)."""
    s = DriverSettings("s7-packtags", part, settings, SETTINGS)
    host = s.host("the PLC")
    map_ = s.table("map", 'a table of tag = "DB<n>.DBD<byte>"')
    tags = resolve_s7(
        part,
        s.whole("db", 1, 1, 65535),
        s.whole("start", 0, 0, 65535 - UNIT_BYTES),
        map_,
        parameters=s.whole("parameters", 5, 0, PARAMETER_ROOM),
        alarms=s.whole("alarms", 0, 0, ALARM_ROOM),
    )
    port, rack, slot = s.whole("port", 102, 1, 65535), s.whole("rack", 0, 0, 7), s.whole("slot", 1, 0, 31)
    endpoint = f"s7://{host}:{port} rack {rack} slot {slot}"
    return Where(endpoint, host, port, *s.polling(), tags, rack=rack, slot=slot)


async def s7_packtags(spec: Any) -> PackTagsUnit:
    """The equipment factory of the ``s7-packtags`` driver."""
    w = where(spec.part, spec.settings)
    link = POOL.link(
        spec.part,
        (w.host, w.port, w.rack, w.slot),
        w.interval,
        w.timeout,
        lambda: S7TagLink(S7Connection(w.host, w.port, w.rack, w.slot, w.timeout), w.interval),
    )
    return await start_unit(spec.part, link, w.tags, spec.settings, POOL.release)
