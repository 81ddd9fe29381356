"""PackML units whose state machine runs in a Siemens S7 PLC, served by uacell from the cell file
alone (the s7-packtags driver): python-snap7's own S7 server holds the PackTags in data block 1 and
runs a TR88 scan-cycle program (uacell.gateway.examples.s7_plc, which answers S7 write jobs as a CPU
does: bit items change one bit, every item of a job is written) on a free port; an asyncua client
(and node-opcua once) drives uacell, which drives the PLC."""

from __future__ import annotations

import asyncio
import os
import struct
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
from uacell.gateway.packml_s7 import S7Connection, resolve_s7, where
from uacell.gateway.s7 import ByteSpan, S7Address, WriteItem, byte_spans, write_items, write_job, write_results
from uacell.server import UacellServer

SRC = str(Path(__file__).resolve().parents[1] / "src")
F, L = "Capper", "Labeler"  # the shipped cell's units: bytes from 0 and from 200 of DB 1


def machines(unit: str) -> tuple[str, str, str]:
    base = f"{unit}.BaseStateMachine"
    return base, f"{base}.MachineState", f"{base}.MachineState.ExecuteState"


BASE, MACH, EXEC = machines(F)


class S7PLC:
    """The example S7 PLC in its own process, and an S7 connection of the test's to look into it."""

    def __init__(self, units: int = 2, acting: float = 0.1) -> None:
        self.port, self.units, self.acting = free_port(), units, acting
        self.proc: subprocess.Popen[str] | None = None
        self.conn: S7Connection | None = None

    def start(self) -> None:
        cmd = [sys.executable, "-m", "uacell.gateway.examples.s7_plc", "--port", str(self.port)]
        cmd += ["--units", str(self.units), "--acting", str(self.acting)]
        self.proc = subprocess.Popen(
            cmd, env={**os.environ, "PYTHONPATH": SRC}, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        assert self.proc.stdout is not None
        line = self.proc.stdout.readline()  # the PLC prints it once it serves (or ends: "")
        assert line.strip() == "listening", line

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(10)
            if self.proc.stdout is not None:
                self.proc.stdout.close()
            self.proc = None

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


@pytest.fixture
async def plc() -> AsyncIterator[S7PLC]:
    p = S7PLC()
    p.start()
    try:
        await p.open()
        yield p
    finally:
        await p.close()
        p.kill()


def shipped_cell(plc: S7PLC) -> str:
    return builtin_cell_path("s7-packtags").read_text().replace("port = 10102", f"port = {plc.port}")


@pytest.fixture
async def served(tmp_path: Path, plc: S7PLC) -> AsyncIterator[tuple[UacellServer, Client]]:
    path = tmp_path / "cell.toml"  # the shipped example, nothing changed but the PLC's port
    path.write_text(shipped_cell(plc))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as s:
        await s[1].load_data_type_definitions()
        yield s


# -- addresses, the layout and the write job, pure ----------------------------------------------------


def test_the_default_layout_from_a_start_and_overrides() -> None:
    tags = resolve_s7("Capper", 10, start=200, parameters=2, alarms=1)
    assert tags["Status.StateCurrent"].address == "DB10.DBD200 DINT"
    assert tags["Status.MachSpeed"].address == "DB10.DBD212 REAL"
    assert tags["Command.CmdChangeRequest"].address == "DB10.DBX240.0"
    assert tags["Command.UnitModeChangeRequest"].address == "DB10.DBX240.1"
    assert tags["Admin.Alarm[0].ID"].address == "DB10.DBD242 DINT"
    assert tags["Command.Parameter[1].Value"].address == "DB10.DBD278 REAL"
    assert "Command.Parameter[2].Value" not in tags
    moved = resolve_s7("Capper", 1, overrides={"Status.StateCurrent": "DB7.DBW20", "Status.MachSpeed": "DB7.DBD4"})
    assert (moved["Status.StateCurrent"].address, moved["Status.MachSpeed"].address) == ("DB7.DBW20", "DB7.DBD4 REAL")
    held = resolve_s7("Capper", 1, overrides={"Status.MachSpeed": "db7.dbd4 dint"})["Status.MachSpeed"]
    assert S7Address.parse(held.address) == S7Address(7, 4, 0, "DINT")


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"map": {"Status.StateCurrent": "DB1.DBX0.0"}}, "Status.StateCurrent: a BOOL cannot hold the Int32"),
        ({"map": {"Command.CmdChangeRequest": "DB1.DBD0"}}, "a DBD holds DINT or REAL, not BOOL"),
        ({"map": {"Status.Nope": "DB1.DBD0"}}, "Capper: map: Status.Nope: not a PackTags tag of the map"),
        ({"map": {"Status.StateCurrent": "MD20"}}, "'MD20' is not an absolute data block address"),
        ({"map": {"Status.StateCurrent": "DB1.DBX4"}}, "a bit address is DBX<byte>.<bit>"),
        ({"map": {"Status.StateCurrent": 7}}, 'needs an address such as "DB7.DBD20"'),
        ({"parameters": 21}, "Capper: parameters: a whole number from 0 to 20"),
        ({"slot": 40}, "Capper: slot: a whole number from 0 to 31"),
        ({"db": 0}, "Capper: db: a whole number from 1 to 65535"),
        ({"interval": 0}, "Capper: interval"),
        ({"bogus": 1}, "the s7-packtags driver has no setting 'bogus'"),
        ({"host": ""}, "Capper: host"),
    ],
)  # fmt: skip
def test_settings_that_cannot_work_are_one_line(settings: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError) as info:
        where("Capper", {"host": "plc"} | settings)
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_nearby_bytes_are_read_in_one_request() -> None:
    tags = [S7Address.parse(t.address) for t in resolve_s7("U", 1, 0, alarms=2).values()]
    # one read: a unit's state and its change request come from the same scan
    assert byte_spans(tags) == [ByteSpan(1, 0, 94)]
    far = [S7Address(1, 0, 0, "DINT"), S7Address(1, 400, 0, "DINT"), S7Address(2, 0, 0, "BOOL")]
    assert byte_spans(far) == [ByteSpan(1, 0, 4), ByteSpan(1, 400, 4), ByteSpan(2, 0, 1)]
    wide = [S7Address(1, b, 0, "DINT") for b in range(0, 400, 10)]
    assert all(s.count <= 200 for s in byte_spans(wide)) and len(byte_spans(wide)) == 2


