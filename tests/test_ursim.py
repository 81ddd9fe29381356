"""The UR controller simulator (tests/ursim) checked against clients we did not write.

- ur-rtde's ``DashboardClient`` (PyPI ``ur-rtde``, C++ by SDU Robotics): it raises unless ``load``,
  ``play``, ``stop``, ``pause`` and ``unlock protective stop`` answer UR's exact strings, and parses
  ``PolyscopeVersion`` / ``get serial number`` as a real e-Series requires. It drives the simulator
  as a process (python -m tests.ursim), the way the driver's tests will run it.
- pymodbus's client reads UR's Modbus register map; the expected register values are worked out
  here by hand from UR's documentation (units, two's complement, joint turns), not by the
  simulator's own encoders.
- A raw asyncio client checks, with a fake clock, what ur-rtde does not reach: UR's 5 s protective
  stop rule, emergency stop and fault latching, a program ending by itself, the controller killed
  and back.
"""

from __future__ import annotations

import asyncio
import json
import math
import socket
import time
from collections.abc import AsyncIterator, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest
from helpers import FakeClock, free_port, wait_until
from pymodbus.client import AsyncModbusTcpClient, ModbusTcpClient
from pymodbus.exceptions import ConnectionException
from ursim.dashboard import NOT_REMOTE, UNLOCK_TOO_EARLY, WELCOME
from ursim.modbus import joint_angle, signed
from ursim.process import URSimProcess
from ursim.robot import HOME, SafetyStatus, URSim
from ursim.server import URSimServers

TIMEOUT = 20.0


def programs(where: Path) -> Path:
    """A controller's programs directory: two programs and a damaged (empty) one."""
    where.mkdir(parents=True, exist_ok=True)
    (where / "pick.urp").write_bytes(b"\x1f\x8b program")  # .urp files are gzip; the content is not read
    (where / "place.urp").write_bytes(b"\x1f\x8b program")
    (where / "empty.urp").write_bytes(b"")
    return where


# -- the simulator as a process, driven by ur-rtde -----------------------------------------------


@pytest.fixture(scope="module")
def process(tmp_path_factory: pytest.TempPathFactory) -> Iterator[URSimProcess]:
    where = programs(tmp_path_factory.mktemp("ursim") / "programs")
    with URSimProcess(where, free_port(), free_port(), free_port(), "--unlock-delay", "0") as p:
        yield p


@pytest.fixture
def robot(process: URSimProcess) -> Iterator[URSimProcess]:
    """The process's controller, fresh: rebooted, Remote control, nothing pressed."""
    assert process.control("reset") == "ok"
    yield process


def client(robot: URSimProcess) -> Any:
    """ur-rtde's DashboardClient, connected (the test is skipped where ur-rtde is not installed)."""
    dashboard_client = pytest.importorskip("dashboard_client", reason="ur-rtde (the test extra) is not installed")
    db = dashboard_client.DashboardClient("127.0.0.1", robot.port)
    db.connect()
    assert db.isConnected()
    return db


def until(read: object, expected: str) -> None:
    deadline = time.monotonic() + TIMEOUT
    while (value := read()) != expected:  # type: ignore[operator]
        assert time.monotonic() < deadline, (value, expected)
        time.sleep(0.01)


def test_ur_rtde_identifies_an_e_series_controller_in_remote_control(robot: URSimProcess) -> None:
    db = client(robot)
    assert db.polyscopeVersion() == "5.19.0.1210631"  # parsed from "URSoftware 5.19.0.1210631 (...)"
    assert db.isInRemoteControl() is True  # only asked when the version is 5.6 or later
    assert db.getSerialNumber() == "20235500042"  # ur-rtde raises unless the answer is a number
    assert db.getRobotModel() == "UR5"
    assert db.robotmode() == "Robotmode: POWER_OFF"
    assert db.safetystatus() == "Safetystatus: NORMAL"
    assert db.safetymode() == "Safetymode: NORMAL"
    assert db.programState() == "STOPPED <unnamed>"
    assert db.getLoadedProgram() == "No program loaded"
    assert db.isProgramSaved() is False  # "false <unnamed>"
    db.disconnect()


