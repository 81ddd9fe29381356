"""modbus-signals: faults, the reset handshake, refused starts and the controller's own programs, against
the example controller (pymodbus's server and its scan-cycle program, its panel switched by the test
through Modbus as an operator would at the cabinet), served by uacell from the cell file alone."""

from __future__ import annotations

import dataclasses
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from asyncua import Client, ua
from conftest import fast_config, serving
from helpers import config_check_connect
from test_gateway_robot import (
    COND,
    PLC,
    READY,
    SO,
    TC,
    TIMING,
    call,
    cell_text,
    held,
    read,
    running_plc,
    s,
    state,
    status,
    until_state,
    wait_controller,
    wait_until_async,
)

from uacell.config import load_cell
from uacell.core.roles import Role
from uacell.gateway.codec import RegisterType
from uacell.gateway.examples.robot_controller import ESTOP, ESTOP_CODE, MODE, PSTOP, REMOTE_OFF
from uacell.gateway.modbus import ModbusTag
from uacell.gateway.modbus_robot import ModbusRobotIO
from uacell.server import UacellServer

FAULT = f"{COND}.ControllerFault"
PROGRAMS = "Palletizer.Controllers.Cabinet.Programs"


@pytest.fixture
async def plc() -> AsyncIterator[PLC]:
    async with running_plc(30.0) as p:  # a run lasts until stopped or faulted
        yield p


@pytest.fixture
async def served(tmp_path: Path, plc: PLC) -> AsyncIterator[tuple[UacellServer, Client]]:
    await plc.io()
    cell = tmp_path / "cell.toml"
    cell.write_text(cell_text(plc.port, palletize=99))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(cell)
    async with serving(config) as served:
        yield served


async def panel(io: ModbusRobotIO, register: int, on: bool) -> None:
    """Switch the controller's panel (its own holding registers, not one of uacell's signals)."""
    await io.conn.write(ModbusTag("holding", register, RegisterType("uint16")), int(on), 1)


async def acknowledge(client: Client, condition: str) -> ua.StatusCode:
    event_id = await read(client, f"{condition}.EventId")
    comment = ua.Variant(ua.LocalizedText("reset at the cabinet"), ua.VariantType.LocalizedText)
    res = await call(client, condition, "Acknowledge", ua.Variant(event_id, ua.VariantType.ByteString), comment)
    return res.StatusCode


async def test_an_emergency_stop_latched_until_acknowledged_then_recovered_over_opc_ua(served, plc: PLC) -> None:
    """E-stop mid-run: the run ends with an error, the drives drop and SystemOperation follows to Idle
    (never Ready with the drives off); GetReady answers 3 while the fault is latched, also after the
    e-stop is released; Acknowledge pulses reset, the fault falls, GetReady and Start work again."""
    _app, client = served
    io = await plc.io()
    assert await status(client, SO, "GetReady") == 0
    await until_state(client, SO, "Ready")
    assert await status(client, TC, "LoadByName", s("pick_and_place")) == 0
    assert await status(client, TC, "Start") == 0
    assert await state(client, SO) == "Executing"
    await panel(io, ESTOP, True)
    await until_state(client, TC, "Ready")
    assert await state(client, READY) == "Suspended"
    await until_state(client, SO, "Idle")  # the drives dropped with the fault
    controller = await held(io)
    assert controller.fault and controller.fault_code == ESTOP_CODE and not controller.drives_are_on
    await wait_until_async(lambda: read(client, f"{FAULT}.ActiveState.Id"), True)
    await wait_until_async(lambda: io.conn.read(io.tags["drives_on"], 1), False)  # uacell no longer asks
    assert await status(client, SO, "GetReady") == 3  # E_ActiveAlarm
    await panel(io, ESTOP, False)  # released, but the controller latches the fault
    await wait_controller(io, lambda c: c.fault)
    assert await status(client, SO, "GetReady") == 3
    assert (await acknowledge(client, FAULT)).is_good()
    await wait_controller(io, lambda c: not c.fault)  # the reset pulse cleared it
    await wait_until_async(lambda: read(client, f"{FAULT}.ActiveState.Id"), False)
    assert await read(client, f"{FAULT}.AckedState.Id") is True
    await wait_until_async(lambda: io.conn.read(io.tags["reset"], 1), False)  # the pulse ended
    assert await status(client, SO, "GetReady") == 0
    await until_state(client, SO, "Ready")
    assert await status(client, TC, "Start") == 0
    assert (await held(io)).running


