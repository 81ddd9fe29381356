"""node-opcua browses the larger example cell and runs a program on its second robot."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from conftest import ServeProcess, start_serve
from test_robotics_interop import run_trusted

from uacell.core.cell_file import builtin_cell_path

pytestmark = pytest.mark.interop


@pytest.fixture
def example_cell(tmp_path: Path) -> Iterator[ServeProcess]:
    """`uacell serve` with the shipped example cell, its simulators sped up."""
    config = tmp_path / "cell.toml"
    text = builtin_cell_path("example").read_text(encoding="utf-8")
    config.write_text(text + "\n[robot]\ntime_scale = 20.0\n\n[packml]\nacting_time = 0.05\n", encoding="utf-8")
    sp = start_serve(tmp_path / "data", "--config", str(config))
    yield sp
    sp.stop()


def test_node_opcua_browses_the_example_cell_and_runs_a_program_on_the_second_robot(example_cell):
    browsed = run_trusted(example_cell, "cell_browse.js")
    parts = {p["path"]: p for p in browsed["parts"]}
    assert {path: parts[path]["type"] for path in parts if not path.count("/Axes/")} == {
        "Welder": "MotionDeviceSystemType",
        "Welder/Controllers/ControllerA": "ControllerType",
        "Welder/Controllers/ControllerA/TaskControls/Seam": "TaskControlType",
        "Welder/Controllers/ControllerA/TaskControls/Service": "TaskControlType",
        "Welder/Controllers/ControllerB": "ControllerType",
        "Welder/Controllers/ControllerB/TaskControls/Seam": "TaskControlType",
        "Welder/Controllers/ControllerB/TaskControls/Cleaning": "TaskControlType",
        "Welder/MotionDevices/ArmA": "MotionDeviceType",
        "Welder/MotionDevices/ArmB": "MotionDeviceType",
        "Handler": "MotionDeviceSystemType",
        "Handler/Controllers/Controller1": "ControllerType",
        "Handler/Controllers/Controller1/TaskControls/Palletize": "TaskControlType",
        "Handler/MotionDevices/Arm1": "MotionDeviceType",
        "Filler": "PackMLBaseObjectType",
        "Capper": "PackMLBaseObjectType",
        "Labeler": "PackMLBaseObjectType",
    }
    assert sorted(p for p in parts if "/ArmB/Axes/" in p) == [
        f"Welder/MotionDevices/ArmB/Axes/J{i}" for i in range(1, 8)
    ]
    assert parts["Welder/Controllers/ControllerB"]["serialNumber"] == "EX-W-CB"
    assert parts["Handler/MotionDevices/Arm1"]["serialNumber"] == "EX-H-A1"

    out = run_trusted(example_cell, "robotics_run.js", "pick_and_place", "Handler", "Controller1", "Palletize")
    assert (out["getReady"], out["loadGripper"], out["load"], out["start"]) == (0, 0, 0, 0)
    assert out["programName"] == "PickAndPlace"
    assert [(e["transition"], e["from"], e["to"]) for e in out["events"]] == [
        ("IdleToReady", "Idle", "Ready"),
        ("ReadyToExecuting", "Ready", "Executing"),
        ("ExecutingToReady", "Executing", "Ready"),
        ("ReadyToIdle", "Ready", "Idle"),  # the script's UnloadProgram at the end
    ]
    assert (out["finalState"], out["reason"]) == ("Ready", 5)
    assert [a["sourceName"] for a in out["audits"]] == ["Method/LoadByName", "Method/Start", "Method/UnloadProgram"]
