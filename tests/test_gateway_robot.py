"""A robot behind Modbus/TCP signals served by uacell from the cell file alone (the modbus-signals
driver): pymodbus's server runs the example controller program on a free port; an asyncua client
powers up, loads, starts, stops and sees faults, and the controller killed and restarted mid-run."""

from __future__ import annotations

import asyncio
import contextlib
import os
import re
import subprocess
import sys
import time
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
from asyncua import Client, ua
from conftest import fast_config, serving
from helpers import call_path, config_check_connect, free_port

from uacell.config import load_cell
from uacell.core.cell_file import builtin_cell_path
from uacell.gateway.modbus import ModbusConnection
from uacell.gateway.modbus_robot import ModbusRobotIO, signal_tags
from uacell.gateway.signals import RobotStatus
from uacell.server import UacellServer

SRC = str(Path(__file__).resolve().parents[1] / "src")
CTRL = "Palletizer.Controllers.Cabinet"
TASK = f"{CTRL}.TaskControls.Main"
TC = f"{TASK}.TaskControlOperation.TaskControlStateMachine"
READY = f"{TC}.ReadySubstateMachine"
SO = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
COND = f"{CTRL}.SystemOperation.Conditions"

# The shipped example, with nothing changed but the port (and, for the fault test, a program number)
SHIPPED = builtin_cell_path("modbus-robot").read_text()


# pulse_width: a pulse ends once confirmed; 1 s lets a controller process starved by a loaded machine still
# see the strobe (with the default 0.2 s, one CI run timed a LoadByName out)
TIMING = "poll = 0.02, confirm_timeout = 6.0, timeout = 3.0, pulse_width = 1.0"


def cell_text(port: int, **programs: int) -> str:
    text = SHIPPED.replace("port = 5020", f"port = {port}")
    for name, number in programs.items():
        text = re.sub(rf"\b{name} = \d+", f"{name} = {number}", text)
    # generous timeouts: on a loaded machine a request may wait (a lost connection would need an
    # acknowledgement, a slow confirmation answer Bad_Timeout)
    return text.replace("unit = 1 }", f"unit = 1, {TIMING} }}")


class PLC:
    """The example controller (pymodbus server + scan-cycle program) as its own process."""

    def __init__(self, port: int, cycle: float) -> None:
        self.port, self.cycle = port, cycle
        self.proc: subprocess.Popen[bytes] | None = None
        self.clients: list[ModbusConnection] = []

    def start(self) -> None:
        cmd = [sys.executable, "-m", "uacell.gateway.examples.robot_controller", "--port", str(self.port)]
        cmd += ["--cycle", str(self.cycle)]
        self.proc = subprocess.Popen(
            cmd, env={**os.environ, "PYTHONPATH": SRC}, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL
        )

    def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            self.proc.wait(10)
            self.proc = None

    async def io(self) -> ModbusRobotIO:
        """A client of its own, to see what the controller holds."""
        conn = ModbusConnection("127.0.0.1", self.port, timeout=2.0)
        self.clients.append(conn)
        deadline = time.monotonic() + 15
        while not await conn.connect():
            assert time.monotonic() < deadline, "the controller did not listen"
            await asyncio.sleep(0.05)
        return ModbusRobotIO(conn, 1, signal_tags())


@contextlib.asynccontextmanager
async def running_plc(cycle: float) -> AsyncIterator[PLC]:
    """The example controller on a free port, its run lasting ``cycle`` seconds; stopped after."""
    p = PLC(free_port(), cycle)
    p.start()
    try:
        yield p
    finally:
        p.kill()
        for conn in p.clients:
            conn.close()


@pytest.fixture
async def plc() -> AsyncIterator[PLC]:
    async with running_plc(1.0) as p:
        yield p


@pytest.fixture
async def served(tmp_path: Path, plc: PLC) -> AsyncIterator[tuple[UacellServer, Client]]:
    await plc.io()  # listening before uacell starts
    cell = tmp_path / "cell.toml"
    cell.write_text(cell_text(plc.port, palletize=99))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(cell)
    async with serving(config) as served:
        yield served


call = call_path


async def status(client: Client, obj: str, method: str, *args: ua.Variant) -> int:
    res = await call(client, obj, method, *args)
    assert res.StatusCode.is_good(), (method, res.StatusCode)
    value: int = res.OutputArguments[0].Value
    return value


async def read(client: Client, path: str) -> object:
    ns = await client.get_namespace_index("urn:uacell:cell")
    return await client.get_node(ua.NodeId(path, ns)).read_value()


async def state(client: Client, machine: str) -> str:
    value = await read(client, f"{machine}.CurrentState")
    assert isinstance(value, ua.LocalizedText)
    return str(value.Text)


async def until_state(client: Client, machine: str, wanted: str, timeout: float = 15.0) -> None:
    deadline = time.monotonic() + timeout
    while (got := await state(client, machine)) != wanted:
        assert time.monotonic() < deadline, f"{machine} is {got}, waited for {wanted}"
        await asyncio.sleep(0.02)