async def test_stand_down_during_a_fault_then_get_ready_after_it(served, plc: PLC) -> None:
    """A fault with the drives on (program 99 faults on start): StandDown takes the drives off and
    SystemOperation to Idle at once; after Acknowledge (reset) GetReady answers 0 and the drives come on."""
    _app, client = served
    io = await plc.io()
    assert await status(client, SO, "GetReady") == 0
    await until_state(client, SO, "Ready")
    assert await status(client, TC, "LoadByName", s("palletize")) == 0
    assert await status(client, TC, "Start") == 3  # faulted on start
    await wait_until_async(lambda: read(client, f"{FAULT}.ActiveState.Id"), True)
    assert (await held(io)).drives_are_on
    assert await status(client, SO, "StandDown") == 0
    await until_state(client, SO, "Idle")
    assert not (await held(io)).drives_are_on
    assert await status(client, SO, "GetReady") == 3
    assert (await acknowledge(client, FAULT)).is_good()
    await wait_until_async(lambda: read(client, f"{FAULT}.ActiveState.Id"), False)
    assert await status(client, SO, "GetReady") == 0
    await until_state(client, SO, "Ready")
    assert (await held(io)).drives_are_on


async def test_a_start_the_controller_refuses_answers_1_at_once_and_writes_nothing(served, plc: PLC) -> None:
    """Remote control off at the cabinet: Start answers 1 (E_SystemState) at once, the task stays Ready,
    the start signal is never set; with remote control back, Start runs."""
    _app, client = served
    io = await plc.io()
    assert await status(client, SO, "GetReady") == 0
    await until_state(client, SO, "Ready")
    assert await status(client, TC, "LoadByName", s("pick_and_place")) == 0
    await panel(io, REMOTE_OFF, True)
    await wait_controller(io, lambda c: not c.remote_ready)
    ns = await client.get_namespace_index("urn:uacell:cell")
    start = client.get_node(ua.NodeId(f"{TC}.Start", ns))
    await wait_until_async(lambda: start.read_attribute(ua.AttributeIds.Executable), False, value=True)
    assert await status(client, TC, "Start") == 1
    assert await status(client, SO, "Start") == 1
    assert await state(client, TC) == "Ready" and await state(client, SO) == "Ready"
    assert not (await io.conn.read(io.tags["start"], 1))
    assert not (await held(io)).running
    await panel(io, REMOTE_OFF, False)
    await wait_controller(io, lambda c: c.remote_ready)
    await wait_until_async(lambda: start.read_attribute(ua.AttributeIds.Executable), True, value=True)
    assert await status(client, SO, "Start") == 0  # SystemOperation's Start: the task's confirmed start
    assert await state(client, TC) == "Executing" and await state(client, SO) == "Executing"
    assert (await held(io)).running


async def test_programs_lists_the_controller_programs_and_load_by_node_id_selects_one(served, plc: PLC) -> None:
    _app, client = served
    io = await plc.io()
    ns = await client.get_namespace_index("urn:uacell:cell")
    folder = client.get_node(ua.NodeId(PROGRAMS, ns))
    names = {(await c.read_browse_name()).Name for c in await folder.get_children()}
    assert {"pick_and_place", "palletize"} <= names
    node = ua.NodeId(f"{PROGRAMS}.palletize", ns)
    description = await client.get_node(node).read_description()
    assert "controller" in str(description.Text)
    expanded = ua.ExpandedNodeId(node.Identifier, node.NamespaceIndex, node.NodeIdType)
    res = await call(client, TC, "LoadByNodeId", ua.Variant(expanded, ua.VariantType.ExpandedNodeId))
    assert res.StatusCode.is_good() and res.OutputArguments[0].Value == 0
    assert (await held(io)).program_echo == 99
    assert await read(client, f"{TC.rsplit('.TaskControlOperation', 1)[0]}.ParameterSet.TaskProgramName") == "palletize"


