"""The pure Robotics model over a controller that keeps its own programs, confirms its starts, reports
its drives and resets its faults (the optional capabilities of decision 70): an in-memory controller
stands in for a gateway driver, so every rule is checked without a transport."""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable, Sequence
from pathlib import Path

import pytest
from helpers import robotics_tables, wait_until

from uacell.core.fsm import Change, Reason
from uacell.robotics.equipment import (
    AlarmListener,
    AlarmReset,
    AlarmStop,
    AxisInfo,
    AxisState,
    ConfirmedStart,
    EquipmentError,
    ExecutionMode,
    PowerFeedback,
    ProgramCatalogue,
    ProgramRejected,
    Progress,
    RobotEquipment,
    RunOutcome,
    StartRefused,
    StopMode,
    UnknownProgram,
)
from uacell.robotics.model import RobotCell, Status, SystemOperation, TaskControl
from uacell.robotics.program import Program
from uacell.robotics.program_cache import DirectoryLibrary
from uacell.robotics.sim import DEFAULT_AXES, SimulatedRobot


class Controller:
    """A controller with programs ``pick`` and ``broken`` (refused when selected); its operator panel is
    the test: ``remote``, ``fault()``, ``drop_drives()``, ``finish()``."""

    def __init__(self) -> None:
        self.remote = True
        self.refuse_next = False
        self.drives = False
        self.fault_active = False
        self.selected = ""
        self.running = asyncio.Event()
        self.ended = asyncio.Event()
        self.resets = 0
        self.sent: list[str] = []
        self._alarms: list[AlarmListener] = []
        self._power: list[Callable[[bool], None]] = []

    # the panel
    def fault(self) -> None:
        self.fault_active = True
        self.ended.set()
        for listener in self._alarms:
            listener("ControllerFault", True, "fault 7")

    def set_drives(self, on: bool) -> None:
        self.drives = on
        for listener in self._power:
            listener(on)

    def finish(self) -> None:
        self.ended.set()

    # RobotEquipment
    @property
    def axes(self) -> Sequence[AxisInfo]:
        return DEFAULT_AXES

    @property
    def alarm_names(self) -> Sequence[str]:
        return ("ControllerFault",)

    def add_alarm_listener(self, listener: AlarmListener) -> None:
        self._alarms.append(listener)

    def axis_states(self) -> Sequence[AxisState]:
        return [AxisState(0.0, 0.0) for _ in DEFAULT_AXES]

    async def power_up(self) -> None:
        self.sent.append("drives on")
        self.set_drives(True)

    async def power_down(self) -> None:
        self.sent.append("drives off")
        self.set_drives(False)

    async def load(self, task: str, program: Program) -> None:
        if program.name.lower() != "pick":
            raise ProgramRejected(f"the controller holds no program {program.name}")
        self.selected = "pick"

    async def unload(self, task: str, name: str) -> None:
        pass

    async def run(self, task: str, pointer: int, mode: ExecutionMode, progress: Progress) -> RunOutcome:
        await self.ended.wait()
        self.running.clear()
        if self.fault_active:
            raise AlarmStop("fault 7")
        return RunOutcome(0, completed=True)

    async def stop(self, task: str, mode: StopMode) -> None:
        self.ended.set()

    # the capabilities
    def start_refusal(self) -> str | None:
        return None if self.remote else "not in remote control"

    async def begin(self, task: str, pointer: int, mode: ExecutionMode) -> None:
        if self.fault_active:
            raise AlarmStop("fault 7")
        if self.refuse_next:  # it changed its mind between its last report and the start
            self.refuse_next = False
            raise StartRefused("not in remote control any more")
        self.sent.append("start")
        self.ended.clear()
        self.running.set()

    def add_power_listener(self, listener: Callable[[bool], None]) -> None:
        self._power.append(listener)

    def alarm_acknowledged(self, name: str) -> None:
        self.resets += 1
        self.fault_active = False
        for listener in self._alarms:
            listener("ControllerFault", False, "")

    def program_names(self) -> Sequence[str]:
        return ("pick", "broken")

    def find_program(self, name: str) -> str | None:
        return name if name in self.program_names() else None

    async def select(self, task: str, name: str) -> None:
        if name == "broken":
            raise ProgramRejected("the controller refuses broken")
        if name not in self.program_names():
            raise UnknownProgram(name)
        self.sent.append(f"select {name}")
        self.selected = name


@pytest.fixture
async def rig(tmp_path: Path) -> AsyncIterator[tuple[RobotCell, Controller]]:
    controller = Controller()
    cell = RobotCell(controller, DirectoryLibrary(tmp_path), tables=robotics_tables())
    yield cell, controller
    controller.ended.set()
    await cell.close()


async def ready_with_pick(cell: RobotCell) -> tuple[TaskControl, SystemOperation]:
    """SystemOperation Ready, the controller's program ``pick`` selected."""
    task, system = cell.tasks["TaskControl1"], cell.system
    assert await system.get_ready() == Status.OK
    await wait_until(lambda: system.state == "Ready")
    assert await task.load_by_name("pick") == Status.OK
    return task, system


def test_the_capabilities_are_protocols_the_simulator_does_not_have() -> None:
    controller = Controller()
    for capability in (RobotEquipment, ConfirmedStart, PowerFeedback, AlarmReset, ProgramCatalogue):
        assert isinstance(controller, capability)
    simulator = SimulatedRobot()
    for capability in (ConfirmedStart, PowerFeedback, AlarmReset, ProgramCatalogue):
        assert not isinstance(simulator, capability)