def s(text: str) -> ua.Variant:
    return ua.Variant(text, ua.VariantType.String)


async def test_a_program_is_selected_started_finished_and_stopped_on_the_controller(served, plc: PLC) -> None:
    app, client = served
    io = await plc.io()
    assert await status(client, SO, "GetReady") == 0
    await until_state(client, SO, "Ready")
    assert (await held(io)).drives_are_on
    # the controller's own program, by its configured name: no file in Programs (none was installed)
    assert not list((app.config.server.data_dir / "programs").rglob("*.robot"))
    assert await status(client, TC, "LoadByName", s("pick_and_place")) == 0
    assert (await held(io)).program_echo == 3  # the controller selected program 3
    assert await state(client, TC) == "Ready"
    assert await read(client, f"{TASK}.ParameterSet.TaskProgramName") == "pick_and_place"
    # Start answers once the controller confirmed it runs: Executing and running at once
    assert await status(client, TC, "Start") == 0
    assert await state(client, TC) == "Executing"
    assert (await held(io)).running
    # the controller's cycle (1 s) ends with program end: Ready, AtProgramStart
    await until_state(client, TC, "Ready")
    assert await state(client, READY) == "AtProgramStart"
    assert (await held(io)).program_end
    # Start again and Stop in the middle: the controller stops at once, the task is Suspended
    assert await status(client, TC, "Start") == 0
    assert await status(client, TC, "Stop", ua.Variant(0, ua.VariantType.Int64)) == 0
    await until_state(client, TC, "Ready")
    assert await state(client, READY) == "Suspended"
    controller = await held(io)
    assert not controller.running and not controller.program_end
    # a name neither the controller nor Programs knows: Status -1, nothing selected
    assert await status(client, TC, "UnloadProgram") == 0
    res = await call(client, TC, "LoadByName", s("nothing_like_it"))
    assert res.StatusCode.is_good() and res.OutputArguments[0].Value == -1
    assert (await held(io)).program_echo == 3


async def test_a_command_the_controller_refuses_is_a_fault_condition(served, plc: PLC) -> None:
    _app, client = served
    assert await status(client, SO, "GetReady") == 0
    await until_state(client, SO, "Ready")
    assert await status(client, TC, "LoadByName", s("palletize")) == 0  # number 99: faults on start
    assert await status(client, TC, "Start") == 3  # the controller faulted instead of running: at once
    assert await state(client, TC) == "Ready"  # never Executing
    await wait_until_async(lambda: read(client, f"{COND}.ControllerFault.ActiveState.Id"), True)
    message = await read(client, f"{COND}.ControllerFault.Message")
    assert isinstance(message, ua.LocalizedText) and "99" in str(message.Text)
    res = await call(client, TC, "Start")  # an active alarm refuses Start: E_ActiveAlarm (3)
    assert res.StatusCode.is_good() and res.OutputArguments[0].Value == 3


async def test_the_controller_killed_and_back_methods_refuse_then_resume(served, plc: PLC) -> None:
    app, client = served
    assert await status(client, SO, "GetReady") == 0
    await until_state(client, SO, "Ready")
    plc.kill()
    await wait_until_async(lambda: read(client, f"{COND}.CommunicationLost.ActiveState.Id"), True)
    res = await call(client, TC, "LoadByName", s("pick_and_place"))
    assert res.StatusCode.value == ua.StatusCodes.BadCommunicationError
    ns = await client.get_namespace_index("urn:uacell:cell")
    method = client.get_node(ua.NodeId(f"{TC}.LoadByName", ns))
    await wait_until_async(lambda: method.read_attribute(ua.AttributeIds.Executable), False, value=True)
    assert await state(client, TC) == "Idle"  # nothing changed, nothing queued
    axis = client.get_node(ua.NodeId("Palletizer.MotionDevices.Arm1.Axes.Axis1.ParameterSet.ActualPosition", ns))

    async def axis_status() -> str:
        return str((await axis.read_data_value(raise_on_bad_status=False)).StatusCode.name)

    await wait_until_async(axis_status, "BadNoCommunication")  # not the position it last had
    plc.start()  # the same port
    back = time.monotonic()
    await wait_until_async(lambda: read(client, f"{COND}.CommunicationLost.ActiveState.Id"), False)
    assert time.monotonic() - back < 10  # backoff at most 2 s, plus the process start
    await wait_until_async(axis_status, "Good")
    assert await status(client, TC, "LoadByName", s("pick_and_place")) == 0
    assert (await (await plc.io()).status()).program_echo == 3
    assert app.dispatcher is not None


async def held(io: ModbusRobotIO, timeout: float = 10.0) -> RobotStatus:
    """What the controller holds now, as the test's own client reads it; a read that failed (on a
    loaded machine the controller's process may answer after the client gave up) is read again."""
    deadline = time.monotonic() + timeout
    while not (got := await io.status()).connected:
        assert time.monotonic() < deadline, "the controller did not answer"
        await asyncio.sleep(0.05)
    return got


