"""A controller configured with `motion_device = ""` moves nothing: programs with a `move` are refused
(decision 33), the rest of the format runs, and its Programs folder starts with idle.robot."""

from __future__ import annotations

import tomllib
from pathlib import Path

from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import wait_until

from uacell.catalog import companions
from uacell.core.cell_file import parse_cell
from uacell.robotics.binding import CONTROLLERS

CELL = """
[[robots]]
name = "Gantry"
  [[robots.controllers]]
  name = "Plc"
  motion_device = ""
"""
TASK = "Gantry.Controllers.Plc.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"
SYSTEM = "Gantry.Controllers.Plc.SystemOperation.SystemOperationStateMachine"


async def test_a_controller_without_a_motion_device_runs_programs_without_move(tmp_path: Path) -> None:
    config = fast_config(tmp_path / "data")
    parsers = {c.cell_section: c.cell_parser for c in companions() if c.cell_section and c.cell_parser}
    config.cell = parse_cell(tomllib.loads(CELL), "cell.toml", parsers)
    app = await start_app(config)
    try:
        programs = tmp_path / "data" / "programs" / "Gantry" / "Plc"
        assert sorted(p.name for p in programs.iterdir()) == ["idle.robot"]
        (programs / "mover.robot").write_text("program Mover\nwait 0.1\nmove 0 0 0 0 0 0\n")
        cell = app.registry(CONTROLLERS)["Gantry.Controllers.Plc"].cell
        async with Client(app.endpoint, timeout=30) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")
            rob = await client.get_namespace_index("http://opcfoundation.org/UA/Robotics/")
            task = client.get_node(ua.NodeId(TASK, ns))
            system = client.get_node(ua.NodeId(SYSTEM, ns))
            assert await task.call_method(f"{rob}:LoadByName", "mover") == -2  # invalid content
            assert "line 3: 'move' needs a motion device" in cell.tasks["TaskControl1"].last_error
            assert await task.call_method(f"{rob}:LoadByName", "idle") == 0
            assert await system.call_method(f"{rob}:GetReady") == 0
            await wait_until(lambda: cell.system.state == "Ready")
            assert await task.call_method(f"{rob}:Start") == 0
            await wait_until(lambda: cell.tasks["TaskControl1"].state == "Executing")
            await wait_until(lambda: cell.tasks["TaskControl1"].state == "Ready")  # ran to its end
            assert await (await task.get_child(f"{rob}:LastTransitionReason")).read_value() == 5  # Application
    finally:
        await app.stop()