async def test_a_local_file_loads_only_a_program_the_controller_holds(served, plc: PLC) -> None:
    """A file in Programs is uacell's text; the controller takes no files: a file whose program it holds
    selects that program, one it does not hold answers -2 and selects nothing."""
    app, client = served
    io = await plc.io()
    root = Path(app.config.server.data_dir) / "programs" / "Palletizer" / "Cabinet"
    (root / "sweep.robot").write_text("program Sweep version 1\nwait 1\n")
    (root / "local_pick.robot").write_text("program PickAndPlace version 3\nwait 1\n")
    res = await call(client, TC, "LoadByName", s("sweep"))
    assert res.StatusCode.is_good() and res.OutputArguments[0].Value == -2
    assert (await held(io)).program_echo == 0 and await state(client, TC) == "Idle"
    assert await status(client, TC, "LoadByName", s("local_pick")) == 0
    assert (await held(io)).program_echo == 3
    assert await read(client, "Palletizer.Controllers.Cabinet.TaskControls.Main.ParameterSet.TaskProgramName") == (
        "PickAndPlace"
    )


MOTION = (
    f'unit = 1, {TIMING}, motion = {{ position = ["input", 20, "int16"],'
    ' speed = ["input", 26, "int16"], scale = 0.01, speed_scale = 0.01, unit = "deg" },'
    ' map = { emergency_stop = ["discrete", 6, "bool"], protective_stop = ["discrete", 7, "bool"],'
    ' operational_mode = ["input", 2, "uint16"] } }'
)
ROBOT = "Palletizer"
SAFETY = f"{ROBOT}.SafetyStates.SafetyState1.ParameterSet"
AXIS = f"{ROBOT}.MotionDevices.Arm1.Axes.Axis{{}}.ParameterSet.{{}}"


async def test_joints_modes_and_safety_come_from_the_controller(tmp_path: Path, plc: PLC) -> None:
    """``motion`` maps the joints' registers (int16, hundredths of a degree): ActualPosition and
    ActualSpeed are the controller's while it moves; the safety signals set SafetyState1's
    OperationalMode, EmergencyStop and ProtectiveStop, and the EmergencyStop / ProtectiveStop conditions."""
    io = await plc.io()
    cell = tmp_path / "cell.toml"
    cell.write_text(cell_text(plc.port).replace(f"unit = 1, {TIMING} }}", MOTION))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(cell)
    joint = ModbusTag("input", 20 + 5, RegisterType("int16"))  # Axis6's position, as the test reads it
    async with serving(config) as (_app, client):
        await wait_until_async(lambda: read(client, f"{SAFETY}.OperationalMode"), 4)  # AUTOMATIC_EXTERNAL
        assert await read(client, f"{SAFETY}.EmergencyStop") is False
        assert await status(client, SO, "GetReady") == 0
        await until_state(client, SO, "Ready")
        assert await status(client, TC, "LoadByName", s("pick_and_place")) == 0
        assert await status(client, TC, "Start") == 0

        async def moved() -> bool:
            ua_value = await read(client, AXIS.format(6, "ActualPosition"))
            raw = await io.conn.read(joint, 1)
            assert isinstance(ua_value, float) and isinstance(raw, int)
            return abs(ua_value) > 5 and abs(ua_value - raw / 100) < 15  # the controller's, not 0

        await wait_until_async(moved, True)
        assert await read(client, AXIS.format(6, "ActualSpeed")) != 0.0
        await panel(io, PSTOP, True)
        await wait_until_async(lambda: read(client, f"{SAFETY}.ProtectiveStop"), True)
        await wait_until_async(lambda: read(client, f"{COND}.ProtectiveStop.ActiveState.Id"), True)
        await until_state(client, TC, "Ready")  # the protective stop ended the run
        await panel(io, PSTOP, False)
        await wait_until_async(lambda: read(client, f"{COND}.ProtectiveStop.ActiveState.Id"), False)
        position = await read(client, AXIS.format(6, "ActualPosition"))
        raw = await io.conn.read(joint, 1)
        assert isinstance(raw, int)
        assert position == pytest.approx(raw / 100, abs=0.01)  # still where it is
        await panel(io, MODE, True)  # 1: MANUAL_REDUCED_SPEED
        await wait_until_async(lambda: read(client, f"{SAFETY}.OperationalMode"), 1)
        await panel(io, ESTOP, True)
        await wait_until_async(lambda: read(client, f"{SAFETY}.EmergencyStop"), True)
        await wait_until_async(lambda: read(client, f"{COND}.EmergencyStop.ActiveState.Id"), True)