async def wait_controller(io: ModbusRobotIO, predicate, timeout: float = 10.0) -> None:
    deadline = time.monotonic() + timeout
    while not predicate(await held(io)):
        assert time.monotonic() < deadline, "the controller did not get there"
        await asyncio.sleep(0.01)


async def wait_until_async(read_value, expected, timeout: float = 15.0, value: bool = False) -> None:
    deadline = time.monotonic() + timeout
    while True:
        got = await read_value()
        if value:
            got = got.Value.Value
        if got == expected:
            return
        assert time.monotonic() < deadline, f"{got} != {expected}"
        await asyncio.sleep(0.02)


def test_cell_file_errors_name_the_part_and_key(tmp_path: Path) -> None:
    from uacell.core.errors import ConfigError

    bad = tmp_path / "bad.toml"
    bad.write_text(cell_text(502).replace('driver = "modbus-signals"', 'driver = "modbus-sigs"'))
    with pytest.raises(ConfigError, match=r"equipment: driver 'modbus-sigs' is not one of: modbus-signals"):
        load_cell(bad)
    bad.write_text(cell_text(502).replace("pick_and_place = 3", "pick_and_place = 2.5"))
    with pytest.raises(ConfigError, match=r"programs: pick_and_place: must be a program number \(1..65535\) or a name"):
        load_cell(bad)
    bad.write_text(cell_text(502).replace("pick_and_place = 3", 'pick_and_place = ""'))
    with pytest.raises(ConfigError, match=r"programs: pick_and_place: must be"):
        load_cell(bad)
    bad.write_text(
        cell_text(502)
        .replace("unit = 1,", "unit = 1, settings = 2,")
        .replace("programs =", "settings = { unit = 2 }\n  programs =")
    )
    with pytest.raises(ConfigError, match=r"settings: 'unit' is given in equipment already"):
        load_cell(bad)


async def test_a_program_without_a_number_is_rejected_before_anything_is_written() -> None:
    from uacell.gateway.robot import ModbusSignalsRobot, Timing, program_key
    from uacell.robotics.equipment import ProgramRejected
    from uacell.robotics.program import parse

    conn = ModbusConnection("127.0.0.1", free_port())  # nobody listens: nothing may be sent
    robot = ModbusSignalsRobot("R.Controllers.C", ModbusRobotIO(conn, 1, signal_tags()), conn, {"a": 1}, (), Timing())
    program = parse("program Sweep version 1\nwait 1\n", [])
    with pytest.raises(ProgramRejected, match="takes no program files and holds no program Sweep"):
        await robot.load("Main", program)
    assert program_key("pick_and_place") == program_key("PickAndPlace") == program_key("pick-and-place")
    conn.close()


async def test_config_check_connect_reads_every_signal(tmp_path: Path, plc: PLC) -> None:
    await plc.io()  # listening
    good, bad = tmp_path / "good.toml", tmp_path / "bad.toml"
    good.write_text(cell_text(plc.port))
    bad.write_text(cell_text(free_port()))  # nobody there
    for path, code in ((good, 0), (bad, 1)):
        proc = await config_check_connect(path)
        assert proc.returncode == code, proc.stdout + proc.stderr
        if code == 0:
            assert "connect: 14 of 14 as configured" in proc.stdout
            assert any("remote_ready" in ln and "discrete 0 = True" in ln for ln in proc.stdout.splitlines())
        else:
            assert "(endpoint)  PROBLEM: unreachable" in proc.stdout


async def test_a_program_selected_by_name_through_a_string_tag(tmp_path: Path, plc: PLC) -> None:
    """programs = { pick_and_place = "PICK01" }: LoadByName writes the controller's name for it into
    the program_name registers (16 ASCII characters) and waits for the name's echo."""
    io = await plc.io()
    cell = tmp_path / "cell.toml"
    cell.write_text(cell_text(plc.port).replace("pick_and_place = 3", 'pick_and_place = "PICK01"'))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(cell)
    async with serving(config) as (_app, client):
        named = ModbusRobotIO(io.conn, 1, signal_tags(), by_name=True)
        assert await status(client, SO, "GetReady") == 0
        await until_state(client, SO, "Ready")
        assert await status(client, TC, "LoadByName", s("pick_and_place")) == 0
        assert (await named.status()).program_name_echo == "PICK01"  # the controller took the name
        assert await state(client, TC) == "Ready"
        assert await status(client, TC, "Start") == 0
        await wait_controller(io, lambda c: c.running)
        await until_state(client, TC, "Ready")
        assert await state(client, READY) == "AtProgramStart"
        assert await status(client, TC, "UnloadProgram") == 0
        assert await status(client, TC, "LoadByName", s("palletize")) == 0  # by number, beside the name
        assert (await held(io)).program_echo == 7
