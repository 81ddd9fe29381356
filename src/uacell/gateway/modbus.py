"""Modbus/TCP transport (pymodbus client): one connection per (host, port), shared by every part.

Reads and writes typed tags (``codec.RegisterType``) in the four Modbus tables. A failed request
marks the connection lost and raises ``CommunicationError``; nothing is queued or retried here (the
driver decides, and never replays a command).

A PLC killed or out of reach is expected: the drivers say it once, and pymodbus's own records of it
("Failed to connect", "No response received", ...) are one DEBUG line each (``quiet_pymodbus``).
"""

from __future__ import annotations

import asyncio
import logging
from dataclasses import dataclass

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException

from uacell.core.logs import quiet_expected
from uacell.gateway.codec import RegisterType
from uacell.gateway.errors import CommunicationError, NoAnswer
from uacell.gateway.pool import SharedPool

TABLES = ("coil", "discrete", "holding", "input")


def endpoint_name(host: str, port: int) -> str:
    """How messages and tables name a Modbus/TCP endpoint."""
    return f"modbus://{host}:{port}"


# how pymodbus's client says that the server went away or cannot be reached
_LOST = (
    "Failed to connect",
    "Not connected, trying to connect!",
    "No response received",
    "Cancel send, because not connected!",
    "Connection to (",
)
_REPEATING = "Repeating...."  # pymodbus's stand-in for its previous message said again


class _PymodbusLost:
    """Which pymodbus records say the server is lost; "Repeating...." takes the fate of the record it repeats."""

    def __init__(self) -> None:
        self.last = False

    def __call__(self, record: logging.LogRecord) -> bool:
        message = str(record.msg)
        if message != _REPEATING:
            self.last = message.startswith(_LOST)
        return self.last


def quiet_pymodbus() -> None:
    """pymodbus's records of a lost server become DEBUG lines (``uacell.core.logs.ExpectedFaults``)."""
    quiet_expected("plc-lost", ("pymodbus.logging",), _PymodbusLost())


@dataclass(frozen=True)
class ModbusTag:
    table: str  # one of TABLES
    address: int
    rtype: RegisterType

    def __post_init__(self) -> None:
        if self.table not in TABLES:
            raise ValueError(f"table {self.table!r} is not one of {', '.join(TABLES)}")
        if self.table in ("coil", "discrete") and self.rtype.name != "bool":
            raise ValueError(f"a {self.table} holds a bool, not {self.rtype.name}")
        if not 0 <= self.address <= 0xFFFF:
            raise ValueError(f"address {self.address} is not 0..65535")

    @property
    def writable(self) -> bool:
        return self.table in ("coil", "holding")

    @property
    def count(self) -> int:
        """Registers (or bits) the tag takes."""
        return 1 if self.table in ("coil", "discrete") else self.rtype.count

    def value_in(self, block: list[int] | list[bool], start: int) -> bool | int | float | str:
        """The tag's value in ``block``, a read of its table from ``start``."""
        words = block[self.address - start : self.address - start + self.count]
        if self.table in ("coil", "discrete"):
            return bool(words[0])
        return self.rtype.decode([int(w) for w in words])


@dataclass(frozen=True)
class Span:
    """A block of one table read in one request."""

    table: str
    start: int
    count: int


MAX_SPAN = {"coil": 2000, "discrete": 2000, "holding": 125, "input": 125}  # what one Modbus request may read


def spans(tags: list[ModbusTag], gap: int = 16) -> list[Span]:
    """The fewest blocks that read every tag: tags of one table closer than ``gap`` registers are read
    together, no block larger than one request may read."""
    out: list[Span] = []
    for table in TABLES:
        current: Span | None = None
        for tag in sorted((t for t in tags if t.table == table), key=lambda t: t.address):
            end = tag.address + tag.count
            if current is not None and tag.address - (current.start + current.count) <= gap:
                if end - current.start <= MAX_SPAN[table]:
                    current = Span(table, current.start, max(current.start + current.count, end) - current.start)
                    out[-1] = current
                    continue
            current = Span(table, tag.address, tag.count)
            out.append(current)
    return out