def test_ur_rtde_loads_powers_up_plays_pauses_and_stops_a_program(robot: URSimProcess) -> None:
    db = client(robot)
    db.loadURP("pick.urp")  # raises unless "Loading program: ..."
    assert db.getLoadedProgram() == f"Loaded program: {robot.programs_dir / 'pick.urp'}"
    assert db.programState() == "STOPPED pick.urp"
    db.powerOn()
    until(db.robotmode, "Robotmode: IDLE")
    db.brakeRelease()
    until(db.robotmode, "Robotmode: RUNNING")
    db.play()  # raises unless "Starting program"
    assert db.running() is True
    assert db.programState() == "PLAYING pick.urp"
    db.pause()  # raises unless "Pausing program"
    assert db.programState() == "PAUSED pick.urp"
    assert db.running() is False
    db.play()  # resumes
    assert db.programState() == "PLAYING pick.urp"
    db.stop()  # raises unless "Stopped"
    assert db.programState() == "STOPPED pick.urp"
    assert db.running() is False
    db.loadURP("place.urp")
    assert db.programState() == "STOPPED place.urp"
    db.closePopup()
    db.closeSafetyPopup()
    db.powerOff()
    assert db.robotmode() == "Robotmode: POWER_OFF"
    db.disconnect()
    state = robot.control("state")
    assert '"program_runs": 1' in state and '"robot_mode": "POWER_OFF"' in state


def test_ur_rtde_gets_the_controllers_refusals_as_errors(robot: URSimProcess) -> None:
    db = client(robot)
    with pytest.raises(RuntimeError, match=r"^File not found: missing\.urp$"):
        db.loadURP("missing.urp")
    with pytest.raises(RuntimeError, match=r"^Error while loading program: .*empty\.urp$"):
        db.loadURP("empty.urp")
    db.loadURP("pick.urp")
    with pytest.raises(RuntimeError, match=r"^Failed to execute: play$"):
        db.play()  # the brakes are on
    with pytest.raises(RuntimeError, match=r"^Failed to execute: stop$"):
        db.stop()  # nothing runs
    with pytest.raises(RuntimeError, match=r"^Failed to execute: pause$"):
        db.pause()
    db.disconnect()


def test_local_control_refuses_commands_until_remote_and_a_new_connection(robot: URSimProcess) -> None:
    before = client(robot)
    assert robot.control("remote off") == "ok"
    local = client(robot)
    assert local.isInRemoteControl() is False
    for refused in (lambda: local.loadURP("pick.urp"), local.play, local.stop, local.pause):
        with pytest.raises(RuntimeError) as info:
            refused()
        assert str(info.value) == NOT_REMOTE
    local.powerOn()  # ur-rtde does not check this reply: the arm must not have powered on
    assert local.robotmode() == "Robotmode: POWER_OFF"
    assert robot.control("remote on") == "ok"
    with pytest.raises(RuntimeError, match="reconnect to port 29999"):
        before.loadURP("pick.urp")  # opened before the switch: UR wants a reconnection
    with pytest.raises(RuntimeError, match="reconnect to port 29999"):
        local.loadURP("pick.urp")
    after = client(robot)
    after.loadURP("pick.urp")
    assert after.programState() == "STOPPED pick.urp"
    for db in (before, local, after):
        db.disconnect()


def test_ur_rtde_unlocks_a_protective_stop_and_resumes(robot: URSimProcess) -> None:
    db = client(robot)
    db.loadURP("pick.urp")
    db.brakeRelease()  # PolyScope 5 powers on and releases from POWER_OFF
    until(db.robotmode, "Robotmode: RUNNING")
    db.play()
    assert robot.control("protective stop") == "ok"
    assert db.safetystatus() == "Safetystatus: PROTECTIVE_STOP"
    assert db.programState() == "PAUSED pick.urp"
    assert db.robotmode() == "Robotmode: RUNNING"
    with pytest.raises(RuntimeError, match=r"^Failed to execute: play$"):
        db.play()
    db.closeSafetyPopup()
    db.unlockProtectiveStop()  # raises unless "Protective stop releasing" (the process waits 0 s)
    assert db.safetystatus() == "Safetystatus: NORMAL"
    db.play()
    assert db.programState() == "PLAYING pick.urp"
    db.disconnect()


