"""Runs the robot signal operations (``signals.SignalOp``) over a Modbus connection.

This is the I/O half of the modbus-signals driver: read the status bits into a ``RobotStatus``,
perform an operation (writes, then status reads until confirmed, pulse ends written on the way).
A transport failure becomes ``CallError("BadCommunicationError")``; nothing is retried or queued.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from uacell.core.errors import CallError
from uacell.gateway.codec import RegisterType
from uacell.gateway.errors import CommunicationError
from uacell.gateway.handshake import Write
from uacell.gateway.modbus import SHARED, ModbusConnection, ModbusTag, spans
from uacell.gateway.signal_robot import perform
from uacell.gateway.signals import (
    DEFAULT_MAP,
    NAME_SIGNALS,
    SAFETY_SIGNALS,
    STATUS_SIGNALS,
    UNITS,
    RobotStatus,
    SignalOp,
)


def signal_tags(overrides: Mapping[str, tuple[str, int, str]] | None = None) -> dict[str, ModbusTag]:
    """The default map with ``overrides`` (signal -> (table, address, type)); unknown signals refused.
    A string's type names its length in registers: ``"string:8"`` (16 ASCII characters)."""
    entries = dict(DEFAULT_MAP)
    for name, entry in (overrides or {}).items():
        if name not in entries:
            raise ValueError(f"{name}: not a signal of the map ({', '.join(DEFAULT_MAP)})")
        entries[name] = entry
    return {name: ModbusTag(table, address, register_type(kind)) for name, (table, address, kind) in entries.items()}


def register_type(kind: str) -> RegisterType:
    """``"uint16"``, ``"bool"``, ... or ``"string:<registers>"``."""
    name, _, length = kind.partition(":")
    if name == "string":
        if not length.isdigit():
            raise ValueError(f"type {kind!r}: a string needs its length in registers, e.g. 'string:8'")
        return RegisterType("string", length=int(length))
    return RegisterType(kind)


@dataclass(frozen=True)
class MotionMap:
    """Where the axes' actual positions (and speeds) are: axis i's value at ``position``'s address plus
    i times its register count; a raw value times ``scale`` is in ``unit`` (per second for a speed)."""

    position: ModbusTag
    speed: ModbusTag | None = None
    scale: float = 1.0
    speed_scale: float = 1.0
    unit: str = "deg"

    def tags(self, axes: int) -> dict[str, ModbusTag]:
        out = {}
        for kind, first in (("position", self.position), ("speed", self.speed)):
            if first is not None:
                for i in range(axes):
                    out[f"axis{i + 1}.{kind}"] = ModbusTag(first.table, first.address + i * first.count, first.rtype)
        return out


MOTION_KEYS = ("position", "speed", "scale", "speed_scale", "unit")


def parse_motion(table: Mapping[str, Any]) -> MotionMap:
    """The ``motion`` setting: ``{ position = ["input", 20, "int16"], speed = [...], scale = 0.01,
    speed_scale = 0.01, unit = "deg" }``; ValueError naming what is wrong."""
    unknown = sorted(set(table) - set(MOTION_KEYS))
    if unknown:
        raise ValueError(f"motion has no key {unknown[0]!r} (it knows {', '.join(MOTION_KEYS)})")
    if "position" not in table:
        raise ValueError('motion needs position = ["input", <first register>, "<type>"]')

    def tag(entry: Any) -> ModbusTag:
        table_, address, kind = entry
        return ModbusTag(str(table_), int(address), register_type(str(kind)))

    unit = str(table.get("unit", "deg"))
    if unit not in UNITS:
        raise ValueError(f"motion unit {unit!r} is not one of {', '.join(UNITS)}")
    return MotionMap(
        position=tag(table["position"]),
        speed=tag(table["speed"]) if "speed" in table else None,
        scale=float(table.get("scale", 1.0)),
        speed_scale=float(table.get("speed_scale", 1.0)),
        unit=unit,
    )


def used_tags(
    tags: Mapping[str, ModbusTag], by_name: bool, safety: Sequence[str], motion: MotionMap | None, axes: int
) -> dict[str, ModbusTag]:
    """Every register the driver reads or writes: the map without the name signals unless a program is
    selected by name, without the safety signals ``map`` does not name, with the axes' registers."""
    used = {
        k: t for k, t in tags.items() if (by_name or k not in NAME_SIGNALS) and (k in safety or k not in SAFETY_SIGNALS)
    }
    if motion is not None:
        used.update(motion.tags(axes))
    return used


class ModbusRobotIO:
    def __init__(
        self,
        conn: ModbusConnection,
        unit: int,
        tags: Mapping[str, ModbusTag],
        poll: float = 0.01,
        clock: Callable[[], float] = time.monotonic,
        by_name: bool = False,
        safety: Sequence[str] = (),
        motion: MotionMap | None = None,
        axes: int = 0,
    ) -> None:
        self.conn, self.unit, self.tags, self.poll, self.clock = conn, unit, tags, poll, clock
        # the name's echo is read only when some program is selected by name (a controller without
        # those registers would answer every status read with an error otherwise); the safety
        # signals only when mapped
        self.signals = (*STATUS_SIGNALS, *(("program_name_echo",) if by_name else ()), *safety)
        self.motion, self.axes = motion, axes
        self._read = {name: tags[name] for name in self.signals}
        self._axis_tags = motion.tags(axes) if motion is not None else {}
        self._spans = spans([*self._read.values(), *self._axis_tags.values()], gap=0)

    @property
    def name(self) -> str:
        return self.conn.name

    async def close(self) -> None:
        await SHARED.release(self.conn)

    async def status(self) -> RobotStatus:
        """The controller's status now, in one read per block of adjacent registers; ``connected=False``
        when it cannot be read."""
        try:
            if not self.conn.connected and not await self.conn.connect():
                return RobotStatus(connected=False)
            blocks = [
                (span, await self.conn.read_block(span.table, span.start, span.count, self.unit))
                for span in self._spans
            ]
        except CommunicationError:
            return RobotStatus(connected=False)

        def value(tag: ModbusTag) -> Any:
            for span, block in blocks:
                if span.table == tag.table and span.start <= tag.address < span.start + span.count:
                    return tag.value_in(block, span.start)
            raise LookupError(tag)

        values = {name: value(tag) for name, tag in self._read.items()}
        if self.motion is not None:
            to_deg = UNITS[self.motion.unit]
            values["positions"] = tuple(
                float(value(self._axis_tags[f"axis{i + 1}.position"])) * self.motion.scale * to_deg
                for i in range(self.axes)
            )
            if self.motion.speed is not None:
                values["speeds"] = tuple(
                    float(value(self._axis_tags[f"axis{i + 1}.speed"])) * self.motion.speed_scale * to_deg
                    for i in range(self.axes)
                )
        return RobotStatus(**values)

    async def write_signal(self, signal: str, value: bool | int | str) -> None:
        """One signal written at once (CallError Bad_CommunicationError when it cannot be)."""
        try:
            await self.conn.write(self.tags[signal], value, self.unit)
        except CommunicationError as exc:
            raise CallError("BadCommunicationError", f"{signal}: {exc}") from None

    async def _write(self, writes: tuple[Write, ...]) -> None:
        for w in writes:
            await self.conn.write(self.tags[w.tag], w.value, self.unit)

    async def perform(self, op: SignalOp) -> None:
        """Write ``op``, wait for its confirmation; CallError with the op's code when it fails."""
        await perform(op, self._write, self.status, self.poll, self.clock)
