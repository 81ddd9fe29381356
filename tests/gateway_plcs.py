"""The example PLCs of the PackTags drivers, each in its own process on a free port with a connection
of the test's to look into it (their program: ``uacell.gateway.examples``); the shipped cell of each,
pointed at it. Used by the drivers' own tests and by the acceptance suite every driver passes
(tests/test_gateway_packml_acceptance.py)."""

from __future__ import annotations

import asyncio
import os
import select
import subprocess
import sys
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from asyncua import Client
from conftest import fast_config, serving
from helpers import free_port

from uacell.config import load_cell
from uacell.core.cell_file import builtin_cell_path
from uacell.gateway.codec import RegisterType
from uacell.gateway.modbus import ModbusConnection, ModbusTag
from uacell.gateway.packml_logix import LogixConnection
from uacell.gateway.packml_modbus import Point, resolve_modbus
from uacell.gateway.packml_s7 import S7Connection, resolve_s7
from uacell.gateway.s7 import S7Address
from uacell.server import UacellServer

SRC = str(Path(__file__).resolve().parents[1] / "src")


@asynccontextmanager
async def serving_cell(tmp_path: Path, text: str) -> AsyncIterator[tuple[UacellServer, Client]]:
    """A server (fast settings) of the cell file ``text`` (a shipped example pointed at a test PLC),
    with a client that knows the data types."""
    path = tmp_path / "cell.toml"
    path.write_text(text)
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as s:
        await s[1].load_data_type_definitions()
        yield s


class ExamplePLC:
    """An example PLC (``uacell.gateway.examples.<module>``) in its own process on ``port``."""

    module = ""
    port: int
    units: int | str
    acting: float
    proc: subprocess.Popen[str] | None

    def start(self) -> None:
        cmd = [sys.executable, "-m", f"uacell.gateway.examples.{self.module}", "--port", str(self.port)]
        cmd += ["--units", str(self.units), "--acting", str(self.acting)]
        self.proc = subprocess.Popen(
            cmd, env={**os.environ, "PYTHONPATH": SRC}, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        assert self.proc.stdout is not None
        # the PLC prints it once it serves (or ends: ""); a PLC that does neither within a minute is killed
        ready, _, _ = select.select([self.proc.stdout], [], [], 60.0)
        line = self.proc.stdout.readline() if ready else "(nothing within 60 s)"
        if line.strip() != "listening":
            self.kill()  # not left running (or its pipe open) when it did not come up
            raise AssertionError(f"the example PLC {self.module} did not start: {line!r}")

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(10)
            if self.proc.stdout is not None:
                self.proc.stdout.close()
            self.proc = None


class ModbusPLC(ExamplePLC):
    """The example PLC in its own process, and a Modbus client of the test's to look into it."""

    def __init__(self, units: int = 2, acting: float = 0.1) -> None:
        self.port, self.units, self.acting = free_port(), units, acting
        self.proc: subprocess.Popen[str] | None = None
        self.conn: ModbusConnection | None = None

    module = "packtags_plc"

    async def open(self) -> None:
        self.conn = ModbusConnection("127.0.0.1", self.port, timeout=2.0)
        assert await self.conn.connect()

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
            self.conn = None

    async def tag(self, base: int, key: str) -> Any:
        assert self.conn is not None
        point = Point.parse(resolve_modbus("test", 1, base)[key].address)
        return await self.conn.read(point.tag, 1)

    async def switch(self, base: int, offset: int, on: bool) -> None:
        """One of the example PLC's test switches (80 refuse, 81 frozen, 82 fault)."""
        assert self.conn is not None
        await self.conn.write(ModbusTag("holding", base + offset, RegisterType("bool")), on, 1)

    async def taken(self, base: int = 0) -> list[float]:
        """The parameters the last Start took (the example PLC copies them to base + 84..)."""
        assert self.conn is not None
        f = RegisterType("float32")
        return [float(await self.conn.read(ModbusTag("holding", base + 84 + 2 * i, f), 1)) for i in range(5)]


class S7PLC(ExamplePLC):
    """The example S7 PLC in its own process, and an S7 connection of the test's to look into it."""

    def __init__(self, units: int = 2, acting: float = 0.1) -> None:
        self.port, self.units, self.acting = free_port(), units, acting
        self.proc: subprocess.Popen[str] | None = None
        self.conn: S7Connection | None = None

    module = "s7_plc"

    async def open(self) -> None:
        self.conn = S7Connection("127.0.0.1", self.port, 0, 1, 3.0)
        assert await self.conn.connect()

    async def close(self) -> None:
        if self.conn is not None:
            await self.conn.close()
            self.conn = None

    async def value(self, address: S7Address) -> Any:
        assert self.conn is not None
        return address.decode(await self.conn.read(address.db, address.byte, address.size), address.byte)

    async def tag(self, start: int, key: str) -> Any:
        return await self.value(S7Address.parse(resolve_s7("test", 1, start)[key].address))

    async def put(self, start: int, key: str, value: Any) -> None:
        assert self.conn is not None
        await self.conn.write([(S7Address.parse(resolve_s7("test", 1, start, alarms=2)[key].address), value)])

    async def switch(self, start: int, bit: int, on: bool) -> None:
        """One of the example PLC's test switches (160.0 refuse, 160.1 frozen, 160.2 fault)."""
        assert self.conn is not None
        await self.conn.write([(S7Address(1, start + 160, bit, "BOOL"), on)])

    async def taken(self, start: int = 0) -> list[float]:
        """The parameters the last Start took (the example PLC copies them to bytes 164..)."""
        return [float(await self.value(S7Address(1, start + 164 + 4 * i, 0, "REAL"))) for i in range(5)]


class LogixPLC(ExamplePLC):
    """The example controller (cpppo) in its own process, and a pylogix session of the test's."""

    def __init__(self, units: str = "Capper", acting: float = 0.1) -> None:
        self.port, self.units, self.acting = free_port(), units, acting
        self.proc: subprocess.Popen[str] | None = None
        self.conn: LogixConnection | None = None

    module = "logix_plc"

    async def open(self) -> None:
        self.conn = LogixConnection("127.0.0.1", self.port, 0, 3.0)
        assert await self.conn.connect()

    async def close(self) -> None:
        if self.conn is not None:
            await asyncio.to_thread(self.conn.close)
            self.conn = None

    async def tag(self, name: str) -> Any:
        assert self.conn is not None
        (value,) = await self.conn.read([name])
        return value

    async def put(self, name: str, value: Any) -> None:
        assert self.conn is not None
        await self.conn.write([(name, value)])

    async def taken(self) -> list[float]:
        return [float(await self.tag(f"{self.units}_Taken[{i}]")) for i in range(5)]


def modbus_cell(plc: ModbusPLC) -> str:
    return builtin_cell_path("modbus-packtags").read_text().replace("port = 5021", f"port = {plc.port}")


def s7_cell(plc: S7PLC) -> str:
    return builtin_cell_path("s7-packtags").read_text().replace("port = 10102", f"port = {plc.port}")


def logix_cell(plc: LogixPLC) -> str:
    return builtin_cell_path("logix-packtags").read_text().replace("port = 44819", f"port = {plc.port}")
