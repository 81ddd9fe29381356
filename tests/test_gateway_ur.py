"""A Universal Robots arm served by uacell from the cell file alone (the ur-dashboard driver), against
ursim: a Dashboard Server and UR Modbus register map written from UR's documentation (tests/ursim, checked
with ur-rtde's DashboardClient in tests/test_ursim.py), on free loopback ports. An asyncua client loads the
robot's own programs by name (no file in Programs), powers up, starts, stops, meets refusals, safety
stops and faults, and the controller killed and back."""

from __future__ import annotations

import asyncio
import math
from collections.abc import AsyncIterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from asyncua import Client, ua
from conftest import fast_config, serving
from helpers import config_check_connect, free_port, wait_until
from test_gateway_robot import call, read, s, state, status, until_state, wait_until_async
from ursim.dashboard import DashboardServer
from ursim.robot import ProgramState as UrProgramState
from ursim.robot import RobotMode, SafetyStatus, URSim
from ursim.server import URSimServers

from uacell.config import load_cell
from uacell.core.cell_file import builtin_cell_path
from uacell.gateway.ur_link import Dashboard

CTRL = "UR5e.Controllers.Cabinet"
TASK = f"{CTRL}.TaskControls.Main"
TC = f"{TASK}.TaskControlOperation.TaskControlStateMachine"
READY = f"{TC}.ReadySubstateMachine"
SO = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
COND = f"{CTRL}.SystemOperation.Conditions"
SAFETY = "UR5e.SafetyStates.SafetyState1.ParameterSet"
AXIS = "UR5e.MotionDevices.Arm1.Axes.Axis{}.ParameterSet.{}"

SHIPPED = builtin_cell_path("ur-robot").read_text()


def program_state(sim: URSim) -> UrProgramState:
    """``sim.program_state`` read afresh: the driver changes it, so no earlier assert on it tells its type."""
    return sim.program_state


def cell_text(dashboard: int, modbus: int) -> str:
    """The shipped cell with nothing changed but the ports (and a faster poll for the tests)."""
    return SHIPPED.replace(
        "port = 29999, modbus_port = 5502", f"port = {dashboard}, modbus_port = {modbus}, poll = 0.02"
    )


@dataclass
class Rig:
    sim: URSim
    servers: URSimServers
    client: Client
    app: Any


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[Rig]:
    programs = tmp_path / "robot-programs"
    programs.mkdir()
    for name in ("pick", "palletize"):
        (programs / f"{name}.urp").write_text(f"<URProgram name={name!r}/>")
    (programs / "empty.urp").write_text("")
    sim = URSim(programs, unlock_delay=0.0, boot_seconds=0.05)
    async with URSimServers(sim, free_port(), free_port()) as servers:
        assert servers.modbus is not None
        cell = tmp_path / "cell.toml"
        cell.write_text(cell_text(servers.dashboard_port, servers.modbus.port))
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(cell)
        async with serving(config) as (app, client):
            yield Rig(sim, servers, client, app)


async def acknowledge(client: Client, condition: str) -> ua.StatusCode:
    event_id = await read(client, f"{condition}.EventId")
    comment = ua.Variant(ua.LocalizedText("checked at the robot"), ua.VariantType.LocalizedText)
    res = await call(client, condition, "Acknowledge", ua.Variant(event_id, ua.VariantType.ByteString), comment)
    return res.StatusCode


async def ready_with(r: Rig, program: str) -> None:
    assert await status(r.client, SO, "GetReady") == 0
    await until_state(r.client, SO, "Ready")
    assert r.sim.robot_mode is RobotMode.RUNNING  # powered and brakes released
    assert await status(r.client, TC, "LoadByName", s(program)) == 0


