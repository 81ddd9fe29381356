"""What every polled PackTags driver does, asserted for each (``modbus-packtags``, ``s7-packtags``,
``logix-packtags``): the shipped cell served by uacell from the cell file alone, the driver's example
PLC (pymodbus's server, snap7's S7 server, cpppo's Logix simulator, each running a TR88 scan-cycle
program) in its own process on a free port; an asyncua client (and node-opcua once) drives uacell,
which drives the PLC; the test reads the PLC through its own connection. What only one transport has
(its layout, its addresses, its write job) is in that driver's own test file."""

from __future__ import annotations

import asyncio
import time
from collections.abc import AsyncIterator, Callable
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, serving
from gateway_plcs import S7PLC, LogixPLC, ModbusPLC, logix_cell, modbus_cell, s7_cell, serving_cell
from helpers import call_path, cell_executable, cell_read, cell_state, cell_status, packml_params, until

from uacell.config import load_cell
from uacell.gateway import modbus, packml_logix, packml_modbus, packml_s7
from uacell.gateway.packml_modbus import Point, resolve_modbus
from uacell.server import UacellServer

F = "Capper"


def machines(unit: str) -> tuple[str, str, str]:
    base = f"{unit}.BaseStateMachine"
    return base, f"{base}.MachineState", f"{base}.MachineState.ExecuteState"


BASE, MACH, EXEC = machines(F)


class ModbusUnits(ModbusPLC):
    """The Modbus PLC by unit name: the shipped cell's units at registers 0 and 100."""

    at = {"Capper": 0, "Labeler": 100, "Filler1": 0}
    switches = {"refuse": 80, "frozen": 81, "fault": 82}

    async def read(self, unit: str, key: str) -> Any:
        return await self.tag(self.at[unit], key)

    async def write(self, unit: str, key: str, value: Any) -> None:
        assert self.conn is not None
        point = Point.parse(resolve_modbus("test", 1, self.at[unit])[key].address)
        await self.conn.write(point.tag, value, point.device)

    async def flip(self, unit: str, switch: str, on: bool) -> None:
        await self.switch(self.at[unit], self.switches[switch], on)

    async def took(self, unit: str) -> list[float]:
        return await self.taken(self.at[unit])

    async def disconnect(self) -> None:
        self.close()

    @staticmethod
    def connections() -> int:
        assert len(packml_modbus.POOL) == len(modbus.SHARED)
        return len(modbus.SHARED)


class S7Units(S7PLC):
    """The S7 PLC by unit name: the shipped cell's units at bytes 0 and 200 of DB 1."""

    at = {"Capper": 0, "Labeler": 200, "Filler1": 0}
    switches = {"refuse": 0, "frozen": 1, "fault": 2}

    async def read(self, unit: str, key: str) -> Any:
        return await self.tag(self.at[unit], key)

    async def write(self, unit: str, key: str, value: Any) -> None:
        await self.put(self.at[unit], key, value)

    async def flip(self, unit: str, switch: str, on: bool) -> None:
        await self.switch(self.at[unit], self.switches[switch], on)

    async def took(self, unit: str) -> list[float]:
        return await self.taken(self.at[unit])

    async def disconnect(self) -> None:
        await self.close()

    @staticmethod
    def connections() -> int:
        return len(packml_s7.POOL)


class LogixUnits(LogixPLC):
    """The Logix controller by unit name: tags under the unit's name, parameters as the cell maps them."""

    async def read(self, unit: str, key: str) -> Any:
        return await self.tag(f"{unit}.{key}")

    async def write(self, unit: str, key: str, value: Any) -> None:
        parameter = key.removeprefix("Command.Parameter[").removesuffix("].Value")
        await self.put(f"{unit}_Parameter[{parameter}]" if parameter != key else f"{unit}.{key}", value)

    async def flip(self, unit: str, switch: str, on: bool) -> None:
        await self.put(f"{unit}_{switch.capitalize()}", on)

    async def took(self, unit: str) -> list[float]:
        return [float(await self.tag(f"{unit}_Taken[{i}]")) for i in range(5)]

    async def disconnect(self) -> None:
        await self.close()

    @staticmethod
    def connections() -> int:
        return len(packml_logix.POOL)


Units = ModbusUnits | S7Units | LogixUnits
# driver -> (the PLC with the shipped cell's units, or with one unit named Filler1; the shipped cell on
# it; the shipped cell's second unit on the same PLC, if it has one)
KINDS: dict[str, tuple[Callable[[bool], Units], Callable[[Any], str], str | None]] = {
    "modbus-packtags": (lambda filler: ModbusUnits(), modbus_cell, "Labeler"),
    "s7-packtags": (lambda filler: S7Units(), s7_cell, "Labeler"),
    "logix-packtags": (lambda filler: LogixUnits("Filler1" if filler else F), logix_cell, None),
}