def test_a_command_is_one_write_job_bits_as_bit_items() -> None:
    """The S7comm "write variable" job, byte by byte: the parameters and the command in one byte item
    (neighbours), the change request as a bit item (transport size BIT, its address in bits)."""
    writes: list[tuple[S7Address, object]] = [
        (S7Address(1, 74, 0, "REAL"), 1.5),
        (S7Address(1, 78, 0, "REAL"), 2.0),
        (S7Address(1, 28, 0, "DINT"), 2),
        (S7Address(1, 40, 0, "BOOL"), True),
    ]
    items = write_items(writes)
    assert items == [
        WriteItem(1, 74, struct.pack(">ff", 1.5, 2.0)),
        WriteItem(1, 28, struct.pack(">i", 2)),
        WriteItem(1, 40, b"\x01", bit=0),
    ]
    pdu = write_job(7, items)
    header, params = pdu[:10], pdu[10 : 10 + 2 + 3 * 12]
    assert struct.unpack(">BBHHHH", header) == (0x32, 0x01, 0, 7, 2 + 36, 4 + 8 + 4 + 4 + 4 + 1)
    assert params[:2] == b"\x05\x03"
    assert params[2:14] == bytes([0x12, 0x0A, 0x10, 0x02, 0, 8, 0, 1, 0x84]) + (74 * 8).to_bytes(3, "big")
    assert params[26:38] == bytes([0x12, 0x0A, 0x10, 0x01, 0, 1, 0, 1, 0x84]) + (40 * 8 + 0).to_bytes(3, "big")
    data = pdu[10 + 38 :]
    assert data[:4] == bytes([0, 0x04, 0, 64]) and data[4:12] == struct.pack(">ff", 1.5, 2.0)
    assert data[12:16] == bytes([0, 0x04, 0, 32]) and data[-5:] == bytes([0, 0x03, 0, 1, 1])
    assert write_results(bytes([0xFF, 0x0A, 0xFF]), 3) == ["", "object does not exist (0x0a)", ""]


# -- against the S7 PLC --------------------------------------------------------------------------------


async def test_a_bit_written_leaves_its_neighbours(plc: S7PLC) -> None:
    """The request bits share byte 40: writing one (a bit item) keeps the other (the test PLC answers
    bit items as an S7 does; snap7's stock server would overwrite the byte)."""
    await plc.switch(0, 1, True)  # frozen: nothing takes the requests
    await plc.put(0, "Command.UnitModeChangeRequest", True)
    await plc.put(0, "Command.CmdChangeRequest", True)
    assert await plc.tag(0, "Command.UnitModeChangeRequest") is True
    assert await plc.tag(0, "Command.CmdChangeRequest") is True
    await plc.put(0, "Command.CmdChangeRequest", False)
    assert await plc.tag(0, "Command.UnitModeChangeRequest") is True


