"""What the PLC owns, uacell follows: every tag of the PackTags map that uacell reads (Status.* and
Admin.*) is walked, on each test PLC (node-opcua's over OPC UA, pymodbus's over Modbus/TCP,
python-snap7's S7 server, cpppo's Logix simulator): the test PLC is frozen (no scan moves
anything), the test writes the tag in the PLC and reads what uacell shows. The speeds the PLC holds
are shown from the start (not the cell file's ``mach_speed``), and a set point the PLC keeps wins
over a SetMachSpeed it did not take."""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable, Callable
from contextlib import asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, serving
from helpers import call_path, cell_read, cell_state, until

from uacell.config import load_cell
from uacell.gateway.packtags import DEFAULT_MAP, resolve

F = "Capper"
EXEC = f"{F}.BaseStateMachine.MachineState.ExecuteState"
BASE = f"{F}.BaseStateMachine"


@dataclass
class PlcUnderTest:
    """One test PLC as this test uses it: a cell file for uacell, a tag writer, a freeze switch."""

    cell: str
    set: Callable[[str, Any], Awaitable[None]]  # (tag key, value): written in the PLC's own type
    freeze: Callable[[bool], Awaitable[None]]
    get: Callable[[str], Awaitable[Any]]


@asynccontextmanager
async def opcua_plc() -> AsyncIterator[PlcUnderTest]:
    from test_gateway_packml import PLC, cell

    p = PLC([F])
    p.start()
    try:
        async with p.new_client() as client:
            p.client = client
            types = {"Int32": ua.VariantType.Int32, "Float": ua.VariantType.Float, "Boolean": ua.VariantType.Boolean}
            tags = resolve(F, "x", parameters=5, alarms=4)

            async def set_(key: str, value: Any) -> None:
                await p.set(F, tags[key].address.removeprefix("x."), value, types[tags[key].type_name])

            async def get(key: str) -> Any:
                return await p.tag(F, tags[key].address.removeprefix("x."))

            async def freeze(on: bool) -> None:
                await p.set(F, "Sim.Frozen", on, ua.VariantType.Boolean)

            yield PlcUnderTest(cell(p, [F], ", alarms = 2"), set_, freeze, get)
    finally:
        p.kill()


@asynccontextmanager
async def modbus_plc() -> AsyncIterator[PlcUnderTest]:
    from gateway_plcs import ModbusPLC

    from uacell.gateway.packml_modbus import Point, resolve_modbus

    p = ModbusPLC(units=1)
    p.start()
    try:
        await p.open()
        tags = resolve_modbus(F, 1, 0, parameters=5, alarms=2)

        async def set_(key: str, value: Any) -> None:
            assert p.conn is not None
            point = Point.parse(tags[key].address)
            await p.conn.write(point.tag, value, 1)

        async def get(key: str) -> Any:
            return await p.tag(0, key)

        async def freeze(on: bool) -> None:
            await p.switch(0, 81, on)

        text = f'[[packml_units]]\nname = "{F}"\nequipment = {{ driver = "modbus-packtags", host = "127.0.0.1", '
        text += f"port = {p.port}, alarms = 2 }}\n"
        yield PlcUnderTest(text, set_, freeze, get)
    finally:
        p.close()
        p.kill()


@asynccontextmanager
async def s7_plc() -> AsyncIterator[PlcUnderTest]:
    from gateway_plcs import S7PLC

    p = S7PLC(units=1)
    p.start()
    try:
        await p.open()

        async def set_(key: str, value: Any) -> None:
            await p.put(0, key, value)

        async def get(key: str) -> Any:
            return await p.tag(0, key)

        async def freeze(on: bool) -> None:
            await p.switch(0, 1, on)

        text = f'[[packml_units]]\nname = "{F}"\nequipment = {{ driver = "s7-packtags", host = "127.0.0.1", '
        text += f"port = {p.port}, db = 1, alarms = 2 }}\n"
        yield PlcUnderTest(text, set_, freeze, get)
    finally:
        await p.close()
        p.kill()


@asynccontextmanager
async def logix_plc() -> AsyncIterator[PlcUnderTest]:
    from gateway_plcs import LogixPLC

    from uacell.gateway.packml_logix import where

    p = LogixPLC()
    p.start()
    try:
        await p.open()
        arrays = {f"Command.Parameter[{i}].Value": f"{F}_Parameter[{i}]" for i in range(5)}
        arrays |= {f"Admin.Alarm[{i}].ID": f"{F}_Alarm[{i}]" for i in range(2)}
        tags = where(F, {"host": "x", "prefix": F, "alarms": 2, "map": arrays}).tags

        async def set_(key: str, value: Any) -> None:
            await p.put(tags[key].address, value)

        async def get(key: str) -> Any:
            return await p.tag(tags[key].address)

        async def freeze(on: bool) -> None:
            await p.put(f"{F}_Frozen", on)

        pairs = ", ".join(f'"{k}" = "{v}"' for k, v in arrays.items())
        text = f'[[packml_units]]\nname = "{F}"\nequipment = {{ driver = "logix-packtags", host = "127.0.0.1", '
        text += f'port = {p.port}, prefix = "{F}", alarms = 2, timeout = 3.0, map = {{ {pairs} }} }}\n'
        yield PlcUnderTest(text, set_, freeze, get)
    finally:
        await p.close()
        p.kill()