async def test_the_robots_programs_by_name_run_stop_and_the_joints(rig: Rig) -> None:
    client, sim = rig.client, rig.sim
    ns = await client.get_namespace_index("urn:uacell:cell")
    programs = client.get_node(ua.NodeId(f"{CTRL}.Programs", ns))
    assert "pick" in {(await c.read_browse_name()).Name for c in await programs.get_children()}
    assert not list((Path(rig.app.config.server.data_dir) / "programs").rglob("*.robot"))  # no stub files
    await ready_with(rig, "palletize")  # not configured: the robot's own file, palletize.urp
    assert sim.loaded is not None and sim.loaded.name == "palletize.urp"
    assert await read(client, f"{TASK}.ParameterSet.TaskProgramName") == "palletize"
    await wait_until_async(
        lambda: _names(programs), True, timeout=10
    )  # the program the robot reports loaded is listed too
    # -1: no such program on the robot; -2: the robot has the file and cannot load it
    res = await call(client, TC, "LoadByName", s("nothing_like_it"))
    assert res.StatusCode.is_good() and res.OutputArguments[0].Value == -1
    res = await call(client, TC, "LoadByName", s("empty"))
    assert res.StatusCode.is_good() and res.OutputArguments[0].Value == -2
    assert await status(client, TC, "LoadByName", s("pick")) == 0
    assert sim.loaded is not None and sim.loaded.name == "pick.urp"
    # Start answers once the robot plays it
    assert await status(client, TC, "Start") == 0
    assert await state(client, TC) == "Executing" and await state(client, SO) == "Executing"
    assert program_state(sim) is UrProgramState.PLAYING

    async def follows() -> bool:  # ActualPosition is the robot's joint, in degrees
        got = await read(client, AXIS.format(1, "ActualPosition"))
        assert isinstance(got, float)
        return abs(got - math.degrees(sim.joints[0])) < 3.0 and abs(got - math.degrees(sim.joints[0])) >= 0

    await wait_until_async(follows, True)
    await wait_until_async(lambda: _moving(client), True)
    # Stop (QuickStop): the robot's "stop"; Ready/Suspended
    assert await status(client, TC, "Stop", ua.Variant(4, ua.VariantType.Int64)) == 0
    await until_state(client, TC, "Ready")
    assert await state(client, READY) == "Suspended"
    assert program_state(sim) is UrProgramState.STOPPED
    # Start again, and the program ends by itself: Ready/AtProgramStart
    assert await status(client, TC, "Start") == 0
    sim.finish_program()
    await until_state(client, TC, "Ready")
    assert await state(client, READY) == "AtProgramStart"
    assert await read(client, f"{SAFETY}.OperationalMode") == 4  # AUTOMATIC, in Remote control
    assert await status(client, SO, "StandDown") == 0
    await until_state(client, SO, "Idle")
    assert sim.robot_mode is RobotMode.POWER_OFF


async def _names(programs: Any) -> bool:
    return "palletize" in {(await c.read_browse_name()).Name for c in await programs.get_children()}


async def _moving(client: Client) -> bool:
    speed = await read(client, AXIS.format(1, "ActualSpeed"))
    return isinstance(speed, float) and speed != 0.0


async def test_local_control_refuses_start_at_once_and_remote_control_lets_it_run(rig: Rig) -> None:
    client, sim = rig.client, rig.sim
    await ready_with(rig, "pick")
    sim.set_remote_control(False)
    await wait_until_async(lambda: read(client, f"{SAFETY}.OperationalMode"), 3)  # AUTOMATIC, local
    assert await status(client, TC, "Start") == 1  # E_SystemState at once, nothing played
    assert await state(client, TC) == "Ready"
    assert program_state(sim) is UrProgramState.STOPPED
    assert "play" not in [line.lower() for line in rig.servers.received]
    sim.set_remote_control(True)
    await wait_until_async(lambda: read(client, f"{SAFETY}.OperationalMode"), 4)
    assert await status(client, TC, "Start") == 0  # the driver connects again, as UR asks
    assert program_state(sim) is UrProgramState.PLAYING


async def test_a_protective_stop_ends_the_run_and_acknowledge_unlocks_it(rig: Rig) -> None:
    client, sim = rig.client, rig.sim
    await ready_with(rig, "pick")
    assert await status(client, TC, "Start") == 0
    sim.protective_stop()
    await until_state(client, TC, "Ready")
    await wait_until_async(lambda: read(client, f"{COND}.ProtectiveStop.ActiveState.Id"), True)
    await wait_until_async(lambda: read(client, f"{SAFETY}.ProtectiveStop"), True)
    assert await status(client, TC, "Start") == 3  # E_ActiveAlarm
    assert (await acknowledge(client, f"{COND}.ProtectiveStop")).is_good()
    await wait_until_async(lambda: read(client, f"{COND}.ProtectiveStop.ActiveState.Id"), False)
    assert sim.safety is SafetyStatus.NORMAL
    assert any(line.lower() == "unlock protective stop" for line in rig.servers.received)
    await until_state(client, SO, "Ready")
    assert await status(client, TC, "Start") == 0


async def test_an_emergency_stop_and_a_fault_are_recovered_over_opc_ua(rig: Rig) -> None:
    client, sim = rig.client, rig.sim
    await ready_with(rig, "pick")
    sim.emergency_stop()
    await wait_until_async(lambda: read(client, f"{COND}.EmergencyStop.ActiveState.Id"), True)
    await until_state(client, SO, "Idle")  # the arm lost power: never Ready with the drives off
    assert await read(client, f"{SAFETY}.EmergencyStop") is True
    assert await status(client, SO, "GetReady") == 3
    sim.release_emergency_stop()
    await wait_until_async(lambda: read(client, f"{COND}.EmergencyStop.ActiveState.Id"), False)
    assert (await acknowledge(client, f"{COND}.EmergencyStop")).is_good()
    assert await status(client, SO, "GetReady") == 0
    await until_state(client, SO, "Ready")
    sim.fault()  # latched until "restart safety"
    await wait_until_async(lambda: read(client, f"{COND}.ControllerFault.ActiveState.Id"), True)
    assert (await acknowledge(client, f"{COND}.ControllerFault")).is_good()
    await wait_until_async(lambda: read(client, f"{COND}.ControllerFault.ActiveState.Id"), False)
    assert any(line.lower() == "restart safety" for line in rig.servers.received)
    await until_state(client, SO, "Idle")  # restart safety leaves the arm powered off
    assert await status(client, SO, "GetReady") == 0
    await until_state(client, SO, "Ready")


