"""One missing tag is one problem, not a dead unit (issue 42): ``config check --connect`` tries every
tag the configuration implies (alarms and parameters too) and names each one the PLC lacks; served,
a missing optional tag is one log line and the rest of the unit works, a missing tag a handshake
needs refuses what needs it with Bad_ConfigurationError naming the tag."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import pytest
from asyncua import ua
from conftest import fast_config, serving
from gateway_plcs import ModbusPLC
from helpers import call_path, cell_read, cell_state, config_check_connect, until
from test_gateway_packml import PLC, cell

from uacell.config import load_cell
from uacell.gateway.packtags import NEEDED_BY, resolve

F = "Capper"
MACH = f"{F}.BaseStateMachine.MachineState"
EXEC = f"{MACH}.ExecuteState"


@pytest.fixture
def plc() -> Any:
    p = PLC([F])
    p.start()
    try:
        yield p
    finally:
        p.kill()


@pytest.fixture
async def modbus() -> Any:
    p = ModbusPLC(units=1)
    p.start()
    try:
        await p.open()
        yield p
    finally:
        p.close()
        p.kill()


def test_what_needs_which_tag_is_declared_on_the_map() -> None:
    tags = resolve(F, "x")
    for keys in NEEDED_BY.values():
        assert set(keys) <= set(tags)


async def test_config_check_names_a_missing_alarm_and_the_unit_works_without_it(
    tmp_path: Path, plc: PLC, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "cell.toml"
    path.write_text(cell(plc, [F], ", alarms = 5"))  # the test PLC has Admin.Alarm[0..3]
    proc = await config_check_connect(path)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    for i in range(4):
        assert any(f"Admin.Alarm[{i}].ID" in ln and "Int32 = 0" in ln and "PROBLEM" not in ln for ln in lines), lines
    bad = [ln for ln in lines if "PROBLEM" in ln]
    assert len(bad) == 1 and "Admin.Alarm[4].ID" in bad[0] and "BadNodeIdUnknown" in bad[0], lines
    assert "connect: 21 of 22 as configured" in proc.stdout, proc.stdout  # 12 + 5 parameters + 5 alarms
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    with caplog.at_level(logging.WARNING, logger="uacell.gateway.packml_plc"):
        async with serving(config) as (_app, client):
            res = await call_path(client, MACH, "Reset")
            assert res.StatusCode.is_good(), res.StatusCode
            await until(lambda: cell_state(client, EXEC), "Idle")
            await client.load_data_type_definitions()
            async with plc.new_client() as plc_client:
                plc.client = plc_client
                await plc.set(F, "Admin.Alarm[3].ID", 55, ua.VariantType.Int32)  # the other alarms still follow

                async def alarms() -> list[int]:
                    return [a.ID for a in await cell_read(client, f"{F}.Admin.Alarm")]

                await until(alarms, [55])
                plc.client = None
    said = [r.getMessage() for r in caplog.records if "Admin.Alarm[4].ID" in r.getMessage()]
    assert len(said) == 1, said
    assert said[0] == (
        f"{F}: the PLC has no Admin.Alarm[4].ID (ns=1;s={F}.PackTags.Admin.Alarm[4].ID: BadNodeIdUnknown); "
        "the unit works without it"
    )


async def test_without_the_plcs_mach_speed_the_cell_files_is_shown(tmp_path: Path, plc: PLC) -> None:
    path = tmp_path / "cell.toml"
    text = cell(plc, [F], ', map = { "Status.MachSpeed" = "ns=1;s=Nope", "Status.CurMachSpeed" = "ns=1;s=Nope2" }')
    path.write_text(text.replace(f'name = "{F}"', f'name = "{F}"\nmach_speed = 33'))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as (_app, client):
        assert (await call_path(client, MACH, "Reset")).StatusCode.is_good()
        await until(lambda: cell_state(client, EXEC), "Idle")
        assert await cell_read(client, f"{F}.Status.MachSpeed") == pytest.approx(33.0)
        assert (await call_path(client, EXEC, "Start", ua.Variant([], ua.VariantType.ExtensionObject))).StatusCode
        await until(lambda: cell_state(client, EXEC), "Execute")
        # no CurMachSpeed in the PLC: MachSpeed in Execute, as for a unit without a PLC
        await until(lambda: cell_read(client, f"{F}.Status.CurMachSpeed"), pytest.approx(33.0))


async def test_a_missing_handshake_tag_refuses_what_needs_it(tmp_path: Path, modbus: ModbusPLC) -> None:
    path = tmp_path / "cell.toml"
    path.write_text(
        f'[[packml_units]]\nname = "{F}"\nequipment = {{ driver = "modbus-packtags", host = "127.0.0.1", '
        f'port = {modbus.port}, map = {{ "Command.CntrlCmd" = ["holding", 9000, "int32"] }} }}\n'
    )
    proc = await config_check_connect(path)
    assert proc.returncode == 1
    problems = [ln for ln in proc.stdout.splitlines() if "PROBLEM" in ln]
    assert len(problems) == 1 and problems[0].split()[2] == "Command.CntrlCmd", problems
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as (_app, client):
        res = await call_path(client, MACH, "Reset")
        assert res.StatusCode.value == ua.StatusCodes.BadConfigurationError
        assert await modbus.tag(0, "Command.CmdChangeRequest") is False  # nothing written
        assert await cell_state(client, MACH) == "Stopped"
        # the rest of the unit works: SetUnitMode has its tags, and the PLC's speed is shown
        res = await call_path(client, F, "SetUnitMode", ua.Variant(2, ua.VariantType.Int32))
        assert res.StatusCode.is_good(), res.StatusCode
        await until(lambda: modbus.tag(0, "Status.UnitModeCurrent"), 2)
        assert await cell_read(client, f"{F}.Status.UnitModeCurrent") == 2
        assert await cell_read(client, f"{F}.Status.MachSpeed") == pytest.approx(60.0)