PLCS = {"opcua": opcua_plc, "modbus": modbus_plc, "s7": s7_plc, "logix": logix_plc}


async def count(client: Client, name: str) -> int:
    (first,) = await cell_read(client, f"{F}.Admin.{name}")
    return int(first.Count)


async def alarms(client: Client) -> list[int]:
    return [a.ID for a in await cell_read(client, f"{F}.Admin.Alarm")]


def checks(client: Client) -> dict[str, tuple[Any, Callable[[], Awaitable[Any]], Any]]:
    """Every tag uacell reads -> (the value written in the PLC, what to read in uacell, what it must say).
    In this order: the abort with a StopReason comes last."""

    def read(path: str) -> Callable[[], Awaitable[Any]]:
        return lambda: cell_read(client, f"{F}.{path}")

    async def stop_reason() -> int:
        return int((await cell_read(client, f"{F}.Admin.StopReason")).ID)

    return {
        "Status.StateCurrent": (4, lambda: cell_state(client, EXEC), "Idle"),  # Stopped -> Idle: followed by Reset
        "Status.UnitModeCurrent": (2, read("Status.UnitModeCurrent"), 2),
        "Status.MachSpeed": (24.0, read("Status.MachSpeed"), pytest.approx(24.0)),
        "Status.CurMachSpeed": (17.5, read("Status.CurMachSpeed"), pytest.approx(17.5)),
        "Admin.ProdProcessedCount": (5, lambda: count(client, "ProdProcessedCount"), 5),
        "Admin.ProdDefectiveCount": (2, lambda: count(client, "ProdDefectiveCount"), 2),
        "Admin.Alarm[0].ID": (12, lambda: alarms(client), [12]),
        "Admin.Alarm[1].ID": (31, lambda: alarms(client), [12, 31]),
        "Admin.StopReason": (77, stop_reason, 77),  # read when the PLC aborts (below)
    }


@pytest.mark.parametrize("kind", sorted(PLCS))
async def test_every_tag_uacell_reads_follows_the_plc(kind: str, tmp_path: Path) -> None:
    async with PLCS[kind]() as plc:
        await plc.freeze(True)
        await plc.set("Status.MachSpeed", 42.0)  # the PLC's own, before uacell starts
        await plc.set("Command.MachSpeed", 42.0)
        path = tmp_path / "cell.toml"
        path.write_text(plc.cell)
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (_app, client):
            await client.load_data_type_definitions()
            # the cell file says nothing and [packml] mach_speed is 60: the PLC's 42 is shown
            await until(lambda: cell_read(client, f"{F}.Status.MachSpeed"), pytest.approx(42.0))
            table = checks(client)
            followed = [k for k in resolve(F, "x", parameters=0, alarms=2) if not k.startswith("Command.")]
            assert sorted(followed) == sorted(table), "every tag uacell reads has its check here"
            assert {k for k in DEFAULT_MAP if not k.startswith("Command.")} <= set(table)
            for key, (value, what, expected) in table.items():
                if key == "Admin.StopReason":
                    await plc.set(key, value)
                    await plc.set("Status.StateCurrent", 9)  # the PLC aborted by itself
                    await until(lambda: cell_state(client, BASE), "Aborted")
                else:
                    await plc.set(key, value)
                await until(what, expected)
            # a set point the PLC keeps (it is frozen: it does not take the request): uacell shows the
            # request at once, then the PLC's Status.MachSpeed again within confirm_timeout (3 s)
            res = await call_path(client, F, "SetMachSpeed", ua.Variant(100.0, ua.VariantType.Float))
            assert res.StatusCode.is_good(), res.StatusCode
            await until(lambda: plc.get("Command.MachSpeed"), pytest.approx(100.0))  # written after the answer
            await until(lambda: cell_read(client, f"{F}.Status.MachSpeed"), pytest.approx(24.0), timeout=10)
            await plc.freeze(False)  # scanning again: it takes the set point and reports it
            res = await call_path(client, F, "SetMachSpeed", ua.Variant(90.0, ua.VariantType.Float))
            assert res.StatusCode.is_good(), res.StatusCode
            await until(lambda: plc.get("Status.MachSpeed"), pytest.approx(90.0))
            await until(lambda: cell_read(client, f"{F}.Status.MachSpeed"), pytest.approx(90.0))