@pytest.fixture(params=sorted(KINDS))
def kind(request: pytest.FixtureRequest) -> str:
    return str(request.param)


async def started(kind: str, filler: bool = False) -> Units:
    plc = KINDS[kind][0](filler)
    plc.start()
    await plc.open()
    return plc


@pytest.fixture
async def plc(kind: str) -> AsyncIterator[Units]:
    p = await started(kind)
    try:
        yield p
    finally:
        await p.disconnect()
        p.kill()


def cell(kind: str, plc: Units) -> str:
    return KINDS[kind][1](plc)


@pytest.fixture
async def served(tmp_path: Path, kind: str, plc: Units) -> AsyncIterator[tuple[UacellServer, Client]]:
    async with serving_cell(tmp_path, cell(kind, plc)) as s:  # the shipped example, pointed at the PLC
        yield s


async def test_a_full_cycle_goes_to_the_plc_and_comes_back(served, kind: str, plc: Units) -> None:
    _app, client = served
    assert plc.connections() == 1  # every unit of the PLC on one connection
    assert await plc.read(F, "Status.StateCurrent") == 2  # Stopped
    assert await cell_state(client, MACH) == "Stopped"
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.is_good(), res.StatusCode
    assert await plc.read(F, "Status.StateCurrent") in (15, 4)  # the PLC took it before the call answered
    await until(lambda: cell_state(client, EXEC), "Idle")
    assert (await call_path(client, F, "SetMachSpeed", ua.Variant(120.0, ua.VariantType.Float))).StatusCode.is_good()
    await until(lambda: plc.read(F, "Command.MachSpeed"), 120.0)
    await plc.write(F, "Command.Parameter[4].Value", 9.5)  # an older Start's value, left in the PLC
    res = await call_path(client, EXEC, "Start", packml_params((1, 180.5), (2, 0.25)))
    assert res.StatusCode.is_good(), res.StatusCode
    assert await plc.took(F) == pytest.approx([180.5, 0.25, 0.0, 0.0, 0.0])  # unused slots are written 0.0
    await until(lambda: cell_state(client, EXEC), "Execute")
    await until(lambda: cell_read(client, f"{F}.Status.CurMachSpeed"), pytest.approx(120.0))  # the PLC's
    await until(lambda: cell_read(client, f"{F}.Status.MachSpeed"), pytest.approx(120.0))  # the PLC's

    async def produced() -> bool:  # the PLC's count, mirrored into Admin.ProdProcessedCount
        (count,) = await cell_read(client, f"{F}.Admin.ProdProcessedCount")
        return bool(count.Count > 0)

    await until(produced, True)
    assert (await call_path(client, MACH, "Stop")).StatusCode.is_good()
    await until(lambda: cell_state(client, MACH), "Stopped")
    assert await plc.read(F, "Status.StateCurrent") == 2
    # uacell's own rules before the PLC's: Start is not allowed in Stopped, nothing is written
    res = await call_path(client, EXEC, "Start", packml_params())
    assert res.StatusCode.value in (ua.StatusCodes.BadInvalidState, ua.StatusCodes.BadMethodInvalid)
    assert await plc.read(F, "Command.CntrlCmd") == 3  # still the Stop
    other = KINDS[kind][2]
    if other is not None:  # the other unit on the same connection was not touched
        assert await cell_state(client, machines(other)[1]) == "Stopped"
        assert await plc.read(other, "Status.StateCurrent") == 2
        res = await call_path(client, machines(other)[1], "Reset")
        assert res.StatusCode.is_good(), res.StatusCode
        await until(lambda: plc.read(other, "Status.StateCurrent"), 4)
        assert await plc.read(F, "Status.StateCurrent") == 2
    # six parameters where the PLC has five: refused, nothing written
    res = await call_path(client, MACH, "Reset")
    await until(lambda: cell_state(client, EXEC), "Idle")
    res = await call_path(client, EXEC, "Start", packml_params(*((i, float(i)) for i in range(6))))
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    assert await plc.read(F, "Command.CntrlCmd") == 1
    # unit modes go through the PLC with their own handshake (their request bit beside the command's)
    res = await call_path(client, F, "SetUnitMode", ua.Variant(2, ua.VariantType.Int32))
    assert res.StatusCode.is_good(), res.StatusCode
    assert await plc.read(F, "Status.UnitModeCurrent") == 2
    assert await cell_read(client, f"{F}.Status.UnitModeCurrent") == 2


async def test_a_command_the_plc_refuses_or_never_takes(served, plc: Units) -> None:
    _app, client = served
    await plc.flip(F, "refuse", True)
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState
    assert await cell_state(client, MACH) == "Stopped" and await plc.read(F, "Status.StateCurrent") == 2
    await plc.flip(F, "refuse", False)
    await plc.flip(F, "frozen", True)  # no scan takes the request
    started_at = time.monotonic()
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.value == ua.StatusCodes.BadTimeout
    assert time.monotonic() - started_at >= 2.5  # confirm_timeout 3 s
    assert await plc.read(F, "Command.CmdChangeRequest") is False  # nothing left half-written
    assert await cell_state(client, MACH) == "Stopped"