class ModbusConnection:
    """One Modbus/TCP endpoint; requests are serialised (one transaction at a time)."""

    def __init__(self, host: str, port: int = 502, timeout: float = 1.0) -> None:
        quiet_pymodbus()
        self.host, self.port, self.timeout = host, port, timeout
        self.attempts = 0  # failed attempts to connect
        self.unanswered = 0  # requests that got no answer
        self._client = AsyncModbusTcpClient(host, port=port, timeout=timeout, retries=0, reconnect_delay=0)
        self._lock = asyncio.Lock()
        self.users = 0

    @property
    def name(self) -> str:
        return endpoint_name(self.host, self.port)

    @property
    def connected(self) -> bool:
        return bool(self._client.connected)

    async def connect(self) -> bool:
        """Try once; True when connected."""
        if not self._client.connected:
            await self._client.connect()
            _cancelled()
            self.attempts += not self._client.connected
        return bool(self._client.connected)

    def close(self) -> None:
        self._client.close()

    async def read(self, tag: ModbusTag, unit: int) -> bool | int | float | str:
        return tag.value_in(await self.read_block(tag.table, tag.address, tag.count, unit), tag.address)

    async def read_block(self, table: str, start: int, count: int, unit: int) -> list[int] | list[bool]:
        """``count`` registers (or bits) of ``table`` from ``start``, in one request."""
        async with self._lock:
            try:
                if table == "coil":
                    rr = await self._client.read_coils(start, count=count, device_id=unit)
                elif table == "discrete":
                    rr = await self._client.read_discrete_inputs(start, count=count, device_id=unit)
                elif table == "holding":
                    rr = await self._client.read_holding_registers(start, count=count, device_id=unit)
                else:
                    rr = await self._client.read_input_registers(start, count=count, device_id=unit)
            except (TimeoutError, ModbusException, OSError) as exc:
                _cancelled()
                self.unanswered += 1
                raise NoAnswer(f"{self.name}: {exc}") from None
        if rr.isError():
            raise CommunicationError(f"{self.name}: unit {unit} {table} {start}..{start + count - 1}: {_refusal(rr)}")
        if table in ("coil", "discrete"):
            return [bool(b) for b in rr.bits[:count]]
        return list(rr.registers)

    async def write(self, tag: ModbusTag, value: object, unit: int) -> None:
        if not tag.writable:
            raise ValueError(f"{tag.table} {tag.address} cannot be written")
        await self.write_block(
            tag.table, tag.address, [bool(value)] if tag.table == "coil" else tag.rtype.encode(value), unit
        )

    async def write_block(self, table: str, start: int, values: list[int] | list[bool], unit: int) -> None:
        """Registers (or one coil) from ``start``, in one request."""
        async with self._lock:
            try:
                if table == "coil":
                    rr = await self._client.write_coil(start, bool(values[0]), device_id=unit)
                else:
                    rr = await self._client.write_registers(start, [int(v) for v in values], device_id=unit)
            except (TimeoutError, ModbusException, OSError) as exc:
                _cancelled()
                self.unanswered += 1
                raise NoAnswer(f"{self.name}: {exc}") from None
        if rr.isError():
            raise CommunicationError(f"{self.name}: unit {unit} {table} {start}: {_refusal(rr)}")


EXCEPTIONS = {1: "illegal function", 2: "illegal data address", 3: "illegal data value", 4: "device failure"}


def _refusal(response: object) -> str:
    """What a Modbus exception response says, in words (``illegal data address (exception 2)``)."""
    code = getattr(response, "exception_code", None)
    return f"{EXCEPTIONS.get(code, 'refused')} (exception {code})" if isinstance(code, int) else str(response)


def _cancelled() -> None:
    """pymodbus turns a cancellation into its own error (or a failed connect): raise it again, so a
    task being cancelled ends instead of reporting a lost connection and going on."""
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        raise asyncio.CancelledError


class ModbusPool(SharedPool[tuple[str, int], ModbusConnection]):
    """Connections shared per endpoint: two parts on the same host and port use one connection."""

    def __init__(self) -> None:
        super().__init__(lambda conn: conn.close(), lambda conn: conn.name)

    def connection(self, host: str, port: int = 502, timeout: float = 1.0, part: str = "") -> ModbusConnection:
        """The connection to ``host``:``port``; a ValueError if it is open with another ``timeout``
        (one connection has one: ``uacell config check`` names both parts, ``shared_settings``)."""
        return self.get((host, port), lambda: ModbusConnection(host, port, timeout), part, timeout=timeout)

    def close(self) -> None:
        for conn in self.values():
            conn.close()
        self._entries.clear()


SHARED = ModbusPool()  # the process's connections: every driver on one host and port uses one
