"""PackML units whose state machine runs in a Rockwell Logix controller, served by uacell from the
cell file alone (the logix-packtags driver, pylogix over EtherNet/IP): cpppo's EtherNet/IP Logix
simulator holds the PackTags as Logix tags by name and runs a TR88 scan-cycle program
(uacell.gateway.examples.logix_plc) on a free port; an asyncua client (and node-opcua once) drives
uacell, which drives the controller. cpppo cannot resolve an array index inside a dotted name, so
the simulator's parameters are a top-level array the cell maps (docs/equipment.md says what the
simulator could not cover)."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, serving
from helpers import (
    call_path,
    cell_executable,
    cell_read,
    cell_state,
    cell_status,
    config_check_connect,
    free_port,
    packml_params,
    until,
)

from uacell.cell_file import builtin_cell_path
from uacell.config import load_cell
from uacell.gateway.packml_logix import LogixConnection, where
from uacell.server import UacellServer

SRC = str(Path(__file__).resolve().parents[1] / "src")
F = "Capper"
BASE, MACH, EXEC = (
    f"{F}.BaseStateMachine",
    f"{F}.BaseStateMachine.MachineState",
    f"{F}.BaseStateMachine.MachineState.ExecuteState",
)


class LogixPLC:
    """The example controller (cpppo) in its own process, and a pylogix session of the test's."""

    def __init__(self, units: str = F, acting: float = 0.1) -> None:
        self.port, self.units, self.acting = free_port(), units, acting
        self.proc: subprocess.Popen[str] | None = None
        self.conn: LogixConnection | None = None

    def start(self) -> None:
        cmd = [sys.executable, "-m", "uacell.gateway.examples.logix_plc", "--port", str(self.port)]
        cmd += ["--units", self.units, "--acting", str(self.acting)]
        self.proc = subprocess.Popen(
            cmd, env={**os.environ, "PYTHONPATH": SRC}, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()
        assert line.strip() == "listening", line

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(10)
            if self.proc.stdout is not None:
                self.proc.stdout.close()
            self.proc = None

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
        return [float(await self.tag(f"{F}_Taken[{i}]")) for i in range(5)]


@pytest.fixture
async def plc() -> AsyncIterator[LogixPLC]:
    p = LogixPLC()
    p.start()
    try:
        await p.open()
        yield p
    finally:
        await p.close()
        p.kill()


def shipped_cell(plc: LogixPLC) -> str:
    return builtin_cell_path("logix-packtags").read_text().replace("port = 44819", f"port = {plc.port}")


@pytest.fixture
async def served(tmp_path: Path, plc: LogixPLC) -> AsyncIterator[tuple[UacellServer, Client]]:
    path = tmp_path / "cell.toml"
    path.write_text(shipped_cell(plc))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as s:
        await s[1].load_data_type_definitions()
        yield s


def test_tags_by_name_under_the_prefix_and_overrides() -> None:
    w = where(F, {"host": "plc", "prefix": "Capper", "alarms": 1, "map": {"Status.StateCurrent": "Program:Line.State"}})
    assert w.tags["Command.CntrlCmd"].address == "Capper.Command.CntrlCmd"
    assert w.tags["Command.Parameter[2].Value"].address == "Capper.Command.Parameter[2].Value"
    assert w.tags["Admin.Alarm[0].ID"].address == "Capper.Admin.Alarm[0].ID"
    assert w.tags["Admin.StopReason"].address == "Capper.Admin.StopReason.ID"
    assert w.tags["Status.StateCurrent"].address == "Program:Line.State"
    assert (w.port, w.slot) == (44818, 0)


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"prefix": "ns=3;s=Capper"}, "Capper: prefix: 'ns=3;s=Capper' is not a Logix tag name"),
        ({"prefix": ""}, "Capper: prefix: empty, and no tag is given in full"),
        ({"map": {"Status.Nope": "X"}}, "Capper: Status.Nope: not a PackTags tag of the map"),
        ({"map": {"Status.StateCurrent": 3}}, "Capper: map: a table of tag = "),
        ({"slot": 40}, "Capper: slot: a whole number from 0 to 31"),
        ({"bogus": 1}, "the logix-packtags driver has no setting 'bogus'"),
    ],
)  # fmt: skip
def test_settings_that_cannot_work_are_one_line(settings: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError) as info:
        where("Capper", {"host": "plc", "prefix": "Capper"} | settings)
    assert message in str(info.value)
    assert "\n" not in str(info.value)


