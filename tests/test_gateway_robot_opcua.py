"""A robot whose signals live in a PLC's OPC UA server (the opcua-signals driver): the example PLC
(``uacell.gateway.examples.robot_plc``: asyncua's server on a free port holding the signals of
docs/equipment.md under Objects/Robot1, string NodeIds ``Robot1.<signal>``, BrowseNames ``<signal>``,
and a scan-cycle controller program on them); uacell, from the cell file
alone, loads by name, starts, stops, follows the joints, recovers a latched fault and the PLC killed and
back."""

from __future__ import annotations

import contextlib
import math
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import ua
from conftest import fast_config, serving
from helpers import config_check_connect, free_port
from test_gateway_robot import call, read, s, state, status, until_state, wait_until_async

from uacell.config import load_cell
from uacell.gateway.examples.robot_plc import FAULT_PROGRAM, PLC

ROBOT = "Palletizer"
CTRL = f"{ROBOT}.Controllers.Cabinet"
TC = f"{CTRL}.TaskControls.Main.TaskControlOperation.TaskControlStateMachine"
SO = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
COND = f"{CTRL}.SystemOperation.Conditions"
AXIS = f"{ROBOT}.MotionDevices.Arm1.Axes.Axis{{}}.ParameterSet.{{}}"


@contextlib.asynccontextmanager
async def running_plc() -> AsyncIterator[PLC]:
    plc = PLC(free_port())
    await plc.start()
    try:
        yield plc
    finally:
        await plc.stop()


def cell(port: int, ns: int, prefix: str | None = None) -> str:
    node = f"ns={ns};s=Robot1"
    where = prefix if prefix is not None else node
    return f"""
[[robots]]
name = "{ROBOT}"

  [[robots.controllers]]
  name = "Cabinet"
  programs = {{ pick_and_place = 3, palletize = {FAULT_PROGRAM} }}
    [robots.controllers.equipment]
    driver = "opcua-signals"
    endpoint = "opc.tcp://127.0.0.1:{port}/"
    prefix = "{where}"
    interval = 0.02
    # as tests/test_gateway_robot.py's TIMING: a PLC process starved on a loaded CI machine still sees
    # the strobe and confirms (a first LoadByName timed out once with 3 s and the default 0.2 s pulse)
    confirm_timeout = 6.0
    pulse_width = 1.0
    map = {{ emergency_stop = "{node}.emergency_stop", operational_mode = "{node}.operational_mode" }}
    motion = {{ position = "{node}.joints", unit = "rad" }}

    [[robots.controllers.task_controls]]
    name = "Main"

  [[robots.motion_devices]]
  name = "Arm1"
  axes = 6
"""


@pytest.fixture
async def plc() -> AsyncIterator[PLC]:
    async with running_plc() as p:
        yield p


@pytest.fixture
async def served(tmp_path: Path, plc: PLC) -> AsyncIterator[Any]:
    path = tmp_path / "cell.toml"
    path.write_text(cell(plc.port, plc.ns))
    config = fast_config(tmp_path / "data")
    config.cell = load_cell(path)
    async with serving(config) as (_app, client):
        yield client


async def test_a_cycle_through_the_plcs_opc_ua_signals(served: Any, plc: PLC) -> None:
    client = served
    assert await status(client, SO, "GetReady") == 0
    await until_state(client, SO, "Ready")
    assert await plc.get("drives_are_on") is True
    assert await status(client, TC, "LoadByName", s("pick_and_place")) == 0  # no file: the PLC's number 3
    assert await plc.get("program_echo") == 3
    assert await status(client, TC, "Start") == 0
    assert await state(client, TC) == "Executing" and await plc.get("running") is True

    async def follows() -> bool:
        got = await read(client, AXIS.format(6, "ActualPosition"))
        joints = await plc.get("joints")
        return isinstance(got, float) and abs(got) > 1.0 and abs(got - math.degrees(joints[5])) < 10

    await wait_until_async(follows, True)
    assert await status(client, TC, "Stop", ua.Variant(0, ua.VariantType.Int64)) == 0
    await until_state(client, TC, "Ready")
    assert await plc.get("running") is False
    await wait_until_async(lambda: plc.get("stop"), False)  # the pulse ends once confirmed (a write after)
    assert await read(client, f"{ROBOT}.SafetyStates.SafetyState1.ParameterSet.OperationalMode") == 4
    await plc.set("emergency_stop", True)
    await wait_until_async(lambda: read(client, f"{COND}.EmergencyStop.ActiveState.Id"), True)


async def test_a_latched_fault_is_reset_by_acknowledge(served: Any, plc: PLC) -> None:
    client = served
    assert await status(client, SO, "GetReady") == 0
    await until_state(client, SO, "Ready")
    assert await status(client, TC, "LoadByName", s("palletize")) == 0
    assert await status(client, TC, "Start") == 3  # the PLC faulted instead of running
    await wait_until_async(lambda: read(client, f"{COND}.ControllerFault.ActiveState.Id"), True)
    event_id = await read(client, f"{COND}.ControllerFault.EventId")
    comment = ua.Variant(ua.LocalizedText("reset"), ua.VariantType.LocalizedText)
    res = await call(
        client, f"{COND}.ControllerFault", "Acknowledge", ua.Variant(event_id, ua.VariantType.ByteString), comment
    )
    assert res.StatusCode.is_good()
    await wait_until_async(lambda: read(client, f"{COND}.ControllerFault.ActiveState.Id"), False)
    assert await plc.get("fault") is False
    await wait_until_async(lambda: plc.get("reset"), False)  # the pulse ends once the fault fell (a write after)


async def test_the_plc_killed_and_back_nothing_replayed(tmp_path: Path) -> None:
    async with running_plc() as plc:
        path = tmp_path / "cell.toml"
        path.write_text(cell(plc.port, plc.ns, prefix=f"/{plc.ns}:Robot1"))  # by browse path this time
        config = fast_config(tmp_path / "data")
        config.cell = load_cell(path)
        async with serving(config) as (_app, client):
            assert await status(client, TC, "LoadByName", s("pick_and_place")) == 0
            assert await plc.get("program_echo") == 3
            await plc.stop()
            await wait_until_async(lambda: read(client, f"{COND}.CommunicationLost.ActiveState.Id"), True)
            res = await call(client, TC, "LoadByName", s("palletize"))
            assert res.StatusCode.value == ua.StatusCodes.BadCommunicationError
            await plc.start()  # the same port, a PLC that restarted: nothing selected
            await wait_until_async(lambda: read(client, f"{COND}.CommunicationLost.ActiveState.Id"), False, 30)
            assert await plc.get("program_echo") == 0 and await plc.get("program_number") == 0  # nothing replayed
            assert await status(client, TC, "LoadByName", s("palletize")) == 0
            assert await plc.get("program_echo") == FAULT_PROGRAM


async def test_config_check_connect_names_a_missing_tag(tmp_path: Path, plc: PLC) -> None:
    bad = tmp_path / "bad.toml"
    bad.write_text(cell(plc.port, plc.ns).replace("Robot1.emergency_stop", "Robot1.no_such_tag"))
    proc = await config_check_connect(bad)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    problems = [ln for ln in proc.stdout.splitlines() if "PROBLEM" in ln]
    assert len(problems) == 1 and "emergency_stop" in problems[0] and "no_such_tag" in problems[0], problems
    assert any("remote_ready" in ln and "Boolean = True" in ln for ln in proc.stdout.splitlines())
