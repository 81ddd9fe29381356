"""PackML units whose state machine runs in a PLC that speaks Modbus/TCP only, served by uacell from
the cell file alone (the modbus-packtags driver): pymodbus's server holds the PackTags registers and
runs a TR88 scan-cycle program (uacell.gateway.examples.packtags_plc) on a free port; an asyncua
client (and node-opcua once) drives uacell, which drives the PLC.

The scenarios every polled PackTags driver passes (a full cycle, a refused and a frozen command, a
fault, the PLC killed and back, node-opcua's cycle) are in test_gateway_packml_acceptance.py; here
is what only this transport has."""

from __future__ import annotations

import asyncio
import logging
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, serving
from gateway_plcs import ModbusPLC, serving_cell
from gateway_plcs import modbus_cell as shipped_cell
from helpers import (
    call_path,
    cell_state,
    cell_status,
    config_check_connect,
    until,
)

from uacell.config import load_cell
from uacell.gateway.codec import RegisterType
from uacell.gateway.modbus import MAX_SPAN, ModbusTag, Span, spans
from uacell.gateway.packml_modbus import Point, resolve_modbus, where
from uacell.server import UacellServer

F, L = "Capper", "Labeler"  # the shipped cell's units: registers from 0 and from 100


def machines(unit: str) -> tuple[str, str, str]:
    base = f"{unit}.BaseStateMachine"
    return base, f"{base}.MachineState", f"{base}.MachineState.ExecuteState"


BASE, MACH, EXEC = machines(F)


@pytest.fixture
async def plc() -> AsyncIterator[ModbusPLC]:
    p = ModbusPLC()
    p.start()
    try:
        await p.open()
        yield p
    finally:
        p.close()
        p.kill()


@pytest.fixture
async def served(tmp_path: Path, plc: ModbusPLC) -> AsyncIterator[tuple[UacellServer, Client]]:
    async with serving_cell(tmp_path, shipped_cell(plc)) as s:  # the shipped example, pointed at the PLC
        yield s


# -- the map, pure ----------------------------------------------------------------------------------


def test_the_default_layout_from_a_base_and_overrides() -> None:
    tags = resolve_modbus("Capper", 3, base=100, parameters=2, alarms=1)
    assert tags["Status.StateCurrent"].address == "unit 3 holding 100 int32 big/big"
    assert tags["Command.CmdChangeRequest"].address == "unit 3 holding 116 bool big/big"
    assert tags["Command.Parameter[1].Value"].address == "unit 3 holding 142 float32 big/big"
    assert tags["Admin.Alarm[0].ID"].address == "unit 3 holding 124 int32 big/big"
    assert "Command.Parameter[2].Value" not in tags
    assert (tags["Command.MachSpeed"].type_name, tags["Command.CmdChangeRequest"].type_name) == ("Float", "Boolean")
    moved = resolve_modbus("Capper", 1, overrides={"Status.StateCurrent": ["input", 7, "uint16"]}, word_order="little")
    point = Point.parse(moved["Status.StateCurrent"].address)
    assert (point.tag.table, point.tag.address, point.tag.rtype.name, point.tag.rtype.word_order) == (
        "input", 7, "uint16", "little"
    )  # fmt: skip
    assert Point.parse(str(point)) == point


@pytest.mark.parametrize(
    ("settings", "message"),
    [
        ({"map": {"Status.StateCurrent": ["holding", 0, "bool"]}}, "Status.StateCurrent: a bool cannot hold the Int32"),
        ({"map": {"Command.CntrlCmd": ["input", 0, "int32"]}}, "Command.CntrlCmd: uacell writes this tag; an input"),
        ({"map": {"Status.Nope": ["holding", 0, "int32"]}}, "Capper: map: Status.Nope: not a PackTags tag of the map"),
        ({"map": {"Status.StateCurrent": ["holding", "x", "int32"]}}, "needs [table, address, type]"),
        ({"map": {"Status.StateCurrent": ["register", 0, "int32"]}}, "Status.StateCurrent: table 'register'"),
        ({"parameters": 21}, "Capper: parameters: a whole number from 0 to 20"),
        ({"base": 1.5}, "Capper: base: a whole number from 0 to 65435, not 1.5"),
        ({"word_order": "middle"}, "Capper: map: Status.StateCurrent: word_order 'middle'"),
        ({"interval": 0}, "Capper: interval"),
        ({"bogus": 1}, "the modbus-packtags driver has no setting 'bogus'"),
        ({"host": ""}, "Capper: host"),
    ],
)  # fmt: skip
def test_settings_that_cannot_work_are_one_line(settings: dict[str, Any], message: str) -> None:
    with pytest.raises(ValueError) as info:
        where("Capper", {"host": "plc"} | settings)
    assert message in str(info.value)
    assert "\n" not in str(info.value)


