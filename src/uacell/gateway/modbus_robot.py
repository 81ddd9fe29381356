"""Runs the robot signal operations (``signals.SignalOp``) over a Modbus connection.

This is the I/O half of the modbus-signals driver: read the status bits into a ``RobotStatus``,
perform an operation (writes, then status reads until confirmed, pulse ends written on the way).
A transport failure becomes ``CallError("BadCommunicationError")``; nothing is retried or queued.
"""

from __future__ import annotations

import asyncio
import time
from collections.abc import Callable, Mapping

from uacell.errors import CallError
from uacell.gateway.codec import RegisterType
from uacell.gateway.handshake import Write
from uacell.gateway.modbus import CommunicationError, ModbusConnection, ModbusTag
from uacell.gateway.signals import DEFAULT_MAP, RobotStatus, SignalOp

STATUS_SIGNALS = (
    "remote_ready",
    "drives_are_on",
    "running",
    "program_end",
    "at_start",
    "fault",
    "program_echo",
    "fault_code",
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


class ModbusRobotIO:
    def __init__(
        self,
        conn: ModbusConnection,
        unit: int,
        tags: Mapping[str, ModbusTag],
        poll: float = 0.01,
        clock: Callable[[], float] = time.monotonic,
        by_name: bool = False,
    ) -> None:
        self.conn, self.unit, self.tags, self.poll, self.clock = conn, unit, tags, poll, clock
        # the name's echo is read only when some program is selected by name (a controller without
        # those registers would answer every status read with an error otherwise)
        self.signals = (*STATUS_SIGNALS, "program_name_echo") if by_name else STATUS_SIGNALS

    async def status(self) -> RobotStatus:
        """The controller's status now; ``connected=False`` when it cannot be read."""
        try:
            if not self.conn.connected and not await self.conn.connect():
                return RobotStatus(connected=False)
            values = {name: await self.conn.read(self.tags[name], self.unit) for name in self.signals}
        except CommunicationError:
            return RobotStatus(connected=False)
        return RobotStatus(**values)  # type: ignore[arg-type]

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
        try:
            await self._write(op.writes)
            try:
                while True:
                    await self._write(op.pulse_end(self.clock()))
                    if op.observe(await self.status(), self.clock()):
                        return
                    await asyncio.sleep(self.poll)
            finally:
                await self._write(op.pulse_end(float("inf")) if op.done else ())
        except CommunicationError as exc:
            raise CallError("BadCommunicationError", f"{op.name}: {exc}") from None
