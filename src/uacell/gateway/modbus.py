"""Modbus/TCP transport (pymodbus client): one connection per (host, port), shared by every part.

Reads and writes typed tags (``codec.RegisterType``) in the four Modbus tables. A failed request
marks the connection lost and raises ``CommunicationError``; nothing is queued or retried here (the
driver decides, and never replays a command).
"""

from __future__ import annotations

import asyncio
from dataclasses import dataclass

from pymodbus.client import AsyncModbusTcpClient
from pymodbus.exceptions import ModbusException

from uacell.gateway.codec import RegisterType

TABLES = ("coil", "discrete", "holding", "input")


class CommunicationError(Exception):
    """The endpoint did not answer or answered with an error (message names the endpoint)."""


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


class ModbusConnection:
    """One Modbus/TCP endpoint; requests are serialised (one transaction at a time)."""

    def __init__(self, host: str, port: int = 502, timeout: float = 1.0) -> None:
        self.host, self.port = host, port
        self._client = AsyncModbusTcpClient(host, port=port, timeout=timeout, retries=0, reconnect_delay=0)
        self._lock = asyncio.Lock()
        self.users = 0

    @property
    def name(self) -> str:
        return f"modbus://{self.host}:{self.port}"

    @property
    def connected(self) -> bool:
        return bool(self._client.connected)

    async def connect(self) -> bool:
        """Try once; True when connected."""
        if not self._client.connected:
            await self._client.connect()
            _cancelled()
        return bool(self._client.connected)

    def close(self) -> None:
        self._client.close()

    async def read(self, tag: ModbusTag, unit: int) -> bool | int | float | str:
        count = tag.rtype.count
        async with self._lock:
            try:
                if tag.table == "coil":
                    rr = await self._client.read_coils(tag.address, count=1, device_id=unit)
                elif tag.table == "discrete":
                    rr = await self._client.read_discrete_inputs(tag.address, count=1, device_id=unit)
                elif tag.table == "holding":
                    rr = await self._client.read_holding_registers(tag.address, count=count, device_id=unit)
                else:
                    rr = await self._client.read_input_registers(tag.address, count=count, device_id=unit)
            except (TimeoutError, ModbusException, OSError) as exc:
                _cancelled()
                raise CommunicationError(f"{self.name}: {exc}") from None
        if rr.isError():
            raise CommunicationError(f"{self.name}: {tag.table} {tag.address}: {rr}")
        if tag.table in ("coil", "discrete"):
            return bool(rr.bits[0])
        return tag.rtype.decode(list(rr.registers))

    async def write(self, tag: ModbusTag, value: object, unit: int) -> None:
        if not tag.writable:
            raise ValueError(f"{tag.table} {tag.address} cannot be written")
        registers = tag.rtype.encode(value)
        async with self._lock:
            try:
                if tag.table == "coil":
                    rr = await self._client.write_coil(tag.address, bool(value), device_id=unit)
                else:
                    rr = await self._client.write_registers(tag.address, registers, device_id=unit)
            except (TimeoutError, ModbusException, OSError) as exc:
                _cancelled()
                raise CommunicationError(f"{self.name}: {exc}") from None
        if rr.isError():
            raise CommunicationError(f"{self.name}: {tag.table} {tag.address}: {rr}")


def _cancelled() -> None:
    """pymodbus turns a cancellation into its own error (or a failed connect): raise it again, so a
    task being cancelled ends instead of reporting a lost connection and going on."""
    task = asyncio.current_task()
    if task is not None and task.cancelling():
        raise asyncio.CancelledError


class ModbusPool:
    """Connections shared per endpoint: two parts on the same host and port use one connection."""

    def __init__(self) -> None:
        self._connections: dict[tuple[str, int], ModbusConnection] = {}

    def get(self, host: str, port: int = 502, timeout: float = 1.0) -> ModbusConnection:
        conn = self._connections.get((host, port))
        if conn is None:
            conn = self._connections[(host, port)] = ModbusConnection(host, port, timeout)
        conn.users += 1
        return conn

    def release(self, conn: ModbusConnection) -> None:
        """One user less; the last one closes the connection."""
        conn.users -= 1
        if conn.users <= 0:
            conn.close()
            self._connections.pop((conn.host, conn.port), None)

    def close(self) -> None:
        for conn in self._connections.values():
            conn.close()
        self._connections.clear()
