"""The ``modbus-packtags`` driver: a PackML unit in a PLC whose PackTags the PLC keeps in Modbus/TCP
registers (docs/equipment.md, "Gateway"; the unit itself is ``packml_plc.PackTagsUnit``).

    [[packml_units]]
    name = "Capper"
    equipment = { driver = "modbus-packtags", host = "10.0.0.5", unit = 1, base = 0 }

Each unit's PackTags sit in holding registers from ``base`` (``LAYOUT``, 100 registers a unit), every
tag overridable with ``map = { "Status.StateCurrent" = ["input", 7, "int32"] }``; ``byte_order`` and
``word_order`` say how the PLC lays out 32-bit values. The link polls what the units watch every
``interval`` (one request per block of nearby registers, ``modbus.spans``), one connection per host
and port shared with every other part on it (robots included); a command's tags are written in
order, neighbouring registers in one request (``Command.CntrlCmd`` and ``Command.CmdChangeRequest``
reach the PLC together).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

from uacell.gateway import DriverSettings
from uacell.gateway.codec import CodecError, RegisterType
from uacell.gateway.errors import CommunicationError
from uacell.gateway.link import PolledLink
from uacell.gateway.modbus import SHARED, ModbusConnection, ModbusTag, endpoint_name, spans
from uacell.gateway.packml_plc import UNIT_SETTINGS, PackTagsUnit, start_unit
from uacell.gateway.packtags import DEFAULT_MAP, ResolvedTag, Where
from uacell.gateway.pool import SharedPool

SETTINGS = ("host", "port", "unit", "base", "interval", "timeout", "byte_order", "word_order", *UNIT_SETTINGS)
UNIT_REGISTERS = 100  # a unit's block of holding registers in the default layout
# tag -> (table, register offset from base, type): the default layout of one unit
LAYOUT: dict[str, tuple[str, int, str]] = {
    "Status.StateCurrent": ("holding", 0, "int32"),
    "Status.UnitModeCurrent": ("holding", 2, "int32"),
    "Status.CurMachSpeed": ("holding", 4, "float32"),
    "Status.MachSpeed": ("holding", 6, "float32"),
    "Admin.ProdProcessedCount": ("holding", 8, "int32"),
    "Admin.ProdDefectiveCount": ("holding", 10, "int32"),
    "Admin.StopReason": ("holding", 12, "int32"),
    "Command.CntrlCmd": ("holding", 14, "int32"),
    "Command.CmdChangeRequest": ("holding", 16, "bool"),
    "Command.UnitMode": ("holding", 18, "int32"),
    "Command.UnitModeChangeRequest": ("holding", 20, "bool"),
    "Command.MachSpeed": ("holding", 22, "float32"),
}
ALARMS_AT, ALARM_ROOM = 24, 8  # Admin.Alarm[i].ID: int32 at base + 24 + 2i
PARAMETERS_AT, PARAMETER_ROOM = 40, 20  # Command.Parameter[i].Value: float32 at base + 40 + 2i
# registers base + 80 .. base + 99 are the PLC's own (the example PLC keeps its test switches there)
# the Modbus types a PackTags type may be kept in
FITS = {
    "Int32": ("int16", "uint16", "int32", "uint32"),
    "Float": ("float32", "float64", "int16", "uint16", "int32", "uint32"),
    "Boolean": ("bool",),
}
WRITTEN = {k for k in DEFAULT_MAP if k.startswith("Command.")}


@dataclass(frozen=True)
class Point:
    """A tag of one device (Modbus unit id); its string form is the address a ``ResolvedTag`` holds."""

    device: int
    tag: ModbusTag

    def __str__(self) -> str:
        t = self.tag
        return f"unit {self.device} {t.table} {t.address} {t.rtype.name} {t.rtype.byte_order}/{t.rtype.word_order}"

    @classmethod
    def parse(cls, text: str) -> Point:
        _, device, table, address, name, orders = text.split(" ")
        byte_order, word_order = orders.split("/")
        rtype = RegisterType(name, byte_order=byte_order, word_order=word_order)  # type: ignore[arg-type]
        return cls(int(device), ModbusTag(table, int(address), rtype))


def resolve_modbus(
    part: str,
    device: int,
    base: int = 0,
    overrides: Mapping[str, Any] | None = None,
    parameters: int = 5,
    alarms: int = 0,
    byte_order: str = "big",
    word_order: str = "big",
) -> dict[str, ResolvedTag]:
    """Every tag of the map as a Modbus point: ``LAYOUT`` from ``base``, then ``overrides``
    (tag -> [table, address, type]). A ValueError names the part, the tag and what is wrong."""
    if not 0 <= parameters <= PARAMETER_ROOM or not 0 <= alarms <= ALARM_ROOM:
        raise ValueError(
            f"{part}: the layout has room for {PARAMETER_ROOM} parameters and {ALARM_ROOM} alarms, "
            f"not {parameters} and {alarms}"
        )
    entries = {k: (table, base + offset, kind) for k, (table, offset, kind) in LAYOUT.items()}
    for i in range(parameters):
        entries[f"Command.Parameter[{i}].Value"] = ("holding", base + PARAMETERS_AT + 2 * i, "float32")
    for i in range(alarms):
        entries[f"Admin.Alarm[{i}].ID"] = ("holding", base + ALARMS_AT + 2 * i, "int32")
    for key, entry in (overrides or {}).items():
        if key not in entries:
            raise ValueError(f"{part}: map: {key}: not a PackTags tag of the map")
        if not isinstance(entry, list | tuple) or len(entry) != 3 or not isinstance(entry[1], int):
            example = '["holding", 7, "int32"]'
            raise ValueError(f"{part}: map: {key} = {entry!r}: needs [table, address, type], e.g. {example}")
        entries[key] = (str(entry[0]), entry[1], str(entry[2]))
    types = {k: t for k, (_, t) in DEFAULT_MAP.items()}
    out = {}
    for key, (table, address, kind) in entries.items():
        type_name = types.get(key, "Float" if key.startswith("Command.Parameter[") else "Int32")
        if kind not in FITS[type_name]:
            raise ValueError(f"{part}: map: {key}: a {kind} cannot hold the {type_name} the tag is")
        try:
            tag = ModbusTag(table, address, RegisterType(kind, byte_order, word_order))  # type: ignore[arg-type]
        except (CodecError, ValueError) as e:
            raise ValueError(f"{part}: map: {key}: {e}") from None
        if (key in WRITTEN or key.startswith("Command.Parameter[")) and not tag.writable:
            raise ValueError(f"{part}: map: {key}: uacell writes this tag; {_article(table)} {table} cannot be written")
        out[key] = ResolvedTag(key, str(Point(device, tag)), type_name)
    return out


class ModbusTagLink(PolledLink):
    """The ``TagLink`` of one Modbus/TCP endpoint: polls the watched points, reconnects with backoff."""

    conn: ModbusConnection

    def __init__(self, conn: ModbusConnection, interval: float) -> None:
        super().__init__(conn, conn.name, interval)

    def parse(self, address: str) -> Point:
        return Point.parse(address)

    def point(self, address: str) -> Point:
        p: Point = self.parsed(address)
        return p

    async def _read(self, addresses: list[str]) -> list[Any]:
        """The values of ``addresses``, one request per block of nearby registers."""
        points = [self.point(a) for a in addresses]
        values: dict[Point, Any] = {}
        for device in sorted({p.device for p in points}):
            mine = [p for p in points if p.device == device]
            for span in spans([p.tag for p in mine]):
                block = await self.conn.read_block(span.table, span.start, span.count, device)
                for p in mine:
                    if p.tag.table == span.table and span.start <= p.tag.address < span.start + span.count:
                        values[p] = p.tag.value_in(block, span.start)
        return [values[p] for p in points]

    async def _write(self, writes: list[tuple[str, Any, str]]) -> None:
        """The values in order; neighbouring holding registers of one device in one request."""
        blocks: list[tuple[int, str, int, list[Any]]] = []  # (device, table, start, values)
        for address, value, _ in writes:
            p = self.point(address)
            t = p.tag
            try:
                words: list[Any] = [bool(value)] if t.table == "coil" else t.rtype.encode(value)
            except CodecError as e:
                raise CommunicationError(f"{self.endpoint}: {p}: {e}") from None
            last = blocks[-1] if blocks else None
            if last and t.table == "holding" == last[1] and last[0] == p.device and last[2] + len(last[3]) == t.address:
                last[3].extend(words)
            else:
                blocks.append((p.device, t.table, t.address, words))
        for device, table, start, values in blocks:
            await self.conn.write_block(table, start, values, device)

    async def close(self) -> None:
        await super().close()
        await SHARED.release(self.conn)


def _article(word: str) -> str:
    return "an" if word[0] in "aeiou" else "a"


# one link per host, port and poll interval, on the process's shared connection to that PLC
POOL: SharedPool[tuple[str, int, float], ModbusTagLink] = SharedPool(
    lambda link: link.close(), lambda link: link.endpoint
)


def modbus_link(host: str, port: int, interval: float, timeout: float = 1.0, part: str = "") -> ModbusTagLink:
    """The link a unit on ``host``:``port`` polls with; a ValueError if the connection has another timeout."""
    SHARED.check((host, port), part, timeout=timeout)
    return POOL.get(
        (host, port, interval), lambda: ModbusTagLink(SHARED.connection(host, port, timeout, part), interval), part
    )


def where(part: str, settings: Mapping[str, Any]) -> Where:
    """The driver's settings, checked (a ValueError names the part and the setting)."""
    s = DriverSettings("modbus-packtags", part, settings, SETTINGS)
    host = s.host("the PLC")
    map_ = s.table("map", "a table of tag = [table, address, type]")
    tags = resolve_modbus(
        part,
        s.whole("unit", 1, 0, 255),
        s.whole("base", 0, 0, 65535 - UNIT_REGISTERS),
        map_,
        parameters=s.whole("parameters", 5, 0, PARAMETER_ROOM),
        alarms=s.whole("alarms", 0, 0, ALARM_ROOM),
        byte_order=s.text("byte_order", "big"),
        word_order=s.text("word_order", "big"),
    )
    port = s.whole("port", 502, 1, 65535)
    return Where(endpoint_name(host, port), host, port, *s.polling(), tags)


async def modbus_packtags(spec: Any) -> PackTagsUnit:
    """The equipment factory of the ``modbus-packtags`` driver."""
    w = where(spec.part, spec.settings)
    link = modbus_link(w.host, w.port, w.interval, w.timeout, spec.part)
    return await start_unit(spec.part, link, w.tags, spec.settings, POOL.release)
