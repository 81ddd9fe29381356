"""The pure Robotics model: TaskControl and SystemOperation for every (state, method), failures, alarms,
coupling, and random command sequences that must keep the machines consistent."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable
from pathlib import Path

import pytest
from helpers import official, robotics_tables, wait_until
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uacell.core.errors import CallError
from uacell.core.fsm import Change, Reason, StateMachine
from uacell.robotics.equipment import EquipmentError, ExecutionMode, ProgramRejected, StopMode
from uacell.robotics.model import (
    RobotCell,
    Status,
    SystemOperation,
    TaskControl,
    TaskModule,
)
from uacell.robotics.program import Program, samples
from uacell.robotics.program_cache import DirectoryLibrary
from uacell.robotics.sim import SimulatedRobot

SCALE = 0.0005  # 1 simulated second = 0.5 ms
SLOW = """\
program Slow version 7
use Gripper
move 10 0 0 0 0 0
wait 2000
call Gripper.pick
"""  # the wait lasts 1 s real: long enough to observe Executing, stopped by the tests
SHORT = "program Short\nmove 5 0 0 0 0 0\nmove 0 0 0 0 0 0\nwait 0.1\n"
FILES = {
    "slow.robot": SLOW,
    "short.robot": SHORT,
    "bad.robot": "program Bad\nmove 0 0 0\n",
    "far.robot": "program Far\nmove 0 0 0 0 0 999\n",
    "lib/extra.robot": "module Extra version 0.1\nroutine r\n  wait 0\nend\n",
}


def make_library(root: Path) -> DirectoryLibrary:
    for name, text in samples().items():
        (root / name).write_text(text)
    for name, text in FILES.items():
        (root / name).parent.mkdir(parents=True, exist_ok=True)
        (root / name).write_text(text)
    return DirectoryLibrary(root)


class Log:
    """Every change of the given machines: (machine, transition or '>'+entered state, reason)."""

    def __init__(self, *machines: StateMachine) -> None:
        self.items: list[tuple[str, str, Reason]] = []
        for m in machines:
            m.listeners.append(self._on)

    def _on(self, c: Change) -> None:
        what = c.transition.name if c.transition else ">" + c.to_state
        self.items.append((c.machine.name, what, c.reason))

    def transitions(self) -> list[tuple[str, str, Reason]]:
        return [i for i in self.items if not i[1].startswith(">")]

    def clear(self) -> None:
        self.items.clear()


@pytest.fixture
async def cell(tmp_path: Path):
    robot = SimulatedRobot(time_scale=SCALE, power_up_time=2.0, power_down_time=0.5)
    c = RobotCell(robot, make_library(tmp_path), tables=robotics_tables())
    yield c
    await c.close()


def tc_of(cell: RobotCell) -> TaskControl:
    return cell.tasks["TaskControl1"]


async def system_ready(cell: RobotCell) -> None:
    assert await cell.system.get_ready() == Status.OK
    await wait_until(lambda: cell.system.state == "Ready")


async def tc_in(cell: RobotCell, state: str) -> TaskControl:
    """Bring TaskControl1 (and the system) into ``state``: Idle, AtProgramStart, Suspended, Executing."""
    tc = tc_of(cell)
    await system_ready(cell)
    if state == "Idle":
        return tc
    assert await tc.load_by_name("gripper") == Status.OK
    assert await tc.load_by_name("slow") == Status.OK
    if state == "AtProgramStart":
        return tc
    assert await tc.start() == Status.OK
    await wait_until(lambda: tc.pointer == 1)  # in the long wait
    if state == "Executing":
        return tc
    assert await tc.stop(StopMode.QUICK_STOP) == Status.OK
    await wait_until(lambda: tc.state == "Ready")
    assert state == "Suspended" and tc.ready.current == "Suspended"
    return tc


TC = "TaskControlStateMachine"
RS = "ReadySubstateMachine"
EXT, APP, SYS, ERR = Reason.EXTERNAL, Reason.APPLICATION, Reason.SYSTEM, Reason.ERROR

# (state, call name, OPC method for Executable, status, resulting (state, ready substate), transitions)
Call = Callable[[TaskControl], Awaitable[int]]
CALLS: dict[str, tuple[str, str, Call]] = {
    "load_by_name": (TC, "LoadByName", lambda t: t.load_by_name("short")),
    "load_file": (TC, "LoadByNodeId", lambda t: t.load_file("short.robot")),
    "unload_program": (TC, "UnloadProgram", lambda t: t.unload_program()),
    "unload_by_name": (TC, "UnloadByName", lambda t: t.unload_by_name("Slow")),
    "unload_by_file": (TC, "UnloadByNodeId", lambda t: t.unload_by_file("slow.robot")),
    "unload_module": (TC, "UnloadByNodeId", lambda t: t.unload_module("Gripper")),
    "start": (TC, "Start", lambda t: t.start()),
    "stop": (TC, "Stop", lambda t: t.stop(0)),
    "reset": (RS, "ResetToProgramStart", lambda t: t.reset_to_program_start()),
}
TABLE = [
    ("Idle", "load_by_name", 0, ("Ready", "AtProgramStart"), [(TC, "IdleToReady", EXT)]),
    ("Idle", "load_file", 0, ("Ready", "AtProgramStart"), [(TC, "IdleToReady", EXT)]),
    ("Idle", "unload_program", 1, ("Idle", None), []),
    ("Idle", "unload_by_name", 1, ("Idle", None), []),  # nothing loaded: cannot act (decision 8)
    ("Idle", "unload_by_file", 1, ("Idle", None), []),  # nothing loaded: cannot act (decision 8)
    ("Idle", "unload_module", 1, ("Idle", None), []),  # nothing loaded: cannot act (decision 8)
    ("Idle", "start", 1, ("Idle", None), []),
    ("Idle", "stop", 1, ("Idle", None), []),
    ("Idle", "reset", 1, ("Idle", None), []),
    ("AtProgramStart", "load_by_name", 0, ("Ready", "AtProgramStart"), []),
    ("AtProgramStart", "load_file", 0, ("Ready", "AtProgramStart"), []),
    ("AtProgramStart", "unload_program", 0, ("Idle", None), [(TC, "ReadyToIdle", EXT)]),
    ("AtProgramStart", "unload_by_name", 0, ("Idle", None), [(TC, "ReadyToIdle", EXT)]),
    ("AtProgramStart", "unload_by_file", 0, ("Idle", None), [(TC, "ReadyToIdle", EXT)]),
    ("AtProgramStart", "unload_module", -4, ("Ready", "AtProgramStart"), []),
    ("AtProgramStart", "start", 0, ("Executing", None), [(TC, "ReadyToExecuting", EXT)]),
    ("AtProgramStart", "stop", 1, ("Ready", "AtProgramStart"), []),
    ("AtProgramStart", "reset", 0, ("Ready", "AtProgramStart"), []),
    ("Suspended", "load_by_name", 0, ("Ready", "AtProgramStart"), [(RS, "SuspendedToProgramStart", EXT)]),
    ("Suspended", "load_file", 0, ("Ready", "AtProgramStart"), [(RS, "SuspendedToProgramStart", EXT)]),
    ("Suspended", "unload_program", 0, ("Idle", None), [(TC, "ReadyToIdle", EXT)]),
    ("Suspended", "unload_by_name", 0, ("Idle", None), [(TC, "ReadyToIdle", EXT)]),
    ("Suspended", "unload_by_file", 0, ("Idle", None), [(TC, "ReadyToIdle", EXT)]),
    ("Suspended", "unload_module", -4, ("Ready", "Suspended"), []),
    ("Suspended", "start", 0, ("Executing", None), [(TC, "ReadyToExecuting", EXT)]),
    ("Suspended", "stop", 1, ("Ready", "Suspended"), []),
    ("Suspended", "reset", 0, ("Ready", "AtProgramStart"), [(RS, "SuspendedToProgramStart", EXT)]),
    ("Executing", "load_by_name", 1, ("Executing", None), []),
    ("Executing", "load_file", 1, ("Executing", None), []),
    ("Executing", "unload_program", 1, ("Executing", None), []),
    ("Executing", "unload_by_name", 1, ("Executing", None), []),
    ("Executing", "unload_by_file", 1, ("Executing", None), []),
    ("Executing", "unload_module", 1, ("Executing", None), []),
    ("Executing", "start", 1, ("Executing", None), []),
    ("Executing", "stop", 0, ("Ready", "Suspended"), [(TC, "ExecutingToReady", EXT)]),
    ("Executing", "reset", 1, ("Executing", None), []),
]


@pytest.mark.parametrize(("state", "call", "status", "result", "transitions"), TABLE)
async def test_task_control_every_state_and_method(
    cell: RobotCell,
    state: str,
    call: str,
    status: int,
    result: tuple[str, str | None],
    transitions: list[tuple[str, str, Reason]],
) -> None:
    tc = await tc_in(cell, state)
    machine_name, method, invoke = CALLS[call]
    executable = tc.executable(machine_name, method)
    log = Log(tc.machine, tc.ready)
    before = (tc.program_name, [m.name for m in tc.modules], tc.pointer)
    assert await invoke(tc) == status
    if call == "stop" and status == 0:
        await wait_until(lambda: tc.state != "Executing")
    assert (tc.state, tc.ready.current if tc.ready.active else None) == result
    assert log.transitions() == transitions
    # Decision 4: Executable is true exactly when the state lets the call succeed (vendor Status values
    # below 0 are about the argument, e.g. a module still in use, not about the state).
    if status >= 0:
        assert executable == (status == 0)
    # TaskProgramLoaded follows the state; a refused call changes nothing.
    assert tc.program_loaded == (tc.state in ("Ready", "Executing"))
    if status != 0:
        assert (tc.program_name, [m.name for m in tc.modules], tc.pointer) == before
    if tc.state == "Ready" and tc.ready.current == "AtProgramStart":
        assert tc.pointer == 0


async def test_executable_in_other_machines_and_unknown_methods(cell: RobotCell) -> None:
    tc = tc_of(cell)
    assert not tc.executable("SystemOperationStateMachine", "Start")
    assert not tc.executable(TC, "ResetToProgramStart")
    assert not tc.executable(TC, "Frobnicate")
    assert tc.executable(TC, "LoadByName")


# --- loading failures -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    ("name", "status"),
    [("nope", Status.NOT_FOUND), ("bad", Status.INVALID_CONTENT), ("far", Status.INVALID_CONTENT)],
)
async def test_failed_load_in_idle_takes_idle_to_idle_with_error(cell: RobotCell, name: str, status: int) -> None:
    tc = tc_of(cell)
    log = Log(tc.machine, tc.ready)
    assert await tc.load_by_name(name) == status
    assert log.items == [(TC, "IdleToIdle", ERR)]
    assert tc.state == "Idle" and not tc.program_loaded and tc.program_name == ""
    assert tc.last_error


async def test_load_file_errors(cell: RobotCell) -> None:
    tc = tc_of(cell)
    assert await tc.load_file("missing.robot") == Status.NOT_FOUND
    assert await tc.load_file("../escape.robot") == Status.NOT_FOUND
    assert await tc.load_file("bad.robot") == Status.INVALID_CONTENT
    assert tc.machine.last_transition is not None and tc.machine.last_transition.name == "IdleToIdle"
    assert await tc.load_file("lib/extra.robot") == Status.OK  # a module in a subdirectory
    assert tc.modules == [TaskModule("Extra", "0.1", False, "lib/extra.robot")]
    assert tc.state == "Idle"  # a module alone is no program


class Boom:
    def __init__(self, exc: Exception) -> None:
        self.exc = exc

    async def __call__(self, *args: object) -> None:
        raise self.exc


@pytest.mark.parametrize(
    ("exc", "status"),
    [
        (EquipmentError("controller busy"), Status.E_UNEXPECTED_ERROR),
        (ProgramRejected("syntax unknown to controller"), Status.INVALID_CONTENT),
        (RuntimeError("bug"), Status.E_UNEXPECTED_ERROR),
    ],
)
async def test_equipment_load_failures(
    cell: RobotCell, monkeypatch: pytest.MonkeyPatch, exc: Exception, status: int
) -> None:
    tc = tc_of(cell)
    monkeypatch.setattr(cell.equipment, "load", Boom(exc))
    log = Log(tc.machine)
    assert await tc.load_by_name("short") == status
    assert log.items == [(TC, "IdleToIdle", ERR)]


async def test_library_read_error_is_unexpected(cell: RobotCell, monkeypatch: pytest.MonkeyPatch) -> None:
    tc = tc_of(cell)

    def denied(relpath: str) -> str:
        raise PermissionError(relpath)

    monkeypatch.setattr(cell.library, "read", denied)
    monkeypatch.setattr(cell.library, "read_small", denied)  # the event loop's way to a small file
    assert await tc.load_by_name("short") == Status.E_UNEXPECTED_ERROR
    assert tc.machine.last_reason == ERR


@pytest.mark.parametrize("state", ["AtProgramStart", "Suspended"])
async def test_failed_load_in_ready_keeps_the_program(cell: RobotCell, state: str) -> None:
    tc = await tc_in(cell, state)
    before = (tc.program_name, tc.pointer, tc.ready.current, tc.modules)
    log = Log(tc.machine, tc.ready)
    assert await tc.load_by_name("bad") == Status.INVALID_CONTENT
    assert await tc.load_by_name("nope") == Status.NOT_FOUND
    assert (tc.program_name, tc.pointer, tc.ready.current, tc.modules) == before
    assert tc.state == "Ready" and log.items == []


async def test_load_in_ready_replaces_program_and_keeps_modules(cell: RobotCell) -> None:
    tc = await tc_in(cell, "AtProgramStart")
    assert tc.program_name == "Slow" and tc.modules[0].is_referenced
    assert await tc.load_by_name("short") == Status.OK
    assert (tc.program_name, tc.program_file) == ("Short", "short.robot")
    assert tc.modules == [TaskModule("Gripper", "1.2", False, "gripper.robot")]
    assert await tc.unload_by_name("Gripper") == Status.OK  # no longer referenced
    assert tc.modules == [] and tc.state == "Ready"
    assert await tc.unload_by_name("Gripper") == Status.NOT_FOUND


async def test_module_names_must_not_clash_with_the_program(cell: RobotCell, tmp_path: Path) -> None:
    tc = await tc_in(cell, "AtProgramStart")
    (tmp_path / "m.robot").write_text("module Slow\nroutine r\nwait 0\nend\n")
    (tmp_path / "p.robot").write_text("program Gripper\nwait 0\n")
    assert await tc.load_by_name("m") == Status.INVALID_CONTENT
    assert await tc.load_by_name("p") == Status.INVALID_CONTENT
    assert tc.program_name == "Slow"


async def test_unload_program_unloads_modules_too(cell: RobotCell) -> None:
    tc = await tc_in(cell, "AtProgramStart")
    assert await tc.load_by_name("extra") == Status.OK
    assert await tc.unload_program() == Status.OK
    assert tc.modules == [] and tc.program_name == "" and not tc.program_loaded
    assert await tc.load_by_name("slow") == Status.OK
    assert await tc.start() == Status.UNRESOLVED_REFERENCE  # Gripper went with the old program
    assert "module Gripper is not loaded" in tc.last_error


async def test_unload_failure_in_equipment(cell: RobotCell, monkeypatch: pytest.MonkeyPatch) -> None:
    tc = await tc_in(cell, "AtProgramStart")
    assert await tc.load_by_name("extra") == Status.OK
    monkeypatch.setattr(cell.equipment, "unload", Boom(EquipmentError("locked")))
    assert await tc.unload_module("Extra") == Status.E_UNEXPECTED_ERROR
    assert await tc.unload_program() == Status.E_UNEXPECTED_ERROR
    assert tc.state == "Ready" and tc.program_name == "Slow"


async def test_modules_can_be_unloaded_in_idle(cell: RobotCell) -> None:
    tc = tc_of(cell)
    assert await tc.load_by_name("extra") == Status.OK
    assert tc.executable(TC, "UnloadByName") and not tc.executable(TC, "UnloadProgram")
    assert await tc.unload_by_file("lib/extra.robot") == Status.OK
    assert tc.modules == [] and tc.state == "Idle"


# --- running -----------------------------------------------------------------------------------------
async def test_program_end_returns_to_ready_at_program_start(cell: RobotCell) -> None:
    tc = tc_of(cell)
    await system_ready(cell)
    assert await tc.load_by_name("short") == Status.OK
    log = Log(tc.machine, tc.ready, *cell.system.machines())
    assert await tc.start() == Status.OK
    assert cell.system.state == "Executing" and cell.system.executing.current == "Running"
    await tc.wait_until_not_executing()
    assert log.transitions() == [
        (TC, "ReadyToExecuting", EXT),
        ("SystemOperationStateMachine", "ReadyToExecuting", SYS),
        (TC, "ExecutingToReady", APP),
        ("SystemOperationStateMachine", "ExecutingToReady", APP),
    ]
    assert tc.ready.current == "AtProgramStart" and tc.pointer == 0
    assert cell.equipment.positions == (0.0,) * 6  # type: ignore[attr-defined]


async def test_resume_continues_where_suspended(cell: RobotCell) -> None:
    tc = await tc_in(cell, "Suspended")
    assert tc.pointer == 1
    seen: list[int] = []
    tc.listeners.append(lambda: seen.append(tc.pointer))
    assert await tc.start() == Status.OK
    await wait_until(lambda: tc.current_line == 4)  # the wait, line 4 of slow.robot
    assert min(seen) == 1  # it did not start again at the move


async def test_step_mode(cell: RobotCell) -> None:
    tc = tc_of(cell)
    await system_ready(cell)
    assert await tc.set_execution_mode(ExecutionMode.STEP) == Status.OK
    assert await tc.load_by_name("short") == Status.OK
    ends = []
    for _ in range(3):
        assert await tc.start() == Status.OK
        await tc.wait_until_not_executing()
        ends.append((tc.pointer, tc.ready.current, tc.machine.last_reason))
    assert ends == [(1, "Suspended", SYS), (2, "Suspended", SYS), (0, "AtProgramStart", APP)]


async def test_continuous_mode_runs_until_stopped_at_end_of_cycle(cell: RobotCell) -> None:
    tc = tc_of(cell)
    await system_ready(cell)
    assert await tc.set_execution_mode(ExecutionMode.CONTINUOUS) == Status.OK
    assert await tc.load_by_name("short") == Status.OK
    assert await tc.start() == Status.OK
    await wait_until(lambda: cell.equipment.cycles >= 2)  # type: ignore[attr-defined]
    assert tc.state == "Executing"
    assert await tc.stop(StopMode.END_OF_CYCLE) == Status.OK
    await tc.wait_until_not_executing()
    assert (tc.state, tc.ready.current, tc.pointer, tc.machine.last_reason) == ("Ready", "Suspended", 0, EXT)


async def test_execution_mode_argument_and_state(cell: RobotCell) -> None:
    tc = await tc_in(cell, "Executing")
    with pytest.raises(CallError) as info:
        await tc.set_execution_mode(3)
    assert (info.value.status, info.value.argument) == ("BadInvalidArgument", 0)
    assert await tc.set_execution_mode(ExecutionMode.STEP) == Status.E_SYSTEM_STATE
    assert tc.execution_mode is ExecutionMode.CYCLE


async def test_stop_is_accepted_at_once_and_completes_later(cell: RobotCell) -> None:
    tc = await tc_in(cell, "Executing")
    assert await tc.stop(StopMode.END_OF_INSTRUCTION) == Status.OK
    assert tc.state == "Executing" and tc.stopping
    assert not tc.executable(TC, "Stop")
    assert await tc.stop(StopMode.QUICK_STOP) == Status.E_SYSTEM_STATE  # one stop at a time
    assert cell.system.executing.current == "Stopping"  # the only executing task is stopping


@pytest.mark.parametrize("mode", [-1, 6, 99])
async def test_stop_mode_outside_possible_stop_modes(cell: RobotCell, mode: int) -> None:
    tc = await tc_in(cell, "Executing")
    for stop in (tc.stop, cell.system.stop):
        with pytest.raises(CallError) as info:
            await stop(mode)
        assert (info.value.status, info.value.argument) == ("BadInvalidArgument", 0)
    assert tc.state == "Executing" and not tc.stopping


async def test_stop_mode_zero_is_the_configured_default(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    robot = SimulatedRobot(time_scale=SCALE, power_up_time=0.1)
    cell = RobotCell(
        robot,
        make_library(tmp_path),
        tables=robotics_tables(),
        possible_stop_modes=(StopMode.QUICK_STOP, StopMode.END_OF_INSTRUCTION),
        default_stop_mode=StopMode.END_OF_INSTRUCTION,
    )
    try:
        tc = await tc_in(cell, "Executing")
        asked: list[StopMode] = []
        real_stop = robot.stop

        async def spy(task: str, mode: StopMode) -> None:
            asked.append(mode)
            await real_stop(task, mode)

        monkeypatch.setattr(robot, "stop", spy)
        with pytest.raises(CallError):
            await tc.stop(StopMode.ON_PATH)  # valid in general, not on this controller
        assert await tc.stop(0) == Status.OK
        assert asked == [StopMode.END_OF_INSTRUCTION]
    finally:
        await cell.close()
    with pytest.raises(ValueError):
        RobotCell(robot, cell.library, tables=robotics_tables(), possible_stop_modes=(StopMode.QUICK_STOP,))


async def test_start_needs_the_system_ready(cell: RobotCell) -> None:
    tc = tc_of(cell)
    assert await tc.load_by_name("short") == Status.OK
    assert not tc.executable(TC, "Start")
    assert await tc.start() == Status.E_SYSTEM_STATE
    assert tc.state == "Ready"


async def test_run_fault_returns_to_ready_with_error(cell: RobotCell, monkeypatch: pytest.MonkeyPatch) -> None:
    tc = tc_of(cell)
    await system_ready(cell)
    assert await tc.load_by_name("short") == Status.OK
    monkeypatch.setattr(cell.equipment, "run", Boom(EquipmentError("servo fault")))
    assert await tc.start() == Status.OK
    await tc.wait_until_not_executing()
    assert (tc.state, tc.ready.current, tc.machine.last_reason) == ("Ready", "Suspended", ERR)
    assert "servo fault" in tc.last_error
    assert (cell.system.state, cell.system.machine.last_reason) == ("Ready", ERR)


async def test_equipment_stop_failure(cell: RobotCell, monkeypatch: pytest.MonkeyPatch) -> None:
    tc = await tc_in(cell, "Executing")
    monkeypatch.setattr(cell.equipment, "stop", Boom(EquipmentError("no answer")))
    assert await tc.stop(0) == Status.E_UNEXPECTED_ERROR
    assert tc.state == "Executing" and not tc.stopping


async def test_system_stop_refused_by_the_equipment_leaves_the_system_running(
    cell: RobotCell, monkeypatch: pytest.MonkeyPatch
) -> None:
    so = await so_in(cell, "Running")
    tc = tc_of(cell)
    real_stop = cell.equipment.stop
    monkeypatch.setattr(cell.equipment, "stop", Boom(EquipmentError("no answer")))
    log = Log(*so.machines(), *tc.machines())
    assert await so.stop(0) == Status.E_UNEXPECTED_ERROR
    # Nothing is stopping, so the system must not claim Stopping (it could never leave it).
    assert (so.state, so.executing.current, tc.state, tc.stopping) == ("Executing", "Running", "Executing", False)
    assert log.transitions() == [] and "TaskControl1" in so.last_error
    check_consistent(cell)
    monkeypatch.setattr(cell.equipment, "stop", real_stop)
    assert so.executable(SO, "Stop") and await so.stop(StopMode.QUICK_STOP) == Status.OK
    await wait_until(lambda: so.state == "Ready")
    assert log.transitions() == [
        (EXE, "RunningToStopping", EXT),
        (TC, "ExecutingToReady", EXT),
        (SO, "ExecutingToReady", EXT),
    ]


async def test_load_in_ready_refused_by_the_equipment_keeps_program_and_substate(
    cell: RobotCell, monkeypatch: pytest.MonkeyPatch
) -> None:
    for state in ("Suspended", "AtProgramStart"):
        tc = await tc_in(cell, state) if state == "Suspended" else tc_of(cell)
        if state == "AtProgramStart":
            assert await tc.reset_to_program_start() == Status.OK
        before = (tc.program_name, tc.program_file, tc.pointer, tc.ready.current, tc.modules)
        log = Log(tc.machine, tc.ready)
        for exc, status in ((EquipmentError("busy"), Status.E_UNEXPECTED_ERROR), (ProgramRejected("no"), -2)):
            monkeypatch.setattr(cell.equipment, "load", Boom(exc))
            assert await tc.load_by_name("short") == status
            assert await tc.load_file("lib/extra.robot") == status
        monkeypatch.undo()
        assert (tc.program_name, tc.program_file, tc.pointer, tc.ready.current, tc.modules) == before
        assert tc.state == "Ready" and log.items == []


async def test_replacing_a_used_module_while_suspended_goes_back_to_the_program_start(cell: RobotCell) -> None:
    tc = await tc_in(cell, "Suspended")
    assert tc.pointer == 1
    log = Log(tc.machine, tc.ready)
    assert await tc.load_by_name("extra") == Status.OK  # not used by the program: the pointer stays
    assert (tc.ready.current, tc.pointer, log.items) == ("Suspended", 1, [])
    assert await tc.load_by_name("gripper") == Status.OK  # Gripper is used: its steps may differ now
    assert (tc.ready.current, tc.pointer) == ("AtProgramStart", 0)
    assert log.items == [(RS, "SuspendedToProgramStart", EXT)]


# --- SystemOperation ---------------------------------------------------------------------------------
SO = "SystemOperationStateMachine"


async def so_in(cell: RobotCell, state: str) -> SystemOperation:
    """StandBy, GettingReady, Ready, Running (a task executes) or Stopping."""
    so = cell.system
    if state == "StandBy":
        return so
    if state == "GettingReady":
        cell.equipment.power_up_time = 5000.0  # type: ignore[attr-defined]
        assert await so.get_ready() == Status.OK
        return so
    await system_ready(cell)
    tc = tc_of(cell)
    assert await tc.load_by_name("gripper") == Status.OK
    assert await tc.load_by_name("slow") == Status.OK
    if state == "Ready":
        return so
    assert await so.start() == Status.OK
    await wait_until(lambda: tc.pointer == 1)
    if state == "Stopping":
        assert await so.stop(StopMode.END_OF_INSTRUCTION) == Status.OK  # the 2000 s wait: stays Stopping
    return so


def background_settled(cell: RobotCell) -> bool:
    """Every background task of ``cell`` has ended, but a running program and a power-up."""
    so, tcs = cell.system, list(cell.tasks.values())
    parked = {so._getting_ready, *(tc._run for tc in tcs)}
    return all(t.done() or t in parked for t in (*so._bg.tasks, *(t for tc in tcs for t in tc._bg.tasks)))


SO_CALLS: dict[str, Callable[[SystemOperation], Awaitable[int]]] = {
    "GetReady": lambda s: s.get_ready(),
    "StandDown": lambda s: s.stand_down(),
    "Start": lambda s: s.start(),
    "Stop": lambda s: s.stop(0),
}
IDLE, EXE = "IdleSubstateMachine", "ExecutingSubstateMachine"
SO_TABLE = [
    ("StandBy", "GetReady", 0, "Ready", [(IDLE, "StandByToGettingReady", EXT), (SO, "IdleToReady", EXT)]),
    ("StandBy", "StandDown", 1, "Idle", []),
    ("StandBy", "Start", 1, "Idle", []),
    ("StandBy", "Stop", 1, "Idle", []),
    ("GettingReady", "GetReady", 1, "Idle", []),
    ("GettingReady", "StandDown", 0, "Idle", [(IDLE, "GettingReadyToStandBy", EXT), (SO, "IdleToIdle", EXT)]),
    ("GettingReady", "Start", 1, "Idle", []),
    ("GettingReady", "Stop", 1, "Idle", []),
    ("Ready", "GetReady", 1, "Ready", []),
    ("Ready", "StandDown", 0, "Idle", [(SO, "ReadyToIdle", EXT)]),
    ("Ready", "Start", 0, "Executing", [(SO, "ReadyToExecuting", EXT), (TC, "ReadyToExecuting", SYS)]),
    ("Ready", "Stop", 1, "Ready", []),
    ("Running", "GetReady", 1, "Executing", []),
    ("Running", "StandDown", 1, "Executing", []),
    ("Running", "Start", 1, "Executing", []),
    (
        "Running",
        "Stop",
        0,
        "Ready",
        [(EXE, "RunningToStopping", EXT), (TC, "ExecutingToReady", EXT), (SO, "ExecutingToReady", EXT)],
    ),
    ("Stopping", "GetReady", 1, "Executing", []),
    ("Stopping", "StandDown", 1, "Executing", []),
    ("Stopping", "Start", 1, "Executing", []),
    ("Stopping", "Stop", 1, "Executing", []),
]


@pytest.mark.parametrize(("state", "method", "status", "result", "transitions"), SO_TABLE)
async def test_system_operation_every_state_and_method(
    cell: RobotCell, state: str, method: str, status: int, result: str, transitions: list[tuple[str, str, Reason]]
) -> None:
    so = await so_in(cell, state)
    executable = so.executable(SO, method)
    log = Log(*so.machines(), *tc_of(cell).machines())
    assert await SO_CALLS[method](so) == status
    await wait_until(lambda: len(log.transitions()) >= len(transitions) and not so.powering_down)
    # Nothing else follows: the cell's background work has ended, but for a program still running or
    # a power-up still under way (both parked in waits of thousands of seconds).
    await wait_until(lambda: background_settled(cell))
    assert so.state == result
    assert log.transitions() == transitions
    assert executable == (status == 0)
    if result == "Idle":
        assert so.idle.current == ("GettingReady" if state == "GettingReady" and status else "StandBy")
    assert (so.state == "Executing") == any(t.executing for t in cell.tasks.values())


async def test_get_ready_is_asynchronous_and_visible(cell: RobotCell) -> None:
    so = cell.system
    assert await so.get_ready() == Status.OK
    assert (so.state, so.idle.current) == ("Idle", "GettingReady")
    assert not so.executable(SO, "GetReady") and so.executable(SO, "StandDown")
    await wait_until(lambda: so.state == "Ready")
    assert cell.equipment.powered  # type: ignore[attr-defined]


async def test_failed_power_up_takes_idle_to_idle_with_error(cell: RobotCell) -> None:
    so = cell.system
    cell.equipment.fail_power_up = True  # type: ignore[attr-defined]
    log = Log(*so.machines())
    assert await so.get_ready() == Status.OK
    await wait_until(lambda: so.idle.current == "StandBy")
    assert log.transitions() == [
        (IDLE, "StandByToGettingReady", EXT),
        (IDLE, "GettingReadyToStandBy", ERR),
        (SO, "IdleToIdle", ERR),
    ]
    assert so.state == "Idle" and "did not come up" in so.last_error


async def test_stand_down_takes_time_and_blocks_start(cell: RobotCell) -> None:
    so = await so_in(cell, "Ready")
    cell.equipment.power_down_time = 2000.0  # type: ignore[attr-defined]
    assert await so.stand_down() == Status.OK
    assert so.state == "Ready" and so.powering_down
    assert not so.executable(SO, "Start") and not tc_of(cell).executable(TC, "Start")
    assert await so.start() == Status.E_SYSTEM_STATE
    assert await tc_of(cell).start() == Status.E_SYSTEM_STATE
    assert await so.stand_down() == Status.E_SYSTEM_STATE


async def test_get_ready_waits_for_the_power_down_of_a_cancelled_get_ready(cell: RobotCell) -> None:
    so = await so_in(cell, "GettingReady")
    cell.equipment.power_down_time = 400.0  # type: ignore[attr-defined]  # 0.2 s real
    assert await so.stand_down() == Status.OK
    assert (so.state, so.idle.current, so.powering_down) == ("Idle", "StandBy", True)
    # A GetReady now would race the drives switching off (and could end Ready with power off).
    assert not so.executable(SO, "GetReady")
    assert await so.get_ready() == Status.E_SYSTEM_STATE
    assert so.idle.current == "StandBy"
    await wait_until(lambda: not so.powering_down, timeout=10.0)
    cell.equipment.power_up_time = 2.0  # type: ignore[attr-defined]
    assert so.executable(SO, "GetReady")
    await system_ready(cell)
    assert cell.equipment.powered  # type: ignore[attr-defined]


async def test_start_with_nothing_to_start_is_refused(cell: RobotCell) -> None:
    so = await so_in(cell, "StandBy")
    await system_ready(cell)
    assert not so.executable(SO, "Start")
    assert await so.start() == Status.E_SYSTEM_STATE
    assert await tc_of(cell).load_by_name("slow") == Status.OK  # uses Gripper, which is missing
    assert await so.start() == Status.UNRESOLVED_REFERENCE
    assert so.state == "Ready"


# --- conditions (decision 18) ---------------------------------------------------------------------------
async def test_active_alarm_and_acknowledge_required(cell: RobotCell) -> None:
    so, robot, tc = cell.system, cell.equipment, tc_of(cell)
    events: list[tuple[str, bool, bool]] = []
    so.condition_listeners.append(lambda c: events.append((c.name, c.active, c.acked)))
    robot.raise_alarm("EmergencyStop", "E-stop pressed at station 2")  # type: ignore[attr-defined]
    assert so.conditions["EmergencyStop"].message == "E-stop pressed at station 2"
    assert not so.executable(SO, "GetReady")
    assert await so.get_ready() == Status.E_ACTIVE_ALARM
    robot.clear_alarm("EmergencyStop")  # type: ignore[attr-defined]
    assert await so.get_ready() == Status.E_ACKNOWLEDGE_REQUIRED
    assert so.state == "Idle" and so.idle.current == "StandBy"
    so.acknowledge("EmergencyStop", "reset by operator")
    with pytest.raises(CallError) as info:
        so.acknowledge("EmergencyStop")
    assert info.value.status == "BadConditionBranchAlreadyAcked"
    with pytest.raises(CallError):
        so.acknowledge("Nope")
    assert events == [("EmergencyStop", True, False), ("EmergencyStop", False, False), ("EmergencyStop", False, True)]
    await system_ready(cell)
    assert await tc.load_by_name("short") == Status.OK
    robot.raise_alarm("CollisionDetected")  # type: ignore[attr-defined]
    assert await so.start() == Status.E_ACTIVE_ALARM
    assert await tc.start() == Status.E_ACTIVE_ALARM
    robot.clear_alarm("CollisionDetected")  # type: ignore[attr-defined]
    assert await so.start() == Status.E_ACKNOWLEDGE_REQUIRED
    assert await tc.start() == Status.E_ACKNOWLEDGE_REQUIRED
    so.acknowledge("CollisionDetected")
    assert await tc.start() == Status.OK


async def test_alarm_while_executing_stops_everything_with_error(cell: RobotCell) -> None:
    so = await so_in(cell, "Running")
    tc = tc_of(cell)
    log = Log(*so.machines(), *tc.machines())
    cell.equipment.raise_alarm("CollisionDetected", "axis 3")  # type: ignore[attr-defined]
    await wait_until(lambda: so.state == "Ready")
    assert log.transitions() == [(TC, "ExecutingToReady", ERR), (SO, "ExecutingToReady", ERR)]
    assert tc.ready.current == "Suspended" and "CollisionDetected" in tc.last_error


async def test_alarm_right_after_start_stops_the_program_with_error(cell: RobotCell) -> None:
    tc = tc_of(cell)
    await system_ready(cell)
    assert await tc.load_by_name("short") == Status.OK
    log = Log(tc.machine, cell.system.machine)
    assert await tc.start() == Status.OK
    cell.equipment.raise_alarm("EmergencyStop")  # type: ignore[attr-defined]  # before the run's first step
    await tc.wait_until_not_executing()
    assert log.transitions() == [
        (TC, "ReadyToExecuting", EXT),
        (SO, "ReadyToExecuting", SYS),
        (TC, "ExecutingToReady", ERR),
        (SO, "ExecutingToReady", ERR),
    ]
    assert tc.ready.current == "Suspended" and cell.equipment.positions == (0.0,) * 6  # type: ignore[attr-defined]


# --- coupling with two task controls (decision 19) -----------------------------------------------------------
async def test_system_start_and_stop_drive_every_task(tmp_path: Path) -> None:
    robot = SimulatedRobot(time_scale=SCALE, power_up_time=0.1)
    cell = RobotCell(robot, make_library(tmp_path), tables=robotics_tables(), task_names=("TC1", "TC2", "TC3"))
    try:
        so, (t1, t2, t3) = cell.system, cell.tasks.values()
        await system_ready(cell)
        for t in (t1, t2):
            assert await t.load_by_name("gripper") == Status.OK
            assert await t.load_by_name("slow") == Status.OK
        assert await so.start() == Status.OK
        assert (t1.state, t2.state, t3.state) == ("Executing", "Executing", "Idle")
        # Stopping one task leaves the system Running; stopping the last makes it Stopping.
        assert await t1.stop(StopMode.END_OF_INSTRUCTION) == Status.OK
        assert so.executing.current == "Running"
        assert await t2.stop(StopMode.END_OF_INSTRUCTION) == Status.OK
        assert so.executing.current == "Stopping"
        assert not t1.executable(TC, "Start") or t1.state != "Ready"
        # Cancel the long waits by a quick stop underneath: the stops complete.
        await robot.stop("TC1", StopMode.QUICK_STOP)
        await robot.stop("TC2", StopMode.QUICK_STOP)
        await wait_until(lambda: so.state == "Ready")
        assert so.machine.last_reason == SYS
        assert await t1.start() == Status.OK and await t2.start() == Status.OK
        assert so.state == "Executing"
        assert await so.stand_down() == Status.E_SYSTEM_STATE
        assert await so.stop(StopMode.QUICK_STOP) == Status.OK
        await wait_until(lambda: so.state == "Ready")
        assert so.machine.last_reason == EXT and t1.state == t2.state == "Ready"
    finally:
        await cell.close()


async def test_cell_listener_hears_every_change(cell: RobotCell) -> None:
    calls: list[int] = []
    cell.add_listener(lambda: calls.append(1))
    assert await tc_of(cell).load_by_name("extra") == Status.OK  # data only, no transition
    assert calls
    calls.clear()
    assert await tc_of(cell).load_by_name("short") == Status.OK
    assert len(calls) >= 2  # the transition, and the data


# --- random command sequences -----------------------------------------------------------------------------
COMMANDS = [
    "so.get_ready",
    "so.stand_down",
    "so.start",
    "so.stop",
    "tc.load.short",
    "tc.load.slow",
    "tc.load.gripper",
    "tc.load.bad",
    "tc.unload_program",
    "tc.unload.Gripper",
    "tc.unload.Slow",
    "tc.start",
    "tc.stop",
    "tc.reset",
    "tc.mode",
    "alarm.raise",
    "alarm.clear",
    "alarm.ack",
    "sleep",
]
# Calls whose success depends only on state: Executable must predict them exactly.
PREDICTED = {
    "so.get_ready": (SO, "GetReady"),
    "so.stand_down": (SO, "StandDown"),
    "so.start": (SO, "Start"),
    "so.stop": (SO, "Stop"),
    "tc.start": (TC, "Start"),
    "tc.stop": (TC, "Stop"),
    "tc.unload_program": (TC, "UnloadProgram"),
    "tc.reset": (RS, "ResetToProgramStart"),
    "tc.load.short": (TC, "LoadByName"),
    "tc.load.gripper": (TC, "LoadByName"),
}


def check_consistent(cell: RobotCell) -> None:
    so = cell.system
    for machine in cell.machines():
        if machine.parent is not None:
            assert machine.active == (machine.parent.active and machine.parent.current == machine.parent_state)
    assert (so.state == "Executing") == any(t.executing for t in cell.tasks.values())
    if so.state == "Executing" and so.executing.current == "Stopping":
        assert all(t.stopping for t in cell.tasks.values() if t.executing)
    assert (so._getting_ready is not None) == (so.state == "Idle" and so.idle.current == "GettingReady")
    for t in cell.tasks.values():
        assert t.program_loaded == (t.state in ("Ready", "Executing"))
        assert t.program_name == (t.program.name if t.program else "")
        if t.ready.active and t.ready.current == "AtProgramStart":
            assert t.pointer == 0
        if t.stopping:
            assert t.state == "Executing"


async def run_commands(root: Path, commands: list[str]) -> None:
    robot = SimulatedRobot(time_scale=0.0002, power_up_time=2.0, power_down_time=2.0)
    cell = RobotCell(robot, make_library(root), tables=robotics_tables())
    so, tc = cell.system, tc_of(cell)
    try:
        for command in commands:
            predicted = PREDICTED.get(command)
            could = (so if predicted[0] == SO else tc).executable(predicted[0], predicted[1]) if predicted else None
            kind, _, arg = command.partition(".")
            status: int | None = None
            if kind == "so":
                status = await SO_CALLS[
                    {"get_ready": "GetReady", "stand_down": "StandDown", "start": "Start", "stop": "Stop"}[arg]
                ](so)
            elif command.startswith("tc.load."):
                status = await tc.load_by_name(command.removeprefix("tc.load."))
            elif command.startswith("tc.unload."):
                status = await tc.unload_by_name(command.removeprefix("tc.unload."))
            elif command == "tc.unload_program":
                status = await tc.unload_program()
            elif command == "tc.start":
                status = await tc.start()
            elif command == "tc.stop":
                status = await tc.stop(StopMode.QUICK_STOP)
            elif command == "tc.reset":
                status = await tc.reset_to_program_start()
            elif command == "tc.mode":
                await tc.set_execution_mode((tc.execution_mode + 1) % 3)
            elif command == "alarm.raise":
                robot.raise_alarm("EmergencyStop")
            elif command == "alarm.clear":
                robot.clear_alarm("EmergencyStop")
            elif command == "alarm.ack":
                if not so.conditions["EmergencyStop"].acked:
                    so.acknowledge("EmergencyStop")
            else:
                await asyncio.sleep(0.002)
            if predicted is not None:
                assert could == (status == Status.OK), (command, status)
            check_consistent(cell)
            await asyncio.sleep(0)
            check_consistent(cell)
    finally:
        await cell.close()


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(commands=st.lists(st.sampled_from(COMMANDS), max_size=40))
def test_random_command_sequences_keep_the_machines_consistent(tmp_path: Path, commands: list[str]) -> None:
    asyncio.run(run_commands(tmp_path, commands))


def test_program_type_is_what_the_equipment_receives(tmp_path: Path) -> None:
    loaded: list[Program] = []

    async def scenario() -> None:
        robot = SimulatedRobot(time_scale=SCALE)
        cell = RobotCell(robot, make_library(tmp_path), tables=robotics_tables())
        real_load = robot.load

        async def spy(task: str, program: Program) -> None:
            loaded.append(program)
            await real_load(task, program)

        robot.load = spy  # type: ignore[method-assign]
        assert await tc_of(cell).load_by_name("pick_and_place") == Status.OK
        await cell.close()

    asyncio.run(scenario())
    assert [(p.name, p.version, p.uses) for p in loaded] == [("PickAndPlace", "2.0", ("Gripper",))]


def test_the_tables_are_checked_against_every_name_the_model_uses() -> None:
    import dataclasses

    from uacell.models import StateTables
    from uacell.robotics.model import STAYS, RoboticsTables

    real = StateTables(official())

    def without_suspended(model: str, type_name: str):
        table = real(model, type_name)
        if type_name != "ReadySubstateMachineType":
            return table
        states = {k: v for k, v in table.states.items() if k != "Suspended"}
        return dataclasses.replace(table, states=states)

    with pytest.raises(LookupError, match="ReadySubstateMachineType in the NodeSet has no Suspended"):
        RoboticsTables.load(without_suspended)
    tables = RoboticsTables.load(real)
    # Every method the model lets act without a transition is one the NodeSet gives some machine.
    assert {m for m, _ in STAYS} <= tables.task_control.methods | tables.ready.methods


async def test_executable_follows_the_nodeset_causes_plus_the_declared_stays(cell: RobotCell) -> None:
    tc = tc_of(cell)
    # Idle: only the loads (IdleToReady is caused by LoadByName/LoadByNodeId); nothing to unload yet.
    offered = {m for machine, m in tc.methods() if tc.executable(machine, m)}
    assert offered == {"LoadByName", "LoadByNodeId"}
    assert {(machine, m) for machine, m in cell.system.methods() if cell.system.executable(machine, m)} == {
        ("SystemOperationStateMachine", "GetReady")
    }


async def test_a_controller_without_a_motion_device_refuses_move_and_runs_the_rest(tmp_path: Path) -> None:
    """motion_device = "": nothing to move, so a program or module with a `move` is invalid content (−2)."""
    from uacell.robotics.binding.programs import IDLE_PROGRAM

    (tmp_path / "idle.robot").write_text(IDLE_PROGRAM)
    cell = RobotCell(
        SimulatedRobot(time_scale=SCALE, power_up_time=0.1),
        make_library(tmp_path),
        tables=robotics_tables(),
        motion_devices=(),
    )
    try:
        tc = tc_of(cell)
        await system_ready(cell)
        for name in ("short", "gripper"):  # a program's move, a module routine's move
            assert await tc.load_by_name(name) == Status.INVALID_CONTENT
            assert "'move' needs a motion device, and this controller moves none" in tc.last_error
        assert tc.state == "Idle"
        assert await tc.load_by_name("idle") == Status.OK
        log = Log(tc.machine)
        assert await tc.start() == Status.OK
        await wait_until(lambda: len(log.transitions()) == 2)  # the program ran to its end
        assert [t for _, t, _ in log.transitions()] == ["ReadyToExecuting", "ExecutingToReady"]
        assert tc.ready.current == "AtProgramStart"
    finally:
        await cell.close()


async def test_the_same_text_loads_the_same_program_and_a_changed_one_is_parsed_again(
    cell: RobotCell, tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import uacell.core.files

    monkeypatch.setattr(uacell.core.files, "SETTLE_NS", 0)  # the library keeps texts at once
    tc = await tc_in(cell, "Idle")
    assert await tc.load_by_name("short") == Status.OK
    first = tc.program
    assert first is not None and first.name == "Short"
    assert await tc.unload_program() == Status.OK
    assert await tc.load_by_name("short") == Status.OK
    assert tc.program is first  # parsed once: a Program is immutable
    assert await tc.unload_program() == Status.OK
    # Another text under the same name (a new file): parsed, and what it says is what runs.
    replacement = tmp_path / "short.new"
    replacement.write_text("program Short version 2\nmove 1 0 0 0 0 0\nwait 0.1\n")
    replacement.replace(tmp_path / "short.robot")
    assert await tc.load_by_name("short") == Status.OK
    assert tc.program is not first and tc.program is not None
    assert (tc.program.version, len(tc.program.instructions)) == ("2", 2)
    assert await tc.unload_program() == Status.OK
    # A text that does not parse is refused every time, never answered from a kept program.
    (tmp_path / "short.robot").write_text("program Short\nmove 0 0 0\n")
    assert await tc.load_by_name("short") == Status.INVALID_CONTENT
    assert await tc.load_by_name("short") == Status.INVALID_CONTENT
    assert tc.program is None and tc.state == "Idle"