async def test_a_controller_program_loads_by_name_with_no_file(
    rig: tuple[RobotCell, Controller], tmp_path: Path
) -> None:
    cell, controller = rig
    task = cell.tasks["TaskControl1"]
    assert await task.load_by_name("pick") == Status.OK
    assert controller.sent == ["select pick"]
    assert task.state == "Ready" and task.program_name == "pick" and task.program_file is None
    assert task.modules == [] and task._start_check() is not Status.UNRESOLVED_REFERENCE
    assert await task.load_by_name("nothing") == Status.NOT_FOUND  # -1: neither a file nor the controller's
    assert await task.load_by_name("broken") == Status.INVALID_CONTENT  # -2: there and refused
    assert task.program_name == "pick" and controller.selected == "pick"  # a failure changes nothing
    assert await task.load_controller_program("pick") == Status.OK  # LoadByNodeId
    # a file stays possible: it wins over the controller's name, its program is selected by name
    (tmp_path / "pick.robot").write_text("program Pick\nwait 1\n")
    (tmp_path / "other.robot").write_text("program Other\nwait 1\n")
    assert await task.load_by_name("pick") == Status.OK
    assert task.program_file == "pick.robot" and task.program_name == "Pick"
    assert await task.load_by_name("other") == Status.INVALID_CONTENT  # the controller holds no Other


async def test_start_is_executing_only_once_confirmed_and_a_refusal_answers_at_once(
    rig: tuple[RobotCell, Controller],
) -> None:
    cell, controller = rig
    task, system = await ready_with_pick(cell)
    controller.remote = False  # as it reports: Start is not Executable and answers 1, nothing sent
    assert not task.executable("TaskControlStateMachine", "Start")
    assert await task.start() == Status.E_SYSTEM_STATE
    assert await system.start() == Status.E_SYSTEM_STATE
    assert task.state == "Ready" and system.state == "Ready" and "start" not in controller.sent
    assert "would refuse the start: not in remote control" in task.last_error
    controller.remote = True
    assert task.executable("TaskControlStateMachine", "Start")
    controller.refuse_next = True  # refused when asked: 1 at once, nothing changed
    assert await task.start() == Status.E_SYSTEM_STATE
    assert task.state == "Ready" and "refused the start" in task.last_error
    changes: list[Change] = []
    system.machine.listeners.append(changes.append)
    assert await system.start() == Status.OK  # SystemOperation's Start: its task's confirmed start
    assert controller.running.is_set() and task.state == "Executing" and system.state == "Executing"
    assert [(c.to_state, c.reason) for c in changes if c.machine is system.machine] == [("Executing", Reason.EXTERNAL)]
    controller.finish()
    await wait_until(lambda: task.state == "Ready" and task.ready.current == "AtProgramStart")


async def test_drives_that_drop_take_system_operation_to_idle_and_acknowledge_resets(
    rig: tuple[RobotCell, Controller],
) -> None:
    cell, controller = rig
    task, system = await ready_with_pick(cell)
    assert await task.start() == Status.OK
    reasons: list[tuple[str, Reason]] = []
    system.machine.listeners.append(lambda c: reasons.append((c.to_state, c.reason)))
    controller.fault()  # the run ends by the fault, the controller drops its drives
    controller.set_drives(False)
    await wait_until(lambda: task.state == "Ready")
    assert task.ready.current == "Suspended"
    await wait_until(lambda: system.state == "Idle")  # never Ready with the drives off
    assert ("Idle", Reason.ERROR) in reasons
    assert await system.get_ready() == Status.E_ACTIVE_ALARM
    assert await task.start() == Status.E_SYSTEM_STATE
    system.acknowledge("ControllerFault", "checked")
    assert controller.resets == 1 and not system.conditions["ControllerFault"].active
    assert await system.get_ready() == Status.OK
    await wait_until(lambda: system.state == "Ready")
    # drives switched on at the pendant while Idle: Ready, switched off: Idle
    assert await system.stand_down() == Status.OK
    await wait_until(lambda: system.state == "Idle" and not system.powering_down)
    controller.set_drives(True)
    assert system.state == "Ready"
    controller.set_drives(False)
    assert system.state == "Idle"


async def test_stand_down_during_a_fault_reaches_idle(rig: tuple[RobotCell, Controller]) -> None:
    cell, controller = rig
    system = cell.system
    assert await system.get_ready() == Status.OK
    await wait_until(lambda: system.state == "Ready")
    controller.fault()  # drives stay on
    assert system.state == "Ready"
    assert await system.stand_down() == Status.OK
    await wait_until(lambda: system.state == "Idle")
    assert controller.sent[-1] == "drives off"


async def test_a_fault_in_answer_to_start_answers_3(rig: tuple[RobotCell, Controller]) -> None:
    cell, controller = rig
    task, _system = await ready_with_pick(cell)

    async def faulting_begin(task: str, pointer: int, mode: ExecutionMode) -> None:
        raise AlarmStop("fault 9 on start")

    controller.begin = faulting_begin  # type: ignore[method-assign]
    assert await task.start() == Status.E_ACTIVE_ALARM
    assert task.state == "Ready"

    async def broken_begin(task: str, pointer: int, mode: ExecutionMode) -> None:
        raise EquipmentError("no answer")

    controller.begin = broken_begin  # type: ignore[method-assign]
    assert await task.start() == Status.E_UNEXPECTED_ERROR
    assert task.state == "Ready"
