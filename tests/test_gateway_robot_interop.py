"""node-opcua through uacell to a gateway robot: the example Modbus controller as its own process,
``uacell serve`` with the shipped cell pointed at it; node-opcua loads the controller's program by name
(no file in Programs), starts it, sees Executing at once and the program end."""

from __future__ import annotations

import asyncio
from pathlib import Path

import pytest
from conftest import run_node, start_serve
from test_gateway_robot import SHIPPED, running_plc

pytestmark = pytest.mark.interop


async def test_node_opcua_loads_a_controller_program_by_name_and_runs_it(tmp_path: Path) -> None:
    async with running_plc(1.0) as plc:
        await plc.io()  # listening
        cell = tmp_path / "cell.toml"
        cell.write_text(SHIPPED.replace("port = 5020", f"port = {plc.port}"))
        sp = start_serve(tmp_path / "data", "--config", str(cell))
        try:
            out = await asyncio.to_thread(
                run_node, "robotics_run.js", sp.endpoint, "pick_and_place", "Palletizer", "Cabinet", "Main"
            )
        finally:
            sp.stop()
    assert not list((tmp_path / "data" / "programs").rglob("*.robot"))  # no stub files
    assert out["loadGripper"] == -1  # no module of that name anywhere: -1
    assert (out["getReady"], out["load"], out["start"]) == (0, 0, 0)
    assert out["programName"] == "pick_and_place"
    assert out["stateAfterStart"] == "Executing"  # Start answered once the controller ran it
    transitions = [e["transition"] for e in out["events"]]
    # the failed load of "gripper" (IdleToIdle, reason 4), then the program's cycle and the unload
    assert transitions == ["IdleToIdle", "IdleToReady", "ReadyToExecuting", "ExecutingToReady", "ReadyToIdle"]
    assert (out["finalState"], out["reason"], out["readySubstate"]) == ("Ready", 5, "AtProgramStart")