async def test_a_full_cycle_goes_to_the_plc_and_comes_back(served, plc: S7PLC) -> None:
    _app, client = served
    from uacell.gateway.packml_s7 import POOL

    assert len(POOL) == 1  # both units on one connection
    assert await plc.tag(0, "Status.StateCurrent") == 2  # Stopped
    assert await cell_state(client, MACH) == "Stopped"
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.is_good(), res.StatusCode
    assert await plc.tag(0, "Status.StateCurrent") in (15, 4)  # the PLC took it before the call answered
    await until(lambda: cell_state(client, EXEC), "Idle")
    assert (await call_path(client, F, "SetMachSpeed", ua.Variant(120.0, ua.VariantType.Float))).StatusCode.is_good()
    await until(lambda: plc.tag(0, "Command.MachSpeed"), 120.0)
    await plc.put(0, "Command.Parameter[4].Value", 9.5)  # an older Start's value, left in the PLC
    res = await call_path(client, EXEC, "Start", packml_params((1, 180.5), (2, 0.25)))
    assert res.StatusCode.is_good(), res.StatusCode
    assert await plc.taken() == pytest.approx([180.5, 0.25, 0.0, 0.0, 0.0])  # unused slots are written 0.0
    await until(lambda: cell_state(client, EXEC), "Execute")
    await until(lambda: cell_read(client, f"{F}.Status.CurMachSpeed"), pytest.approx(120.0))  # the PLC's

    async def produced() -> bool:  # the PLC's count, mirrored into Admin.ProdProcessedCount
        (count,) = await cell_read(client, f"{F}.Admin.ProdProcessedCount")
        return bool(count.Count > 0)

    await until(produced, True)
    assert (await call_path(client, MACH, "Stop")).StatusCode.is_good()
    await until(lambda: cell_state(client, MACH), "Stopped")
    assert await plc.tag(0, "Status.StateCurrent") == 2
    # uacell's own rules before the PLC's: Start is not allowed in Stopped, nothing is written
    res = await call_path(client, EXEC, "Start", packml_params())
    assert res.StatusCode.value in (ua.StatusCodes.BadInvalidState, ua.StatusCodes.BadMethodInvalid)
    assert await plc.tag(0, "Command.CntrlCmd") == 3  # still the Stop
    # six parameters where the PLC has five: refused, nothing written
    res = await call_path(client, MACH, "Reset")
    await until(lambda: cell_state(client, EXEC), "Idle")
    res = await call_path(client, EXEC, "Start", packml_params(*((i, float(i)) for i in range(6))))
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidArgument
    assert await plc.tag(0, "Command.CntrlCmd") == 1
    # the other unit on the same connection, bytes from 200, was not touched
    assert await cell_state(client, machines(L)[1]) == "Stopped" and await plc.tag(200, "Status.StateCurrent") == 2
    res = await call_path(client, machines(L)[1], "Reset")
    assert res.StatusCode.is_good(), res.StatusCode
    await until(lambda: plc.tag(200, "Status.StateCurrent"), 4)
    # unit modes go through the PLC with their own handshake (their request bit beside the command's)
    res = await call_path(client, F, "SetUnitMode", ua.Variant(2, ua.VariantType.Int32))
    assert res.StatusCode.is_good(), res.StatusCode
    assert await plc.tag(0, "Status.UnitModeCurrent") == 2
    assert await cell_read(client, f"{F}.Status.UnitModeCurrent") == 2


async def test_a_command_the_plc_refuses_or_never_takes(served, plc: S7PLC) -> None:
    _app, client = served
    await plc.switch(0, 0, True)  # refuse
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.value == ua.StatusCodes.BadInvalidState
    assert await cell_state(client, MACH) == "Stopped" and await plc.tag(0, "Status.StateCurrent") == 2
    await plc.switch(0, 0, False)
    await plc.switch(0, 1, True)  # frozen: no scan takes the request
    started = time.monotonic()
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.value == ua.StatusCodes.BadTimeout
    assert time.monotonic() - started >= 2.5  # confirm_timeout 3 s
    assert await plc.tag(0, "Command.CmdChangeRequest") is False  # nothing left half-written
    assert await cell_state(client, MACH) == "Stopped"


async def test_the_plc_faults_and_uacell_aborts_with_its_stop_reason(served, plc: S7PLC) -> None:
    _app, client = served
    assert (await call_path(client, MACH, "Reset")).StatusCode.is_good()
    await until(lambda: cell_state(client, EXEC), "Idle")
    await plc.switch(0, 2, True)
    await until(lambda: cell_state(client, BASE), "Aborted")
    assert (await cell_read(client, f"{F}.Admin.StopReason")).ID == 42