def test_nearby_tags_are_read_in_one_request() -> None:
    tags = [Point.parse(t.address).tag for t in resolve_modbus("U", 1, 0, alarms=2).values()]
    watched = [t for t in tags if t.address in (0, 2, 8, 10, 12, 24, 26)]
    assert spans(watched) == [Span("holding", 0, 28)]
    far = [ModbusTag("holding", 0, RegisterType("int32")), ModbusTag("holding", 100, RegisterType("int32"))]
    assert spans(far) == [Span("holding", 0, 2), Span("holding", 100, 2)]
    wide = [ModbusTag("holding", a, RegisterType("uint16")) for a in range(0, 200, 10)]
    assert all(s.count <= MAX_SPAN["holding"] for s in spans(wide)) and len(spans(wide)) == 2
    mixed = [ModbusTag("coil", 3, RegisterType("bool")), ModbusTag("holding", 3, RegisterType("bool"))]
    assert spans(mixed) == [Span("coil", 3, 1), Span("holding", 3, 1)]


# -- against the Modbus PLC -------------------------------------------------------------------------


async def test_config_check_connect_names_a_register_the_plc_does_not_have(
    tmp_path: Path, plc: ModbusPLC, caplog: pytest.LogCaptureFixture
) -> None:
    text = shipped_cell(plc).replace(
        "base = 100 }", 'base = 100, map = { "Admin.StopReason" = ["holding", 9000, "int32"] } }'
    )
    path = tmp_path / "cell.toml"
    path.write_text(text)
    proc = await config_check_connect(path)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    lines = proc.stdout.splitlines()
    bad = [ln for ln in lines if "PROBLEM" in ln]
    assert len(bad) == 1 and bad[0].startswith("Labeler") and "Admin.StopReason" in bad[0], lines
    assert "PROBLEM: unit 1 holding 9000 int32 big/big: illegal data address (exception 2)" in bad[0], lines
    assert any(ln.startswith("Capper") and "Status.StateCurrent" in ln and "= 2" in ln for ln in lines), lines
    assert "connect: 33 of 34 as configured" in proc.stdout, proc.stdout
    # served anyway: one log line names the unit, the tag, where it was looked for and what the PLC
    # said; the tag is optional, so both units work (issue 42: one missing tag is not a dead unit)
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    with caplog.at_level(logging.WARNING, logger="uacell.gateway.packml_plc"):
        async with serving(config) as (_app, client):

            def stop_reason_logged() -> Any:
                async def found() -> bool:
                    return any(
                        "Labeler: the PLC has no Admin.StopReason (unit 1 holding 9000" in r.getMessage()
                        for r in caplog.records
                    )

                return found()

            await until(stop_reason_logged, True)
            await until(lambda: cell_status(client, f"{F}.Status.MachSpeed"), "Good")
            res = await call_path(client, machines(L)[1], "Reset")
            assert res.StatusCode.is_good(), res.StatusCode
            await until(lambda: cell_state(client, machines(L)[2]), "Idle")
            assert await plc.tag(100, "Status.StateCurrent") == 4
    said = [r.getMessage() for r in caplog.records if "Admin.StopReason" in r.getMessage()]
    assert "illegal data address (exception 2)); the unit works without it" in said[0], said
    assert len(said) == 1, said  # once


async def test_fifty_units_on_one_modbus_connection(tmp_path: Path) -> None:
    """50 units of one PLC, registers 100 apart, reset at once: one connection, every one in Idle.

    The PLC simulator is a Python process sharing two cores with the whole suite: it is given 5 s to
    answer instead of the default 1 s (a loaded CI run once saw one answer come later than that)."""
    from uacell.gateway.modbus import SHARED
    from uacell.gateway.packml_modbus import POOL

    p = ModbusPLC(units=50)
    p.start()
    try:
        await p.open()
        path = tmp_path / "cell.toml"
        path.write_text(
            "".join(
                f'[[packml_units]]\nname = "U{i}"\nequipment = {{ driver = "modbus-packtags", host = "127.0.0.1", '
                f"port = {p.port}, base = {100 * i}, timeout = 5.0 }}\n\n"
                for i in range(50)
            )
        )
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (_app, client):
            assert len(POOL) == 1 and len(SHARED) == 1

            async def reset(i: int) -> str:
                return str((await call_path(client, machines(f"U{i}")[1], "Reset")).StatusCode.name)

            results = await asyncio.gather(*(reset(i) for i in range(50)))
            assert results == ["Good"] * 50
            for i in range(50):
                await until(lambda i=i: cell_state(client, machines(f"U{i}")[2]), "Idle")
                assert await p.tag(100 * i, "Status.StateCurrent") == 4  # nothing lost: Idle in the PLC too
    finally:
        p.close()
        p.kill()


