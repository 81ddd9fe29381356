"""The Modbus signals I/O against pymodbus's own server running the example robot controller."""

from __future__ import annotations

import asyncio
import os
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from pathlib import Path

import pytest
from helpers import free_port

from uacell.core.errors import CallError
from uacell.gateway.modbus import ModbusConnection, ModbusPool
from uacell.gateway.modbus_robot import ModbusRobotIO, signal_tags
from uacell.gateway.signals import RobotStatus, SignalOp

SRC = str(Path(__file__).resolve().parents[1] / "src")


def start_controller(port: int, cycle: float) -> subprocess.Popen[bytes]:
    env = {**os.environ, "PYTHONPATH": SRC}
    cmd = [sys.executable, "-m", "uacell.gateway.examples.robot_controller", "--port", str(port), "--cycle", str(cycle)]
    return subprocess.Popen(cmd, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


@pytest.fixture
def controller() -> Iterator[tuple[int, subprocess.Popen[bytes]]]:
    port = free_port()
    proc = start_controller(port, 1.0)  # a run long enough to stop it before it ends
    try:
        yield port, proc
    finally:
        proc.kill()
        proc.wait(10)


@pytest.fixture
async def robot(controller: tuple[int, subprocess.Popen[bytes]]) -> AsyncIterator[ModbusRobotIO]:
    conn = ModbusConnection("127.0.0.1", controller[0], timeout=0.5)
    for _ in range(200):  # the process needs a moment to listen
        if await conn.connect():
            break
        await asyncio.sleep(0.05)
    assert conn.connected
    try:
        yield ModbusRobotIO(conn, 1, signal_tags(), poll=0.005)
    finally:
        conn.close()


async def test_program_selected_started_stopped_and_finished(robot: ModbusRobotIO) -> None:
    s = await robot.status()
    assert s == RobotStatus(remote_ready=True)
    await robot.perform(SignalOp.load(7, s, robot.clock(), 2.0, 0.05))
    await robot.perform(SignalOp.drives(True, await robot.status(), robot.clock(), 2.0))
    s = await robot.status()
    assert (s.program_echo, s.drives_are_on, s.running) == (7, True, False)
    await robot.perform(SignalOp.start(s, robot.clock(), 2.0, 0.05))
    assert (await robot.status()).running
    await robot.perform(SignalOp.stop(await robot.status(), robot.clock(), 2.0, 0.05))
    s = await robot.status()
    assert (s.running, s.program_end) == (False, False)  # stopped, not finished
    await robot.perform(SignalOp.start(s, robot.clock(), 2.0, 0.05))
    deadline = robot.clock() + 10.0
    # The PLC sets program end and clears running in one scan; a poll may fall between the two writes.
    while not (s.program_end and not s.running) and robot.clock() < deadline:
        await asyncio.sleep(0.005)
        s = await robot.status()
    assert (s.running, s.program_end, s.at_start) == (False, True, True)
    # the pulses were ended: nothing left set
    for name in ("start", "stop", "program_strobe"):
        assert await robot.conn.read(robot.tags[name], 1) is False


async def test_fault_refuses_then_reset(robot: ModbusRobotIO) -> None:
    await robot.perform(SignalOp.load(99, await robot.status(), robot.clock(), 2.0, 0.05))
    await robot.perform(SignalOp.drives(True, await robot.status(), robot.clock(), 2.0))
    with pytest.raises(CallError, match="fault 99") as err:
        await robot.perform(SignalOp.start(await robot.status(), robot.clock(), 2.0, 0.05))
    assert err.value.status == "BadInvalidState"
    assert await robot.conn.read(robot.tags["start"], 1) is False
    s = await robot.status()
    assert (s.fault, s.fault_code) == (True, 99)
    await robot.perform(SignalOp.reset(s, robot.clock(), 2.0, 0.05))
    s = await robot.status()
    assert (s.fault, s.fault_code) == (False, 0)


async def test_controller_gone(robot: ModbusRobotIO, controller: tuple[int, subprocess.Popen[bytes]]) -> None:
    s = await robot.status()
    controller[1].kill()
    controller[1].wait(10)
    assert (await robot.status()).connected is False
    with pytest.raises(CallError) as err:
        await robot.perform(SignalOp.load(3, s, robot.clock(), 1.0, 0.05))
    assert err.value.status == "BadCommunicationError"


async def test_pool_shares_one_connection_per_endpoint() -> None:
    pool = ModbusPool()
    a = pool.connection("127.0.0.1", 1502)
    assert pool.connection("127.0.0.1", 1502) is a
    assert pool.connection("127.0.0.1", 1503) is not a
    assert a.users == 2
    pool.close()


def test_signal_overrides_checked() -> None:
    tags = signal_tags({"program_number": ("holding", 10, "uint32")})
    assert (tags["program_number"].address, tags["program_number"].rtype.count) == (10, 2)
    with pytest.raises(ValueError, match=r"^speed: not a signal of the map"):
        signal_tags({"speed": ("holding", 1, "uint16")})
    with pytest.raises(ValueError, match="a coil holds a bool, not uint16"):
        signal_tags({"start": ("coil", 0, "uint16")})