def test_ur_rtde_recovers_a_latched_fault_with_restart_safety(robot: URSimProcess) -> None:
    db = client(robot)
    db.loadURP("pick.urp")
    db.brakeRelease()
    until(db.robotmode, "Robotmode: RUNNING")
    db.play()
    assert robot.control("fault") == "ok"
    assert db.safetystatus() == "Safetystatus: FAULT"
    assert db.robotmode() == "Robotmode: POWER_OFF"
    assert db.programState() == "STOPPED pick.urp"
    db.powerOn()
    assert db.robotmode() == "Robotmode: POWER_OFF"  # latched: the arm cannot power on
    db.unlockProtectiveStop()  # not a protective stop: nothing to unlock, the fault stays
    assert db.safetystatus() == "Safetystatus: FAULT"
    db.restartSafety()
    assert db.safetystatus() == "Safetystatus: NORMAL"
    assert db.robotmode() == "Robotmode: POWER_OFF"
    db.powerOn()
    until(db.robotmode, "Robotmode: IDLE")
    db.disconnect()


def test_the_control_port_kills_and_restarts_the_controller_and_nothing_is_replayed(robot: URSimProcess) -> None:
    db = client(robot)
    db.loadURP("pick.urp")
    db.brakeRelease()
    until(db.robotmode, "Robotmode: RUNNING")
    db.play()
    with ModbusTcpClient("127.0.0.1", port=robot.modbus_port, timeout=TIMEOUT) as mb:
        assert mb.read_input_registers(258, count=1).registers == [7]  # RUNNING, same state as the dashboard
    assert robot.control("kill") == "ok"
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", robot.port), timeout=TIMEOUT).close()
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", robot.modbus_port), timeout=TIMEOUT).close()
    assert robot.control("restart") == "ok"
    state = json.loads(robot.control("state"))
    assert (state["robot_mode"], state["program_state"], state["loaded"]) == ("POWER_OFF", "STOPPED", None)
    again = client(robot)
    assert again.getLoadedProgram() == "No program loaded"
    assert again.robotmode() == "Robotmode: POWER_OFF"
    with ModbusTcpClient("127.0.0.1", port=robot.modbus_port, timeout=TIMEOUT) as mb:
        assert mb.read_holding_registers(258, count=1).registers == [3]
    again.disconnect()


def test_the_control_port_refuses_what_it_does_not_know(robot: URSimProcess) -> None:
    assert robot.control("jump") == "error: unknown command: jump"
    assert robot.control("operational mode fast").startswith("error: operational mode must be one of")
    assert robot.control("program seconds soon") == "error: not a number of seconds: soon"
    assert robot.control("robot mode flying").startswith("error: robot mode must be one of NO_CONTROLLER")
    assert robot.control("safety calm").startswith("error: safety status must be one of NORMAL")
    assert robot.control("operational mode manual") == "ok"
    assert robot.control("program seconds 2.5") == "ok"
    assert robot.control("robot mode backdrive") == "ok"
    assert robot.control("safety reduced") == "ok"
    db = client(robot)
    assert db.robotmode() == "Robotmode: BACKDRIVE"
    assert db.safetystatus() == "Safetystatus: REDUCED"
    db.send("get operational mode\n")
    assert db.receive() == "MANUAL"
    db.disconnect()
    with ModbusTcpClient("127.0.0.1", port=robot.modbus_port, timeout=TIMEOUT) as mb:
        assert mb.read_holding_registers(258, count=9).registers == [6, 0, 1, 0, 0, 0, 0, 0, 2]


