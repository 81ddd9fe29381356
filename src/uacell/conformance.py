"""Driver conformance tests: run them against your equipment factory before you serve it.

Point the kit at your factory (the same ``"package.module:factory"`` you write in the configuration)
and run it with pytest::

    UACELL_ROBOT_FACTORY=mydriver:make_robot pytest --pyargs uacell.conformance
    UACELL_UNIT_FACTORY=mydriver:make_filler UACELL_SETTINGS='address = "10.0.0.7"' pytest --pyargs uacell.conformance

``UACELL_SETTINGS`` is the part's ``settings`` table as TOML (what the server passes to the factory);
``UACELL_AXES`` the number of axes of the motion device a controller moves (default 6);
``UACELL_CONFORMANCE_TIMEOUT`` how many seconds an operation may take (default 60). The tests of the
kind you did not name are skipped. They drive the equipment through the Protocol exactly as the
server's models do (docs/equipment.md): a robot powers up, loads a program generated for its axes,
runs it to its end, is stopped in the middle of a second run, unloads and powers down; a PackML
unit is reset, started, produces, and is stopped, each acting state completed by the driver.
PackML tests need the official NodeSets (``uacell models fetch``).
"""

from __future__ import annotations

import asyncio
import inspect
import os
import tomllib
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar

import pytest

from uacell.equipment_factory import EquipmentSpec, close_equipment, make_equipment
from uacell.robotics.equipment import AxisInfo, AxisState, ExecutionMode, RobotEquipment, RunOutcome, StopMode
from uacell.robotics.program import Kind, parse, wave_program

T = TypeVar("T")
TASK = "TaskControl1"


def _timeout() -> float:
    return float(os.environ.get("UACELL_CONFORMANCE_TIMEOUT", "60"))


def _settings() -> dict[str, Any]:
    return tomllib.loads(os.environ.get("UACELL_SETTINGS", ""))


def _factory(variable: str) -> str:
    factory = os.environ.get(variable, "")
    if not factory:
        pytest.skip(f"{variable} is not set")
    return factory


def _run(make: Callable[[], Awaitable[T]]) -> T:
    async def bounded() -> T:
        return await asyncio.wait_for(make(), _timeout())

    return asyncio.run(bounded())


def _axes() -> tuple[AxisInfo, ...]:
    from uacell.robotics.sim import DEFAULT_AXES

    count = int(os.environ.get("UACELL_AXES", "6"))
    return tuple(
        DEFAULT_AXES[i] if i < len(DEFAULT_AXES) else AxisInfo(f"Axis{i + 1}", -180.0, 180.0, 300.0)
        for i in range(count)
    )


async def _robot() -> Any:
    spec = EquipmentSpec("Conformance.Controllers.Controller1", _settings(), _axes())
    return await make_equipment(_factory("UACELL_ROBOT_FACTORY"), spec, RobotEquipment)


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

    _run(check)


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

    _run(check)


# --- PackML units --------------------------------------------------------------------------------
def test_unit_completes_its_acting_states_and_produces() -> None:
    from uacell.models import StateTables
    from uacell.packml.equipment import PackMLEquipment
    from uacell.packml.model import EXECUTE, MACHINE, PackMLTables, PackMLUnit

    async def check() -> None:
        spec = EquipmentSpec("Conformance", _settings())
        equipment = await make_equipment(_factory("UACELL_UNIT_FACTORY"), spec, PackMLEquipment)
        unit = PackMLUnit(equipment, name="Conformance", tables=PackMLTables.load(StateTables()), mach_speed=600.0)
        ticking = asyncio.ensure_future(unit.run(0.02))

        async def reach(state: str) -> None:
            while unit.state != state:
                await asyncio.sleep(0.02)

        try:
            unit.command(MACHINE, "Reset")
            await reach("Idle")
            unit.command(EXECUTE, "Start", [])
            await reach("Execute")
            while unit.admin.prod_processed_count[0].count < 1:
                await asyncio.sleep(0.02)
            unit.command(MACHINE, "Stop")
            await reach("Stopped")
        finally:
            ticking.cancel()
            await asyncio.gather(ticking, return_exceptions=True)
            unit.close()
            if inspect.isawaitable(unit.equipment_closed):  # a driver's close() may be a coroutine
                await unit.equipment_closed

    _run(check)