async def test_the_robot_killed_and_back_nothing_replayed(rig: Rig) -> None:
    client, sim = rig.client, rig.sim
    await ready_with(rig, "pick")
    await rig.servers.kill()
    await wait_until_async(lambda: read(client, f"{COND}.CommunicationLost.ActiveState.Id"), True)
    res = await call(client, TC, "Start")
    assert res.StatusCode.value == ua.StatusCodes.BadCommunicationError
    sent = len(rig.servers.received)
    await rig.servers.restart()  # rebooted: powered off, nothing loaded
    await wait_until_async(lambda: read(client, f"{COND}.CommunicationLost.ActiveState.Id"), False)
    await until_state(client, SO, "Idle")
    commands = [line.lower() for line in rig.servers.received[sent:]]
    assert not any(c.startswith(("load", "play", "power", "brake")) for c in commands), commands
    assert sim.robot_mode is RobotMode.POWER_OFF and sim.loaded is None


async def test_config_check_connect_names_an_unreachable_dashboard(tmp_path: Path) -> None:
    sim = URSim(tmp_path, unlock_delay=0.0)
    async with URSimServers(sim, free_port(), free_port()) as servers:
        assert servers.modbus is not None
        good, bad = tmp_path / "good.toml", tmp_path / "bad.toml"
        good.write_text(cell_text(servers.dashboard_port, servers.modbus.port))
        bad.write_text(cell_text(free_port(), servers.modbus.port))  # nobody on that port
        proc = await config_check_connect(good)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert any("robotmode" in ln and "Robotmode: POWER_OFF" in ln for ln in proc.stdout.splitlines())
        assert any("holding 258..266" in ln for ln in proc.stdout.splitlines())
        proc = await config_check_connect(bad)
        assert proc.returncode == 1, proc.stdout + proc.stderr
        problem = [ln for ln in proc.stdout.splitlines() if "PROBLEM" in ln]
        assert len(problem) == 1 and "dashboard 127.0.0.1" in problem[0] and "unreachable" in problem[0], problem


async def test_a_process_stop_pauses_and_start_resumes_a_reset_restarts(rig: Rig) -> None:
    """ProcessStop (3) is the robot's ``pause``: Start resumes it with ``play``; after
    ResetToProgramStart, Start stops the paused program first, so it begins again."""
    client, sim = rig.client, rig.sim
    await ready_with(rig, "pick")
    assert await status(client, TC, "Start") == 0
    assert await status(client, TC, "Stop", ua.Variant(3, ua.VariantType.Int64)) == 0
    await until_state(client, TC, "Ready")
    assert await state(client, READY) == "Suspended" and program_state(sim) is UrProgramState.PAUSED
    runs = sim.program_runs
    assert await status(client, TC, "Start") == 0  # resumed, not begun again
    assert program_state(sim) is UrProgramState.PLAYING and sim.program_runs == runs
    assert await status(client, TC, "Stop", ua.Variant(5, ua.VariantType.Int64)) == 0
    await until_state(client, TC, "Ready")
    assert await status(client, f"{TC}.ReadySubstateMachine", "ResetToProgramStart") == 0
    assert await status(client, TC, "Start") == 0
    assert program_state(sim) is UrProgramState.PLAYING and sim.program_runs == runs + 1  # begun again


async def test_a_new_connection_asked_for_while_a_command_waits_leaves_exactly_one(tmp_path: Path) -> None:
    """The driver connects anew after the pendant went Remote (UR's server judges a connection by when
    it was opened) while its poller may be asking: the new connection waits for the command under way,
    which is answered, and the Dashboard Server then holds exactly one connection, none once closed."""
    server = DashboardServer(URSim(tmp_path, unlock_delay=0.0, boot_seconds=0.05))
    await server.start()
    dashboard = Dashboard("127.0.0.1", server.port, timeout=10.0)
    try:
        answers: list[str] = []

        async def poll() -> None:
            for _ in range(40):
                answers.append(await dashboard.ask("programState"))

        async def reconnect() -> None:
            for _ in range(15):
                await dashboard.connect()
                await asyncio.sleep(0)

        await asyncio.gather(poll(), reconnect())
        assert len(answers) == 40 and all(a.startswith("STOPPED") for a in answers), answers[:3]
        await wait_until(lambda: len(server._writers) == 1, timeout=10)  # the replaced ones closed
        dashboard.close()
        await wait_until(lambda: not server._writers, timeout=10)
    finally:
        dashboard.close()
        await server.stop()