async def test_config_check_connect_names_a_missing_axis_or_safety_register(tmp_path: Path, plc: PLC) -> None:
    await plc.io()
    bad = tmp_path / "bad.toml"
    motion = MOTION.replace('["input", 20, "int16"]', '["input", 200, "int16"]')
    bad.write_text(cell_text(plc.port).replace(f"unit = 1, {TIMING} }}", motion))
    proc = await config_check_connect(bad)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    problems = [ln for ln in proc.stdout.splitlines() if "PROBLEM" in ln]
    assert any("axis1.position" in ln and "input 200" in ln for ln in problems), proc.stdout
    assert not any("emergency_stop" in ln for ln in problems)  # that one is there
    assert any("operational_mode" in ln and "input 2 = " in ln for ln in proc.stdout.splitlines())


async def test_loads_by_name_keep_locks_and_roles(tmp_path: Path, plc: PLC) -> None:
    """Another session's DI lock on the Controller: Bad_ResourceUnavailable, nothing sent; an observer:
    Bad_UserAccessDenied; exactly as for the simulator."""
    io = await plc.io()
    cell = tmp_path / "cell.toml"
    cell.write_text(cell_text(plc.port))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(cell)
    async with serving(config) as (app, client), Client(app.endpoint, timeout=30) as other:
        ctrl = "Palletizer.Controllers.Cabinet"
        res = await call(other, f"{ctrl}.Lock", "InitLock", s("maintenance"))
        assert res.StatusCode.is_good() and res.OutputArguments[0].Value == 0
        res = await call(client, TC, "LoadByName", s("pick_and_place"))
        assert res.StatusCode.value == ua.StatusCodes.BadResourceUnavailable
        assert (await held(io)).program_echo == 0  # nothing was selected
        assert (await call(other, f"{ctrl}.Lock", "ExitLock")).OutputArguments[0].Value == 0
        manager = app.server.iserver.user_manager
        policy = manager.policy
        manager.policy = dataclasses.replace(policy, anonymous_role=Role.OBSERVER)
        try:
            async with Client(app.endpoint, timeout=30) as observer:  # its role: observer
                res = await call(observer, TC, "LoadByName", s("pick_and_place"))
                assert res.StatusCode.value == ua.StatusCodes.BadUserAccessDenied
        finally:
            manager.policy = policy
        assert (await held(io)).program_echo == 0
        assert await status(client, TC, "LoadByName", s("pick_and_place")) == 0
        assert (await held(io)).program_echo == 3


async def test_back_to_back_loads_each_give_the_controller_a_strobe_edge(tmp_path: Path, plc: PLC) -> None:
    """The strobe stays low for pulse_gap between two loads (here 0.3 s, above the example controller's
    scan even on a loaded machine): the controller sees every rising edge, each load is confirmed."""
    io = await plc.io()
    cell = tmp_path / "cell.toml"
    cell.write_text(cell_text(plc.port, palletize=99).replace(TIMING, f"{TIMING}, pulse_gap = 0.3"))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(cell)
    async with serving(config) as (_app, client):
        for name, number in (("pick_and_place", 3), ("palletize", 99), ("pick_and_place", 3), ("palletize", 99)):
            assert await status(client, TC, "LoadByName", s(name)) == 0
            assert (await held(io)).program_echo == number