async def test_the_plc_killed_and_back_nothing_replayed(served, plc: S7PLC) -> None:
    _app, client = served
    assert (await call_path(client, MACH, "Reset")).StatusCode.is_good()
    await until(lambda: cell_state(client, EXEC), "Idle")
    await plc.close()
    plc.kill()

    def executable() -> Any:
        return cell_executable(client, f"{EXEC}.Start")

    await until(executable, False)
    res = await call_path(client, EXEC, "Start", packml_params())
    assert res.StatusCode.value == ua.StatusCodes.BadCommunicationError

    def speed_status() -> Any:
        return cell_status(client, f"{F}.Status.MachSpeed")

    await until(speed_status, "BadNoCommunication")
    await until(lambda: cell_status(client, f"{MACH}.CurrentState"), "UncertainNoCommunicationLastUsableValue")
    plc.start()  # the same port: a PLC restarted, in Stopped, its command tags 0
    back = time.monotonic()
    await until(lambda: cell_state(client, MACH), "Stopped")  # the PLC's state as it now is
    assert time.monotonic() - back <= 5.0
    await until(speed_status, "Good")
    await plc.open()
    assert await plc.tag(0, "Command.CntrlCmd") == 0  # the refused Start was not replayed
    assert await plc.tag(0, "Command.CmdChangeRequest") is False
    res = await call_path(client, MACH, "Reset")
    assert res.StatusCode.is_good(), res.StatusCode
    await until(lambda: plc.tag(0, "Status.StateCurrent"), 4)


async def test_node_opcua_runs_a_cycle_through_uacell_to_the_s7_plc(tmp_path: Path, plc: S7PLC) -> None:
    """The independent client: node-opcua resets and starts (with two parameters) a unit the PLC owns."""
    from conftest import run_node

    path = tmp_path / "cell.toml"
    path.write_text(shipped_cell(plc).replace(f'name = "{F}"', 'name = "Filler1"'))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as (app, _client):
        out = await asyncio.to_thread(run_node, "packml_start.js", app.endpoint)
        assert (out["reset"], out["start"], out["state"]) == ("Good", "Good", "Execute")
        assert await plc.tag(0, "Status.StateCurrent") == 6  # the PLC is in Execute
        assert await plc.taken() == pytest.approx([250.5, -12.25, 0.0, 0.0, 0.0])


async def test_config_check_connect_names_an_address_the_plc_does_not_have(tmp_path: Path, plc: S7PLC) -> None:
    text = shipped_cell(plc).replace(
        "start = 200 }",
        'start = 200, alarms = 2, map = { "Admin.StopReason" = "DB9.DBD0", "Admin.Alarm[1].ID" = "DB1.DBD9000" } }',
    )
    path = tmp_path / "cell.toml"
    path.write_text(text)
    proc = await config_check_connect(path)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    bad = [ln for ln in lines if "PROBLEM" in ln]
    assert len(bad) == 2 and all(ln.startswith("Labeler") for ln in bad), lines
    assert "Admin.StopReason" in bad[0] and "PROBLEM: DB9.DBD0 DINT: Object does not exist (0x0a)" in bad[0], bad
    assert "Admin.Alarm[1].ID" in bad[1] and "DB1.DBD9000 DINT: Invalid address (0x05)" in bad[1], bad
    assert any(ln.startswith("Capper") and "Status.StateCurrent" in ln and "= 2" in ln for ln in lines), lines
    assert "connect: 34 of 36 as configured" in proc.stdout, proc.stdout  # 17 + 19 tags (2 alarms)
    # served: both optional, so the unit works
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as (_app, client):
        res = await call_path(client, machines(L)[1], "Reset")
        assert res.StatusCode.is_good(), res.StatusCode
        await until(lambda: plc.tag(200, "Status.StateCurrent"), 4)


def test_units_on_one_plc_must_agree_on_the_connection() -> None:
    """One connection per PLC (host, port, rack, slot): a second unit on it with another poll interval
    is refused, naming the unit and the setting; another slot is another PLC (its own connection)."""
    from uacell.gateway.link import SharedLinks
    from uacell.gateway.packml_s7 import S7Connection, S7TagLink

    pool = SharedLinks()

    def get(part: str, settings: dict[str, Any]) -> Any:
        w = where(part, {"host": "plc"} | settings)
        key = (w.host, w.port, w.rack, w.slot)
        return pool.link(part, key, w.interval, w.timeout, lambda: S7TagLink(S7Connection(*key, w.timeout), w.interval))

    first = get("Capper", {"start": 0})
    assert get("Labeler", {"start": 200}) is first
    with pytest.raises(ValueError, match=r"Filler: interval: another unit on s7://plc:102 rack 0 slot 1 set 0\.05"):
        get("Filler", {"start": 400, "interval": 0.2})
    assert get("Other", {"slot": 2, "interval": 0.2}) is not first
    assert first.users == 2