async def test_the_plc_faults_and_uacell_aborts_with_its_stop_reason(served, plc: Units) -> None:
    _app, client = served
    assert (await call_path(client, MACH, "Reset")).StatusCode.is_good()
    await until(lambda: cell_state(client, EXEC), "Idle")
    await plc.flip(F, "fault", True)
    await until(lambda: cell_state(client, BASE), "Aborted")

    async def stop_reason() -> int:
        return int((await cell_read(client, f"{F}.Admin.StopReason")).ID)

    await until(stop_reason, 42)  # a stored value: seen once durable, a few ms after the state (docs/packml.md)


async def test_the_plc_killed_and_back_nothing_replayed(served, plc: Units) -> None:
    """Killed while Stopped: the last state stays readable, marked not current; killed while Idle: the
    PLC restarted in Stopped is followed there. No refused command is replayed either time."""
    _app, client = served
    ns = await client.get_namespace_index("urn:uacell:cell")
    await plc.disconnect()
    plc.kill()

    def executable() -> Any:
        return cell_executable(client, f"{MACH}.Reset")

    await until(executable, False)
    assert (await call_path(client, MACH, "Reset")).StatusCode.value == ua.StatusCodes.BadCommunicationError

    def speed_status() -> Any:
        return cell_status(client, f"{F}.Status.MachSpeed")

    await until(speed_status, "BadNoCommunication")  # the PLC's values are not current any more

    def machine_quality() -> Any:  # the machines show the PLC's last state, and say it is not live
        return cell_status(client, f"{MACH}.CurrentState")

    await until(machine_quality, "UncertainNoCommunicationLastUsableValue")
    last = await client.get_node(ua.NodeId(f"{MACH}.CurrentState", ns)).read_data_value(raise_on_bad_status=False)
    assert last.Value.Value.Text == "Stopped"  # the last state known, still readable
    warnings = client.get_node(ua.NodeId(f"{F}.Admin.Warning", ns))
    assert any(w.ID == 9001 for w in await warnings.read_value())  # uacell's own: readable, says why
    plc.start()  # the same port
    back = time.monotonic()
    await until(executable, True)
    assert time.monotonic() - back <= 5.0
    await until(speed_status, "Good")
    await until(machine_quality, "Good")
    assert not any(w.ID == 9001 for w in await warnings.read_value())
    await plc.open()
    assert await plc.read(F, "Command.CmdChangeRequest") is False  # the refused Reset was not replayed
    assert await plc.read(F, "Command.CntrlCmd") == 0
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.is_good(), res.StatusCode
    await until(lambda: plc.read(F, "Status.StateCurrent"), 4)
    await until(lambda: cell_state(client, EXEC), "Idle")
    # killed while Idle
    await plc.disconnect()
    plc.kill()
    await until(lambda: cell_executable(client, f"{EXEC}.Start"), False)
    res = await call_path(client, EXEC, "Start", packml_params())
    assert res.StatusCode.value == ua.StatusCodes.BadCommunicationError
    await until(speed_status, "BadNoCommunication")
    plc.start()  # a PLC restarted, in Stopped, its command tags 0
    back = time.monotonic()
    await until(lambda: cell_state(client, MACH), "Stopped")  # the PLC's state as it now is
    assert time.monotonic() - back <= 5.0
    await until(speed_status, "Good")
    await plc.open()
    assert await plc.read(F, "Command.CntrlCmd") == 0  # the refused Start was not replayed
    assert await plc.read(F, "Command.CmdChangeRequest") is False
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.is_good(), res.StatusCode
    await until(lambda: plc.read(F, "Status.StateCurrent"), 4)


async def test_node_opcua_runs_a_cycle_through_uacell_to_the_plc(tmp_path: Path, kind: str) -> None:
    """The independent client: node-opcua resets and starts (with two parameters) a unit the PLC owns."""
    from conftest import run_node

    plc = await started(kind, filler=True)
    try:
        path = tmp_path / "cell.toml"
        path.write_text(cell(kind, plc).replace(F, "Filler1"))
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (app, _client):
            out = await asyncio.to_thread(run_node, "packml_start.js", app.endpoint)
            assert (out["reset"], out["start"], out["state"]) == ("Good", "Good", "Execute")
            assert await plc.read("Filler1", "Status.StateCurrent") == 6  # the PLC is in Execute
            assert await plc.took("Filler1") == pytest.approx([250.5, -12.25, 0.0, 0.0, 0.0])
    finally:
        await plc.disconnect()
        plc.kill()