def test_the_process_exits_after_the_shutdown_command(tmp_path: Path) -> None:
    p = URSimProcess(programs(tmp_path / "programs"), free_port(), free_port(), free_port())
    p.start()
    proc = p.proc
    assert proc is not None
    try:
        with socket.create_connection(("127.0.0.1", p.port), timeout=TIMEOUT) as s:
            f = s.makefile("rw")
            assert f.readline() == WELCOME + "\n"
            f.write("shutdown\n")
            f.flush()
            assert f.readline() == "Shutting down\n"
            assert f.readline() == ""  # the controller closed the connection
        assert proc.wait(TIMEOUT) == 0
    finally:
        p.stop()


def test_a_killed_process_comes_back_on_the_same_ports(tmp_path: Path) -> None:
    with URSimProcess(programs(tmp_path / "programs"), free_port(), free_port(), free_port()) as p:
        db = client(p)
        db.loadURP("pick.urp")
        p.kill()  # SIGKILL: the controller is gone at once
        with pytest.raises(OSError):
            socket.create_connection(("127.0.0.1", p.port), timeout=TIMEOUT).close()
        p.start()
        again = client(p)
        assert again.getLoadedProgram() == "No program loaded"
        again.disconnect()


# -- in process: raw protocol with a fake clock, and the Modbus map -----------------------------