async def test_communication_lost_is_an_alarm_condition(served, plc: ModbusPLC) -> None:
    """While the PLC is away the unit's CommunicationLost condition (AlarmConditionType, in
    <unit>/Conditions) is active and its events reach alarm clients; an operator acknowledges it with
    the EventId it carries; it clears when the PLC answers again."""
    app, client = served
    ns = await client.get_namespace_index("urn:uacell:cell")
    cond = ua.NodeId(f"{F}.Conditions.CommunicationLost", ns)

    def read(path: str) -> Any:
        return client.get_node(ua.NodeId(f"{F}.Conditions.CommunicationLost.{path}", ns)).read_value()

    assert await read("ActiveState.Id") is False and await read("AckedState.Id") is True
    assert await read("SourceName") == F
    arrived: list[Any] = []

    class Events:
        def event_notification(self, event: Any) -> None:
            arrived.append(event)

    sub = await client.create_subscription(20, Events())
    await sub.subscribe_events(client.get_node(ua.ObjectIds.Server), client.get_node(ua.ObjectIds.AlarmConditionType))
    plc.close()
    plc.kill()
    await until(lambda: read("ActiveState.Id"), True)
    assert await read("AckedState.Id") is False and "communication lost" in (await read("Message")).Text

    async def lost_event() -> bool:
        return any(e.SourceName == F and e.ActiveState.Text == "Active" for e in arrived)

    await until(lost_event, True)
    acknowledge = app.dispatcher.method_of(cond, "Acknowledge")

    async def acknowledgeable() -> bool:
        dv = await client.get_node(acknowledge).read_attribute(ua.AttributeIds.Executable)
        return bool(dv.Value.Value)

    await until(acknowledgeable, True)  # raised by the equipment, outside any call
    event_id = ua.Variant(await read("EventId"), ua.VariantType.ByteString)
    comment = ua.Variant(ua.LocalizedText("cable checked"), ua.VariantType.LocalizedText)
    (res,) = await client.uaclient.call([ua.CallMethodRequest(cond, acknowledge, [event_id, comment])])
    assert res.StatusCode.is_good(), res.StatusCode
    await until(lambda: read("AckedState.Id"), True)
    await until(acknowledgeable, False)
    (again,) = await client.uaclient.call([ua.CallMethodRequest(cond, acknowledge, [event_id, comment])])
    assert again.StatusCode.value == ua.StatusCodes.BadConditionBranchAlreadyAcked
    plc.start()
    await until(lambda: read("ActiveState.Id"), False)
    assert await read("Retain") is False  # inactive and acknowledged: nothing left for an alarm list
    await sub.delete()


async def test_uacell_started_while_the_plc_runs_follows_it_there(tmp_path: Path, plc: ModbusPLC) -> None:
    """The PLC is in Execute (started from its own panel) before uacell starts: uacell's three
    machines reach Execute by TR88's steps, and a Stop from a client then goes to the PLC."""
    state, command, request = (Point.parse(resolve_modbus("t", 1, 0)[k].address).tag for k in (
        "Status.StateCurrent", "Command.CntrlCmd", "Command.CmdChangeRequest"))  # fmt: skip
    assert plc.conn is not None
    for cmd, reached in ((1, 4), (2, 6)):  # Reset -> Idle, Start -> Execute, at the PLC's panel
        await plc.conn.write_block("holding", command.address, [*command.rtype.encode(cmd), 1], 1)
        await until(lambda: plc.conn.read(state, 1), reached)
    assert request.address == command.address + 2  # written together above
    path = tmp_path / "cell.toml"
    path.write_text(shipped_cell(plc))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as (_app, client):
        await until(lambda: cell_state(client, EXEC), "Execute", timeout=5.0)
        assert (await cell_state(client, MACH), await cell_state(client, BASE)) == ("Running", "Cleared")
        res = await call_path(client, MACH, "Stop")
        assert res.StatusCode.is_good(), res.StatusCode
        await until(lambda: plc.tag(0, "Status.StateCurrent"), 2)
        await until(lambda: cell_state(client, MACH), "Stopped")
