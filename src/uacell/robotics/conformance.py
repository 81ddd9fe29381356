"""Robot driver conformance: run it against your equipment factory before you serve it.

    UACELL_ROBOT_FACTORY=mydriver:make_robot pytest --pyargs uacell.robotics.conformance

``UACELL_SETTINGS`` is the controller's ``settings`` table as TOML, ``UACELL_AXES`` the number of axes
of the motion device it moves (default 6), ``UACELL_CONFORMANCE_TIMEOUT`` the seconds an operation
may take (default 60). The tests drive the equipment through the Protocol exactly as the server's
model does (docs/equipment.md): the robot powers up, loads a program generated for its axes, runs it
to its end, is stopped in the middle of a second run, unloads and powers down.
"""

from __future__ import annotations

import asyncio
import os
from typing import Any

from uacell.core.conformance_kit import factory, run, settings
from uacell.core.equipment_factory import close_equipment, make_equipment
from uacell.robotics.equipment import (
    AxisInfo,
    AxisState,
    ControllerEquipmentSpec,
    ExecutionMode,
    RobotEquipment,
    RunOutcome,
    StopMode,
)
from uacell.robotics.program import Kind, parse, wave_program

TASK = "TaskControl1"


def _axes() -> tuple[AxisInfo, ...]:
    from uacell.robotics.sim import DEFAULT_AXES

    count = int(os.environ.get("UACELL_AXES", "6"))
    return tuple(
        DEFAULT_AXES[i] if i < len(DEFAULT_AXES) else AxisInfo(f"Axis{i + 1}", -180.0, 180.0, 300.0)
        for i in range(count)
    )


async def _robot() -> Any:
    spec = ControllerEquipmentSpec("Conformance.Controllers.Controller1", settings(), _axes())
    return await make_equipment(factory("UACELL_ROBOT_FACTORY"), spec, RobotEquipment)


# --- robot controllers ---------------------------------------------------------------------------
def test_robot_factory_returns_equipment_that_describes_itself() -> None:
    async def check() -> None:
        robot = await _robot()
        try:
            axes = list(robot.axes)
            assert axes, "a controller moves at least one axis"
            assert len(axes) == len(_axes()), f"{len(axes)} axes reported, the motion device has {len(_axes())}"
            for a in axes:
                assert isinstance(a, AxisInfo) and a.min_position < a.max_position and a.max_speed > 0, a
            assert all(isinstance(n, str) and n for n in robot.alarm_names)
            states = list(robot.axis_states())
            assert len(states) == len(axes) and all(isinstance(s, AxisState) for s in states)
            changes: list[tuple[str, bool, str]] = []
            robot.add_alarm_listener(lambda name, active, text: changes.append((name, active, text)))
        finally:
            await close_equipment(robot, "conformance")

    run(check)


def test_robot_runs_a_program_to_its_end_and_stops_on_request() -> None:
    async def check() -> None:
        robot = await _robot()
        try:
            await robot.power_up()
            program = parse(wave_program(robot.axes), [a.limits for a in robot.axes])
            assert program.kind is Kind.PROGRAM
            await robot.load(TASK, program)
            pointers: list[int] = []
            outcome = await robot.run(TASK, 0, ExecutionMode.CYCLE, lambda p, line: pointers.append(p))
            assert isinstance(outcome, RunOutcome)
            assert outcome == RunOutcome(0, completed=True), f"a CYCLE run to its end returns {outcome}"
            assert pointers and pointers == sorted(pointers), f"progress must advance: {pointers}"
            # A second run, stopped as soon as it has started: run returns, not completed, robot still.
            started = asyncio.Event()
            run = asyncio.ensure_future(robot.run(TASK, 0, ExecutionMode.CONTINUOUS, lambda p, line: started.set()))
            await started.wait()
            await robot.stop(TASK, StopMode.QUICK_STOP)
            stopped = await run
            assert isinstance(stopped, RunOutcome) and not stopped.completed, stopped
            assert all(s.speed == 0 for s in robot.axis_states()), "the robot is still when run returns"
            await robot.unload(TASK, program.name)
            await robot.power_down()
        finally:
            await close_equipment(robot, "conformance")

    run(check)