class Line:
    """A raw Dashboard client: one line out, one line back."""

    def __init__(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        self.reader, self.writer = reader, writer

    @classmethod
    async def open(cls, port: int) -> Line:
        reader, writer = await asyncio.open_connection("127.0.0.1", port)
        line = cls(reader, writer)
        assert await line.read() == WELCOME
        return line

    async def read(self) -> str:
        raw = await asyncio.wait_for(self.reader.readline(), TIMEOUT)
        assert raw.endswith(b"\n"), raw
        return raw.decode()[:-1]

    async def __call__(self, command: str) -> str:
        self.writer.write((command + "\n").encode())
        await self.writer.drain()
        return await self.read()

    async def close(self) -> None:
        self.writer.close()
        await self.writer.wait_closed()


@dataclass
class Cell:
    sim: URSim
    servers: URSimServers
    clock: FakeClock


@pytest.fixture
async def cell(tmp_path: Path) -> AsyncIterator[Cell]:
    """The simulator in process on a fake clock, with its Dashboard and Modbus ports."""
    clock = FakeClock()
    sim = URSim(programs(tmp_path / "programs"), clock=clock, boot_seconds=1.0)
    async with URSimServers(sim, free_port(), free_port()) as servers:
        yield Cell(sim, servers, clock)


async def test_a_port_that_cannot_be_had_closes_the_ports_already_open(tmp_path: Path) -> None:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        servers = URSimServers(URSim(programs(tmp_path / "programs")), free_port(), taken.getsockname()[1])
        with pytest.raises(OSError, match="Modbus server could not listen"):
            await servers.start()
    with pytest.raises(ConnectionRefusedError):
        await asyncio.open_connection("127.0.0.1", servers.dashboard_port)


async def running_program(line: Line, clock: FakeClock, sim: URSim) -> None:
    assert await line("load pick.urp") == f"Loading program: {sim.programs_dir / 'pick.urp'}"
    assert await line("power on") == "Powering on"
    assert await line("robotmode") == "Robotmode: POWER_ON"
    clock.advance(1.0)  # boot_seconds
    assert await line("robotmode") == "Robotmode: IDLE"
    assert await line("brake release") == "Brake releasing"
    assert await line("robotmode") == "Robotmode: RUNNING"
    assert await line("play") == "Starting program"


async def open_line(servers: URSimServers) -> Line:
    return await Line.open(servers.dashboard_port)


async def test_unlocking_a_protective_stop_waits_five_seconds_as_ur_documents(cell: Cell) -> None:
    sim, servers, clock = cell.sim, cell.servers, cell.clock
    line = await open_line(servers)
    await running_program(line, clock, sim)
    sim.protective_stop()
    assert await line("unlock protective stop") == UNLOCK_TOO_EARLY
    clock.advance(4.9)
    assert await line("unlock protective stop") == UNLOCK_TOO_EARLY
    assert await line("safetystatus") == "Safetystatus: PROTECTIVE_STOP"
    clock.advance(0.1)
    assert await line("unlock protective stop") == "Protective stop releasing"
    assert await line("safetystatus") == "Safetystatus: NORMAL"
    assert await line("programState") == "PAUSED pick.urp"
    await line.close()


async def test_an_emergency_stop_latches_while_pressed_and_leaves_the_arm_off(cell: Cell) -> None:
    sim, servers, clock = cell.sim, cell.servers, cell.clock
    line = await open_line(servers)
    await running_program(line, clock, sim)
    sim.emergency_stop()
    assert await line("safetystatus") == "Safetystatus: SYSTEM_EMERGENCY_STOP"
    assert await line("robotmode") == "Robotmode: POWER_OFF"
    assert await line("running") == "Program running: false"
    assert await line("power on") == "Powering on"
    clock.advance(2.0)
    assert await line("robotmode") == "Robotmode: POWER_OFF"
    assert await line("restart safety") == "Restarting safety"
    assert await line("safetystatus") == "Safetystatus: SYSTEM_EMERGENCY_STOP"  # still pressed
    sim.release_emergency_stop()
    assert await line("safetystatus") == "Safetystatus: NORMAL"
    assert sim.safety_popup
    assert await line("close safety popup") == "closing safety popup"
    assert not sim.safety_popup
    assert await line("power on") == "Powering on"
    clock.advance(1.0)
    assert await line("robotmode") == "Robotmode: IDLE"
    sim.emergency_stop(robot=True)
    assert await line("safetymode") == "Safetymode: ROBOT_EMERGENCY_STOP"
    await line.close()


async def test_a_safeguard_stop_pauses_and_a_violation_needs_restart_safety(cell: Cell) -> None:
    sim, servers, clock = cell.sim, cell.servers, cell.clock
    line = await open_line(servers)
    await running_program(line, clock, sim)
    sim.safeguard_stop(True)
    assert await line("safetystatus") == "Safetystatus: SAFEGUARD_STOP"
    assert await line("programState") == "PAUSED pick.urp"
    assert await line("play") == "Failed to execute: play"
    sim.safeguard_stop(False)
    assert await line("play") == "Starting program"
    sim.fault(SafetyStatus.VIOLATION)
    assert await line("safetystatus") == "Safetystatus: VIOLATION"
    assert await line("brake release") == "Brake releasing"
    assert await line("robotmode") == "Robotmode: POWER_OFF"
    assert await line("restart safety") == "Restarting safety"
    assert await line("safetystatus") == "Safetystatus: NORMAL"
    await line.close()


async def test_a_program_ends_by_itself_after_its_duration(cell: Cell) -> None:
    sim, servers, clock = cell.sim, cell.servers, cell.clock
    sim.program_seconds = 3.0
    line = await open_line(servers)
    await running_program(line, clock, sim)
    clock.advance(2.0)
    assert await line("running") == "Program running: true"
    clock.advance(1.5)
    assert await line("running") == "Program running: false"
    assert await line("programState") == "STOPPED pick.urp"
    assert sim.programs_finished == 1
    assert await line("play") == "Starting program"  # the same program again
    sim.finish_program()
    assert await line("programState") == "STOPPED pick.urp"
    assert sim.programs_finished == 2
    await line.close()


async def test_other_commands_answer_as_polyscope_5_does(cell: Cell) -> None:
    sim, servers, clock = cell.sim, cell.servers, cell.clock
    line = await open_line(servers)
    assert await line("version") == "5.19.0.1210631"
    assert await line("get operational mode") == "AUTOMATIC"
    assert await line("set operational mode manual") == "Operational mode 'MANUAL' is set"
    assert await line("get operational mode") == "MANUAL"
    assert await line("set operational mode fast") == "Failed setting operational mode: fast"
    assert await line("clear operational mode") == (
        "No longer controlling the operational mode. Current operational mode: 'MANUAL'."
    )
    assert await line("popup Hello there") == "showing popup"
    assert sim.popup == "Hello there"
    assert await line("close popup") == "closing popup"
    assert await line("addToLog cycle 7 done") == "Added log message"
    assert sim.log == ["cycle 7 done"]
    assert await line("addToLog") == "No log message to add"
    assert await line("isProgramSaved") == "false <unnamed>"
    assert await line("load installation default.installation") == "File not found: default.installation"
    assert await line("load") == "File not found: "
    assert await line("load pick.txt") == "File not found: pick.txt"
    assert await line("jump") == "could not understand: 'jump'"
    assert await line("ROBOTMODE") == "Robotmode: POWER_OFF"
    await running_program(line, clock, sim)
    assert await line("load place.urp") == f"Error while loading program: {sim.programs_dir / 'place.urp'}"
    assert await line("quit") == "Disconnected"
    assert await line.reader.read() == b""  # closed by the server
    assert servers.received[-1] == "quit"
    await line.close()


async def test_commands_sent_together_or_with_crlf_get_one_reply_each_in_order(cell: Cell) -> None:
    line = await open_line(cell.servers)
    line.writer.write(b"robotmode\r\nprogramState\nis in remote control\r\n")
    await line.writer.drain()
    assert [await line.read() for _ in range(3)] == ["Robotmode: POWER_OFF", "STOPPED <unnamed>", "true"]
    assert cell.servers.received == ["robotmode", "programState", "is in remote control"]
    await line.close()


async def test_a_line_over_the_limit_is_not_understood_and_the_connection_goes_on(cell: Cell) -> None:
    line = await open_line(cell.servers)
    assert (await line("x" * 70000)).startswith("could not understand: ")
    assert await line("robotmode") == "Robotmode: POWER_OFF"
    await line.close()


async def test_killed_and_restarted_the_controller_comes_back_powered_off_with_nothing_loaded(cell: Cell) -> None:
    sim, servers, clock = cell.sim, cell.servers, cell.clock
    line = await open_line(servers)
    await running_program(line, clock, sim)
    await servers.kill()
    assert await asyncio.wait_for(line.reader.read(), TIMEOUT) == b""  # dropped, nothing answered
    with pytest.raises(OSError):
        await Line.open(servers.dashboard_port)
    await servers.restart()
    again = await open_line(servers)
    assert await again("robotmode") == "Robotmode: POWER_OFF"
    assert await again("get loaded program") == "No program loaded"
    assert await again("programState") == "STOPPED <unnamed>"
    await again.close()
    await line.close()


# -- the Modbus register map ------------------------------------------------------------------


async def modbus(servers: URSimServers) -> AsyncModbusTcpClient:
    assert servers.modbus is not None
    client = AsyncModbusTcpClient("127.0.0.1", port=servers.modbus.port, timeout=TIMEOUT, reconnect_delay=0)
    assert await client.connect()
    return client


async def registers(client: AsyncModbusTcpClient, address: int, count: int, holding: bool = True) -> list[int]:
    read = client.read_holding_registers if holding else client.read_input_registers
    response = await read(address, count=count)
    assert not response.isError(), response
    return list(response.registers)


async def test_modbus_robot_and_safety_modes_follow_the_dashboard(cell: Cell) -> None:
    sim, servers, clock = cell.sim, cell.servers, cell.clock
    client = await modbus(servers)
    line = await open_line(servers)
    # 256-266: version 5.19, POWER_OFF (3), not powered, no stop, safety NORMAL (1)
    assert await registers(client, 256, 11) == [5, 19, 3, 0, 0, 0, 0, 0, 0, 0, 1]
    await running_program(line, clock, sim)
    assert await registers(client, 258, 3) == [7, 0, 1]  # RUNNING, power on
    assert await registers(client, 310, 6, holding=False) == [253] * 6  # joints in RUNNING mode
    sim.protective_stop()
    assert await registers(client, 261, 6) == [1, 0, 0, 0, 1, 3]  # protective stopped, should stop, PROTECTIVE_STOP
    sim.emergency_stop()
    assert await registers(client, 258, 9) == [3, 0, 0, 0, 1, 0, 0, 1, 6]  # POWER_OFF, e-stopped, SYSTEM_E_STOP
    assert await registers(client, 310, 6) == [239] * 6
    await line.close()
    client.close()


async def test_modbus_joint_angles_count_turns_as_ur_explains(cell: Cell) -> None:
    sim, servers = cell.sim, cell.servers
    client = await modbus(servers)
    sim.joints = [-0.5, 1.0, 3.2, -3.2, 6.3, 0.0]
    angles = await registers(client, 270, 6)
    turns = await registers(client, 320, 6)
    # by hand: within-turn mrad (0..6283) and the turn (65535 is -1 in two's complement)
    assert angles == [5783, 1000, 3200, 3083, 17, 0]
    assert turns == [65535, 0, 0, 65535, 1, 0]
    decoded = [joint_angle(a, t) for a, t in zip(angles, turns, strict=True)]
    assert decoded == pytest.approx(sim.joints, abs=0.001)
    client.close()


async def test_modbus_joint_speeds_are_signed_mrad_per_second_while_a_program_moves(cell: Cell) -> None:
    sim, servers, clock = cell.sim, cell.servers, cell.clock
    client = await modbus(servers)
    line = await open_line(servers)
    await running_program(line, clock, sim)
    clock.advance(0.5)
    angles, turns = await registers(client, 270, 6), await registers(client, 320, 6)
    first = [joint_angle(a, t) for a, t in zip(angles, turns, strict=True)]
    speeds = [signed(v) / 1000 for v in await registers(client, 280, 6)]
    assert first != pytest.approx(list(HOME), abs=0.01)  # the arm moved
    assert speeds == pytest.approx(sim.speeds, abs=0.001)
    assert any(s < -0.1 for s in speeds) or any(s > 0.1 for s in speeds)
    clock.advance(1.5)  # a quarter turn of the swing later: some joints now turn the other way
    later = [signed(v) / 1000 for v in await registers(client, 280, 6)]
    assert any(a * b < 0 for a, b in zip(speeds, later, strict=True))
    assert await line("pause") == "Pausing program"
    assert await registers(client, 280, 6) == [0] * 6
    await line.close()
    client.close()


async def test_modbus_tcp_pose_is_signed_tenths_of_mm_and_mrad(cell: Cell) -> None:
    sim, servers = cell.sim, cell.servers
    client = await modbus(servers)
    sim.joints = [0.0] * 6
    # UR5e stretched out (UR's DH table): x = a2 + a3, y = -(d4 + d6), z = d1 - d5; flange turned +90 deg about x
    pose = [signed(v) for v in await registers(client, 400, 6)]
    assert pose == [-8172, -2329, 628, round(math.pi / 2 * 1000), 0, 0]
    client.close()


async def test_modbus_state_registers_are_read_only_and_general_purpose_ones_writable(cell: Cell) -> None:
    servers = cell.servers
    client = await modbus(servers)
    assert (await client.write_register(258, 7)).isError()
    assert await registers(client, 258, 1) == [3]
    assert not (await client.write_register(130, 4242)).isError()
    assert await registers(client, 130, 1) == [4242]
    client.close()


async def test_modbus_connections_drop_when_the_controller_is_killed(cell: Cell) -> None:
    servers = cell.servers
    client = await modbus(servers)
    await servers.kill()
    await wait_until(lambda: not client.connected, TIMEOUT)  # the controller dropped the connection
    with pytest.raises(ConnectionException):
        await client.read_holding_registers(258, count=1)
    client.close()
    await servers.restart()
    again = await modbus(servers)
    assert await registers(again, 258, 1) == [3]
    again.close()