async def test_a_full_cycle_goes_to_the_controller_and_comes_back(served, plc: LogixPLC) -> None:
    _app, client = served
    assert await plc.tag(f"{F}.Status.StateCurrent") == 2
    assert await cell_state(client, MACH) == "Stopped"
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.is_good(), res.StatusCode
    assert await plc.tag(f"{F}.Status.StateCurrent") in (15, 4)
    await until(lambda: cell_state(client, EXEC), "Idle")
    assert (await call_path(client, F, "SetMachSpeed", ua.Variant(120.0, ua.VariantType.Float))).StatusCode.is_good()
    await until(lambda: plc.tag(f"{F}.Command.MachSpeed"), 120.0)
    await plc.put(f"{F}_Parameter[4]", 9.5)  # an older Start's value
    res = await call_path(client, EXEC, "Start", packml_params((1, 180.5), (2, 0.25)))
    assert res.StatusCode.is_good(), res.StatusCode
    assert await plc.taken() == pytest.approx([180.5, 0.25, 0.0, 0.0, 0.0])
    await until(lambda: cell_state(client, EXEC), "Execute")
    await until(lambda: cell_read(client, f"{F}.Status.CurMachSpeed"), pytest.approx(120.0))

    async def produced() -> bool:
        (count,) = await cell_read(client, f"{F}.Admin.ProdProcessedCount")
        return bool(count.Count > 0)

    await until(produced, True)
    assert (await call_path(client, MACH, "Stop")).StatusCode.is_good()
    await until(lambda: cell_state(client, MACH), "Stopped")
    res = await call_path(client, EXEC, "Start", packml_params())
    assert res.StatusCode.value in (ua.StatusCodes.BadInvalidState, ua.StatusCodes.BadMethodInvalid)
    assert await plc.tag(f"{F}.Command.CntrlCmd") == 3
    res = await call_path(client, F, "SetUnitMode", ua.Variant(2, ua.VariantType.Int32))
    assert res.StatusCode.is_good(), res.StatusCode
    assert await plc.tag(f"{F}.Status.UnitModeCurrent") == 2


async def test_a_command_the_controller_refuses_or_never_takes(served, plc: LogixPLC) -> None:
    _app, client = served
    await plc.put(f"{F}_Refuse", True)
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState
    await plc.put(f"{F}_Refuse", False)
    await plc.put(f"{F}_Frozen", True)
    started = time.monotonic()
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.value == ua.StatusCodes.BadTimeout
    assert time.monotonic() - started >= 2.5
    assert await plc.tag(f"{F}.Command.CmdChangeRequest") is False
    assert await cell_state(client, MACH) == "Stopped"


async def test_the_controller_faults_and_uacell_aborts_with_its_stop_reason(served, plc: LogixPLC) -> None:
    _app, client = served
    assert (await call_path(client, MACH, "Reset")).StatusCode.is_good()
    await until(lambda: cell_state(client, EXEC), "Idle")
    await plc.put(f"{F}_Fault", True)
    await until(lambda: cell_state(client, BASE), "Aborted")
    assert (await cell_read(client, f"{F}.Admin.StopReason")).ID == 42


async def test_the_controller_killed_and_back_nothing_replayed(served, plc: LogixPLC) -> None:
    _app, client = served
    await plc.close()
    plc.kill()
    await until(lambda: cell_executable(client, f"{MACH}.Reset"), False)
    assert (await call_path(client, MACH, "Reset")).StatusCode.value == ua.StatusCodes.BadCommunicationError
    await until(lambda: cell_status(client, f"{F}.Status.MachSpeed"), "BadNoCommunication")
    plc.start()
    await until(lambda: cell_executable(client, f"{MACH}.Reset"), True)
    await until(lambda: cell_status(client, f"{F}.Status.MachSpeed"), "Good")
    await plc.open()
    assert await plc.tag(f"{F}.Command.CmdChangeRequest") is False  # the refused Reset was not replayed
    assert await plc.tag(f"{F}.Command.CntrlCmd") == 0
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.is_good(), res.StatusCode
    await until(lambda: plc.tag(f"{F}.Status.StateCurrent"), 4)


async def test_node_opcua_runs_a_cycle_through_uacell_to_the_controller(tmp_path: Path) -> None:
    from conftest import run_node

    p = LogixPLC(units="Filler1")
    p.start()
    try:
        await p.open()
        path = tmp_path / "cell.toml"
        path.write_text(shipped_cell(p).replace("Capper", "Filler1"))
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (app, _client):
            out = await asyncio.to_thread(run_node, "packml_start.js", app.endpoint)
            assert (out["reset"], out["start"], out["state"]) == ("Good", "Good", "Execute")
            assert await p.tag("Filler1.Status.StateCurrent") == 6
            assert [float(await p.tag(f"Filler1_Taken[{i}]")) for i in range(2)] == pytest.approx([250.5, -12.25])
    finally:
        await p.close()
        p.kill()


async def test_config_check_connect_names_a_tag_the_controller_does_not_have(tmp_path: Path, plc: LogixPLC) -> None:
    path = tmp_path / "cell.toml"
    path.write_text(
        shipped_cell(plc).replace(
            '"Capper_Parameter[4]" }', '"Capper_Parameter[4]", "Admin.StopReason" = "Capper.Nope" }'
        )
    )
    proc = await config_check_connect(path)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    bad = [ln for ln in proc.stdout.splitlines() if "PROBLEM" in ln]
    assert len(bad) == 1 and "Admin.StopReason" in bad[0] and "Capper.Nope: Path destination unknown" in bad[0], bad
    assert "connect: 16 of 17 as configured" in proc.stdout, proc.stdout
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as (_app, client):  # optional: the unit works
        res = await call_path(client, MACH, "Reset")
        assert res.StatusCode.is_good(), res.StatusCode
