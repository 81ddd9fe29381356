"""OPC 40010-1 remote operation, free of OPC UA: TaskControl, SystemOperation and the cell wiring them.

The rules are docs/decisions.md 8-21 (docs/robotics.md is the client's view of them). State lives
only in ``uacell.core.fsm.StateMachine`` objects built from the NodeSet tables; the OPC UA binding
listens to them and to ``listeners`` (called after any other observable change) and publishes.
Operations return the Int32 ``Status`` of the Robotics methods, or raise ``CallError`` for Bad codes.
The shared rules (names, Status, the refusal path) are ``uacell.robotics.rules``; loading programs is
``uacell.robotics.loading``. This module reads no file: programs come from the ``ProgramLibrary``
the composer hands in (``uacell.robotics.program_cache`` for files).
"""

from __future__ import annotations

import asyncio
import contextvars
import logging
from collections.abc import Callable, Sequence

from uacell.core.background import Background
from uacell.core.capabilities import has
from uacell.core.conditions import ConditionSet
from uacell.core.errors import CallError
from uacell.core.fsm import Reason, StateMachine
from uacell.robotics.equipment import (
    AlarmReset,
    AlarmStop,
    ConfirmedStart,
    EquipmentError,
    ExecutionMode,
    PowerFeedback,
    RobotEquipment,
    RunOutcome,
    StartRefused,
    StopMode,
)
from uacell.robotics.loading import ParsedPrograms, ProgramLibrary, ProgramLoading
from uacell.robotics.program import (
    DEFAULT_LIMITS,
    NothingToExecute,
    Program,
    ProgramError,
    ProgramLimits,
    ProgramTooLarge,
    measure,
)
from uacell.robotics.rules import (
    AT_PROGRAM_START,
    EXECUTING,
    EXECUTING_SUB,
    GETTING_READY,
    IDLE,
    IDLE_SUB,
    READY,
    READY_SUB,
    RUNNING,
    STAND_BY,
    STAYS,
    STOPPING,
    SUSPENDED,
    SYSTEM_OPERATION,
    TASK_CONTROL,
    Guarded,
    Listener,
    RoboticsTables,
    Status,
    TaskModule,
    notify,
    resolve_stop_mode,
)

__all__ = [  # what other modules import from here, wherever it is defined
    "AT_PROGRAM_START", "EXECUTING", "EXECUTING_SUB", "GETTING_READY", "IDLE", "IDLE_SUB", "READY",
    "READY_SUB", "RUNNING", "STAND_BY", "STAYS", "STOPPING", "SUSPENDED", "SYSTEM_OPERATION",
    "TASK_CONTROL", "Listener", "ProgramLibrary", "RobotCell", "RoboticsTables", "Status",
    "SystemOperation", "TaskControl", "TaskModule",
]  # fmt: skip

log = logging.getLogger(__name__)
_UNKNOWN = object()


# --- TaskControl -----------------------------------------------------------------------------------
class TaskControl(ProgramLoading):
    """One task control: loads programs and modules (``ProgramLoading``), runs them on the equipment
    (TaskControlStateMachine)."""

    def __init__(
        self,
        name: str,
        equipment: RobotEquipment,
        library: ProgramLibrary,
        *,
        tables: RoboticsTables,
        system: SystemOperation | None = None,
        motion_devices: Sequence[str] = ("Arm1",),
        possible_stop_modes: Sequence[StopMode] = tuple(StopMode),
        default_stop_mode: StopMode = StopMode.ON_PATH,
        execution_mode: ExecutionMode = ExecutionMode.CYCLE,
        bounds: ProgramLimits = DEFAULT_LIMITS,
    ) -> None:
        self.name = name
        self.equipment = equipment
        self.library = library
        self.bounds = bounds
        self._parsed = ParsedPrograms()
        self.system = system
        self.motion_devices = tuple(motion_devices)
        self.possible_stop_modes = tuple(possible_stop_modes)
        self.default_stop_mode = default_stop_mode
        self.execution_mode = execution_mode
        self.machine = StateMachine(TASK_CONTROL, tables.task_control, IDLE)
        self.ready = StateMachine(READY_SUB, tables.ready, AT_PROGRAM_START, parent=self.machine, parent_state=READY)
        self._machines = {m.name: m for m in self.machine.walk()}
        # What a method needs beyond the table (None: nothing more, else the Status to answer).
        self._conditions: dict[str, Callable[[], Status | None]] = {
            "Start": self._start_conditions,
            "Stop": lambda: Status.E_SYSTEM_STATE if self.stopping else None,
            "UnloadByName": self._something_loaded,
            "UnloadByNodeId": self._something_loaded,
        }
        self.program: Program | None = None
        self.program_file: str | None = None
        self.on_controller = False  # the program is the controller's own (no file, no text)
        self._modules: dict[str, tuple[Program, str | None]] = {}
        self.pointer = 0  # index of the next step to execute
        self.current_line = 0  # source line of the instruction being executed (0: none)
        self.last_error = ""  # why the last operation failed, for logs and diagnostics
        self.stopping = False
        self._stop_context: contextvars.Context | None = None  # the Stop call that is stopping the run
        self.listeners: list[Listener] = []
        self._lock = asyncio.Lock()
        self._bg = Background()
        self._run: asyncio.Task[None] | None = None
        self._resolution: object = _UNKNOWN
        if system is not None:
            system.add_task(self)

    def __repr__(self) -> str:
        return f"<TaskControl {self.name} {self.machine.current} {self.program_name!r}>"

    # observable data
    @property
    def program_name(self) -> str:
        return self.program.name if self.program else ""

    @property
    def program_loaded(self) -> bool:
        return self.program is not None

    @property
    def state(self) -> str:
        return self.machine.current

    @property
    def executing(self) -> bool:
        return self.machine.current == EXECUTING

    def machines(self) -> list[StateMachine]:
        return self.machine.walk()

    def _changed(self) -> None:
        self._resolution = _UNKNOWN
        notify(self.listeners)
        if self.system is not None:
            self.system._changed()

    # running
    def _start_check(self) -> Status | None:
        """Why Start would fail now (None: it can succeed)."""
        return self._refusal(TASK_CONTROL, "Start")

    def _start_conditions(self) -> Status | None:
        if self.program is None or self._lock.locked():
            return Status.E_SYSTEM_STATE
        if self.system is not None:
            if not self.system.allows_task_start():
                return Status.E_SYSTEM_STATE
            alarm = self.system.alarm_status()
            if alarm is not None:
                return alarm
        if has(self.equipment, ConfirmedStart) and self.equipment.start_refusal() is not None:
            return Status.E_SYSTEM_STATE  # the controller would refuse it: nothing is sent
        problem = self._unresolved()
        if isinstance(problem, ProgramTooLarge | NothingToExecute):
            return Status.INVALID_CONTENT
        if problem is not None:
            return Status.UNRESOLVED_REFERENCE
        return None

    def _unresolved(self) -> ProgramError | None:
        """Why the program's calls do not resolve against the loaded modules (cached per load/unload)."""
        if self._resolution is _UNKNOWN:
            self._resolution = None
            if self.program is not None and not self.on_controller:
                try:
                    measure(self.program, {n: m for n, (m, _) in self._modules.items()}, self.bounds)
                except ProgramError as e:
                    self._resolution = e
        return self._resolution  # type: ignore[return-value]

    async def start(self) -> int:
        """Start: Ready -> Executing, from the program start or where it was suspended; on equipment
        that confirms starts (``ConfirmedStart``) once the controller confirmed it."""
        if has(self.equipment, ConfirmedStart):
            return await self._start_confirmed(Reason.EXTERNAL)
        return self._start(Reason.EXTERNAL)

    async def _start_confirmed(self, reason: Reason) -> int:
        """Start on a controller that confirms it: Executing once it runs; a refusal answers at once
        (StartRefused: 1, a fault: 3, another failure: 2) and changes nothing. Loads wait meanwhile,
        a second Start answers 1."""
        assert has(self.equipment, ConfirmedStart)
        if (problem := self._start_problem()) is not None:
            return problem
        async with self._lock:
            try:
                await self.equipment.begin(self.name, self.pointer, self.execution_mode)
            except StartRefused as e:
                return self._fail(Status.E_SYSTEM_STATE, f"the controller refused the start: {e}")
            except AlarmStop as e:
                return self._fail(Status.E_ACTIVE_ALARM, f"the controller refused the start: {e}")
            except EquipmentError as e:
                return self._fail(Status.E_UNEXPECTED_ERROR, f"the controller did not start: {e}")
            return self._go(reason)

    def _start_problem(self) -> Status | None:
        problem = self._start_check()
        if problem is not None:
            if problem in (Status.UNRESOLVED_REFERENCE, Status.INVALID_CONTENT):
                return Status(self._fail(problem, str(self._unresolved())))
            refusal = self.equipment.start_refusal() if has(self.equipment, ConfirmedStart) else None
            why = f"the controller would refuse the start: {refusal}" if refusal else f"cannot start in {self.state}"
            return Status(self._fail(problem, why))
        return None

    def _start(self, reason: Reason) -> int:
        if (problem := self._start_problem()) is not None:
            return problem
        return self._go(reason)

    def _go(self, reason: Reason) -> int:
        self.stopping = False
        self._stop_context = None
        self.machine.move(EXECUTING, reason)
        mode = self.execution_mode
        log.info("%s: started %s at step %d (%s)", self.name, self.program_name, self.pointer, mode.name)
        self._run = self._bg.spawn(self._execute(self.pointer, self.execution_mode))
        if self.system is not None:
            self.system._task_started(self)
        self._changed()
        return Status.OK

    async def _execute(self, pointer: int, mode: ExecutionMode) -> None:
        reason: Reason
        try:
            outcome = await self.equipment.run(self.name, pointer, mode, self._progress)
        except asyncio.CancelledError:
            raise
        except Exception as e:  # EquipmentError or a bug: the program stays loaded, the robot is still
            if not isinstance(e, EquipmentError):
                log.exception("%s: run failed", self.name)
            self.last_error = f"run ended by a fault: {e}"
            log.warning("%s: %s", self.name, self.last_error)
            outcome, reason = RunOutcome(self.pointer, False), Reason.ERROR
        else:
            if self.stopping:
                reason = Reason.EXTERNAL
            elif outcome.completed:
                reason = Reason.APPLICATION
            else:
                reason = Reason.SYSTEM  # a STEP done, or the controller stopped by itself
        stop, self._stop_context = self._stop_context, None
        if stop is not None and self.stopping:
            stop.run(self._finish, outcome, reason)  # in the Stop call's context: its audit event
        else:
            self._finish(outcome, reason)

    def _progress(self, pointer: int, line: int) -> None:
        self.pointer, self.current_line = pointer, line
        notify(self.listeners)

    def _finish(self, outcome: RunOutcome, reason: Reason) -> None:
        stopped = self.stopping
        self.stopping = False
        self.pointer, self.current_line = outcome.pointer, 0
        self.machine.move(READY, reason)
        # Decision 16: after Stop, Suspended; after the program ended by itself, AtProgramStart.
        at_start = outcome.completed and not stopped and reason != Reason.ERROR
        self.ready.enter(AT_PROGRAM_START if at_start else SUSPENDED, reason)
        log.info("%s: %s is Ready (%s, step %d)", self.name, self.program_name, reason.name, self.pointer)
        if self.system is not None:
            self.system._task_finished(self, reason)
        self._changed()

    async def stop(self, stop_mode: int) -> int:
        """Stop: accepted at once (Status 0); ExecutingToReady follows when the robot has stopped."""
        mode = resolve_stop_mode(stop_mode, self.possible_stop_modes, self.default_stop_mode)
        return await self._stop(mode)

    async def _stop(self, mode: StopMode, system_reason: Reason = Reason.SYSTEM) -> int:
        if (problem := self._refusal(TASK_CONTROL, "Stop")) is not None:
            return problem
        self.stopping = True
        try:
            await self.equipment.stop(self.name, mode)
        except EquipmentError as e:
            self.stopping = False
            return self._fail(Status.E_UNEXPECTED_ERROR, f"controller could not stop: {e}")
        log.info("%s: stopping (%s)", self.name, mode.name)
        # ExecutingToReady follows once the robot has stopped: the caller's (decision 38).
        self._stop_context = contextvars.copy_context()
        if self.system is not None and self.executing:  # the run may have ended while the stop was asked
            self.system._task_stopping(system_reason)
        self._changed()
        return Status.OK

    async def reset_to_program_start(self) -> int:
        """ResetToProgramStart: in Ready, move the program pointer to the start."""
        if (problem := self._refusal(READY_SUB, "ResetToProgramStart")) is not None:
            return problem
        self.pointer, self.current_line = 0, 0
        if self.ready.current == SUSPENDED:
            self.ready.move(AT_PROGRAM_START, Reason.EXTERNAL)
            self._changed()
        return Status.OK

    async def set_execution_mode(self, mode: int) -> int:
        """Change ExecutionMode (CYCLE 0, CONTINUOUS 1, STEP 2); not while Executing."""
        if mode not in [int(m) for m in ExecutionMode]:
            raise CallError("BadInvalidArgument", f"ExecutionMode {mode} is unknown", argument=0)
        if self.machine.current == EXECUTING:
            return Status.E_SYSTEM_STATE
        self.execution_mode = ExecutionMode(mode)
        self._changed()
        return Status.OK

    async def wait_until_not_executing(self) -> None:
        """Wait for a running program (if any) to end and the machine to leave Executing."""
        if self._run is not None:
            await asyncio.wait({self._run})

    async def close(self) -> None:
        await self._bg.close()


# --- SystemOperation -------------------------------------------------------------------------------
class SystemOperation(Guarded, ConditionSet):
    """The robot system's power state and alarms (SystemOperationStateMachine), coupled to task controls;
    its conditions are SystemOperation/Conditions (decision 18)."""

    def __init__(
        self,
        equipment: RobotEquipment,
        *,
        tables: RoboticsTables,
        possible_stop_modes: Sequence[StopMode] = tuple(StopMode),
        default_stop_mode: StopMode = StopMode.ON_PATH,
    ) -> None:
        self.equipment = equipment
        self.possible_stop_modes = tuple(possible_stop_modes)
        self.default_stop_mode = default_stop_mode
        self.machine = StateMachine(SYSTEM_OPERATION, tables.system_operation, IDLE)
        self.idle = StateMachine(IDLE_SUB, tables.idle, STAND_BY, parent=self.machine, parent_state=IDLE)
        self.executing = StateMachine(
            EXECUTING_SUB, tables.executing, RUNNING, parent=self.machine, parent_state=EXECUTING
        )
        self._machines = {m.name: m for m in self.machine.walk()}
        # What a method needs beyond the table (None: nothing more, else the Status to answer).
        self._conditions: dict[str, Callable[[], Status | None]] = {
            "GetReady": self._get_ready_conditions,
            "StandDown": self._stand_down_conditions,
            "Start": self._start_conditions,
            "Stop": lambda: None if self.executing.is_in(RUNNING) else Status.E_SYSTEM_STATE,
        }
        self.tasks: list[TaskControl] = []
        ConditionSet.__init__(self, equipment.alarm_names)
        self.listeners: list[Listener] = []
        self.powering_down = False
        self.last_error = ""
        self._stop_requested = False
        self._getting_ready: asyncio.Task[None] | None = None
        self._bg = Background()
        self._external_start = False  # a SystemOperation Start is starting its tasks (confirmed starts)
        self.drives_on: bool | None = None  # the controller's drive power, for PowerFeedback equipment
        equipment.add_alarm_listener(self._on_alarm)
        if has(equipment, PowerFeedback):
            equipment.add_power_listener(self._on_power)

    def __repr__(self) -> str:
        return f"<SystemOperation {self.machine.current}>"

    def add_task(self, task: TaskControl) -> None:
        if task not in self.tasks:
            self.tasks.append(task)
            task.system = self

    @property
    def state(self) -> str:
        return self.machine.current

    def machines(self) -> list[StateMachine]:
        return self.machine.walk()

    def _changed(self) -> None:
        notify(self.listeners)

    # conditions (decision 18)
    def alarm_status(self) -> Status | None:
        """E_ActiveAlarm if a condition is active, E_AcknowledgeRequired if one awaits acknowledging."""
        enabled = [c for c in self.conditions.values() if c.enabled]
        if any(c.active for c in enabled):
            return Status.E_ACTIVE_ALARM
        if any(not c.acked for c in enabled):
            return Status.E_ACKNOWLEDGE_REQUIRED
        return None

    def _on_alarm(self, name: str, active: bool, message: str) -> None:
        self.alarm(name, active, message)

    def acknowledge(self, name: str, comment: str = "") -> None:
        """The condition's Acknowledge; equipment that resets alarms (``AlarmReset``) is told."""
        super().acknowledge(name, comment)
        if has(self.equipment, AlarmReset):
            self.equipment.alarm_acknowledged(name)

    def _on_power(self, on: bool) -> None:
        """The controller's drive power changed (``PowerFeedback``): the power state follows, so that
        SystemOperation is never Ready with the drives off nor Idle/StandBy with them on."""
        self.drives_on = on
        self._follow_power()
        self._changed()  # what a start needs may have changed with it: Executable is evaluated again

    def _follow_power(self) -> None:
        if self.drives_on is None or self.powering_down or self._getting_ready is not None:
            return  # a GetReady or StandDown under way completes the transition itself
        if not self.drives_on and self.machine.current == READY:
            self.last_error = "the controller switched the drives off"
            log.warning("%s", self.last_error)
            self.machine.move(IDLE, Reason.ERROR)
            self.idle.enter(STAND_BY, Reason.ERROR)
            self._changed()
        elif self.drives_on and self.idle.is_in(STAND_BY):
            self.machine.move(READY, Reason.SYSTEM)
            self._changed()

    def conditions_changed(self) -> None:
        self._changed()

    # coupling with task controls (decision 19)
    def allows_task_start(self) -> bool:
        m = self.machine
        return not self.powering_down and (m.current == READY or self.executing.is_in(RUNNING))

    def _task_started(self, task: TaskControl) -> None:
        if self.machine.current == READY:
            self._stop_requested = False
            reason = Reason.EXTERNAL if self._external_start else Reason.SYSTEM
            self.machine.move(EXECUTING, reason)
            self.executing.enter(RUNNING, reason)
            self._changed()

    def _task_stopping(self, reason: Reason = Reason.SYSTEM) -> None:
        # The system is Stopping once every executing task is on its way to a stop.
        if self.executing.is_in(RUNNING) and all(t.stopping for t in self.tasks if t.executing):
            self.executing.move(STOPPING, reason)
            self._changed()

    def _task_finished(self, task: TaskControl, reason: Reason) -> None:
        if self.machine.current != EXECUTING or any(t.executing for t in self.tasks):
            return
        if self._stop_requested:
            reason = Reason.EXTERNAL
        elif reason == Reason.EXTERNAL:  # a task-control Stop: for the system it is a consequence
            reason = Reason.SYSTEM
        self._stop_requested = False
        self.machine.move(READY, reason)
        self._changed()
        self._follow_power()  # the drives went off during the run (a fault): Idle

    def _get_ready_conditions(self) -> Status | None:
        if not self.idle.is_in(STAND_BY) or self.powering_down:
            return Status.E_SYSTEM_STATE
        return self.alarm_status()

    def _stand_down_conditions(self) -> Status | None:
        # In Idle StandDown cancels GettingReady; in Ready it powers down (once).
        if self.idle.is_in(GETTING_READY) or (self.machine.current == READY and not self.powering_down):
            return None
        return Status.E_SYSTEM_STATE

    # methods
    async def get_ready(self) -> int:
        """GetReady: Idle -> (GettingReady) -> Ready once drive power is up. Returns when accepted."""
        if (problem := self._refusal(SYSTEM_OPERATION, "GetReady")) is not None:
            return problem
        self.idle.move(GETTING_READY, Reason.EXTERNAL)
        # Ready follows once the drives are on: the call's completion, the caller's (decision 38).
        self._getting_ready = self._bg.spawn(self._power_up(), context=contextvars.copy_context())
        self._changed()
        return Status.OK

    async def _power_up(self) -> None:
        try:
            await self.equipment.power_up()
        except asyncio.CancelledError:
            raise
        except Exception as e:
            if not isinstance(e, EquipmentError):
                log.exception("power up failed")
            self.last_error = f"getting ready failed: {e}"
            log.warning("%s", self.last_error)
            self._getting_ready = None
            self.idle.move(STAND_BY, Reason.ERROR)
            self.machine.move(IDLE, Reason.ERROR)
            self._changed()
            return
        self._getting_ready = None
        self.machine.move(READY, Reason.EXTERNAL)
        self._changed()

    async def stand_down(self) -> int:
        """StandDown: Ready -> Idle (drive power off), or cancel GettingReady (IdleToIdle)."""
        if (problem := self._refusal(SYSTEM_OPERATION, "StandDown")) is not None:
            return problem
        if self.idle.is_in(GETTING_READY):
            if self._getting_ready is not None:
                self._getting_ready.cancel()
                self._getting_ready = None
            self.idle.move(STAND_BY, Reason.EXTERNAL)
            self.machine.move(IDLE, Reason.EXTERNAL)
            # Until the drives are off again a GetReady would race the power-down: it answers 1.
            self.powering_down = True
            self._bg.spawn(self._power_down(transition=False))
            self._changed()
            return Status.OK
        self.powering_down = True
        # ReadyToIdle follows once the drives are off: the call's completion, the caller's (decision 38).
        self._bg.spawn(self._power_down(transition=True), context=contextvars.copy_context())
        self._changed()
        return Status.OK

    async def _power_down(self, transition: bool) -> None:
        try:
            await self.equipment.power_down()
        except asyncio.CancelledError:
            raise
        except Exception as e:
            if not isinstance(e, EquipmentError):
                log.exception("power down failed")
            self.last_error = f"standing down failed: {e}"
            log.warning("%s", self.last_error)
            self.powering_down = False
            self._changed()
            return
        self.powering_down = False
        if transition and self.machine.current == READY:
            self.machine.move(IDLE, Reason.EXTERNAL)
            self.idle.enter(STAND_BY, Reason.EXTERNAL)
        self._changed()

    def _start_check(self) -> Status | None:
        return self._refusal(SYSTEM_OPERATION, "Start")

    def _start_conditions(self) -> Status | None:
        if self.powering_down:
            return Status.E_SYSTEM_STATE
        alarm = self.alarm_status()
        if alarm is not None:
            return alarm
        problems = [t._start_check() for t in self.tasks if t.machine.current == READY and t.program]
        if not problems:
            return Status.E_SYSTEM_STATE  # nothing to start: the system cannot be Executing without a task
        if all(p is not None for p in problems):
            return problems[0]
        return None

    async def start(self) -> int:
        """Start: starts every task control that is Ready with a program; Ready -> Executing."""
        problem = self._start_check()
        if problem is not None:
            return problem
        if has(self.equipment, ConfirmedStart):
            return await self._start_confirmed()
        self._stop_requested = False
        self.machine.move(EXECUTING, Reason.EXTERNAL)
        self.executing.enter(RUNNING, Reason.EXTERNAL)
        for task in self.tasks:
            if task.machine.current == READY and task._start_check() is None:
                task._start(Reason.SYSTEM)
        self._changed()
        return Status.OK

    async def _start_confirmed(self) -> int:
        """Start each task that can on a controller that confirms starts: ReadyToExecuting (reason 1)
        with the first it confirms; when it confirms none, the first refusal's answer."""
        answers: list[int] = []
        failure: CallError | None = None
        self._external_start = True
        try:
            for task in list(self.tasks):
                if task.machine.current == READY and task._start_check() is None:
                    try:
                        answers.append(await task._start_confirmed(Reason.SYSTEM))
                    except CallError as e:  # Bad_Timeout, Bad_CommunicationError: answered if none started
                        failure = failure or e
        finally:
            self._external_start = False
        if Status.OK in answers:
            return Status.OK
        if failure is not None:
            raise failure
        return answers[0] if answers else Status.E_SYSTEM_STATE

    async def stop(self, stop_mode: int) -> int:
        """Stop: stops every executing task control; ExecutingToReady when all have stopped."""
        mode = resolve_stop_mode(stop_mode, self.possible_stop_modes, self.default_stop_mode)
        if (problem := self._refusal(SYSTEM_OPERATION, "Stop")) is not None:
            return problem
        self._stop_requested = True
        failed = []
        for task in list(self.tasks):
            if task.executing and not task.stopping:
                # The last task to accept takes RunningToStopping (reason External, see _task_stopping).
                status = await task._stop(mode, Reason.EXTERNAL)
                if status != Status.OK:
                    log.warning("system stop: %s answered %d", task.name, status)
                    failed.append(task.name)
        if failed:
            # A task that keeps running keeps the system Running (no transition leaves Stopping).
            self._stop_requested = False
            self.last_error = f"stop refused by {', '.join(failed)}"
            return Status.E_UNEXPECTED_ERROR
        return Status.OK

    async def close(self) -> None:
        await self._bg.close()


# --- the cell ---------------------------------------------------------------------------------------
class RobotCell:
    """A controller: SystemOperation, its task controls, the equipment and the program library."""

    def __init__(
        self,
        equipment: RobotEquipment,
        library: ProgramLibrary,
        *,
        tables: RoboticsTables,
        task_names: Sequence[str] = ("TaskControl1",),
        motion_devices: Sequence[str] = ("Arm1",),
        possible_stop_modes: Sequence[StopMode] = tuple(StopMode),
        default_stop_mode: StopMode = StopMode.ON_PATH,
        bounds: ProgramLimits = DEFAULT_LIMITS,
    ) -> None:
        if default_stop_mode not in possible_stop_modes:
            raise ValueError("the default stop mode must be one of the possible stop modes")
        self.equipment = equipment
        self.library = library
        self.system = SystemOperation(
            equipment, tables=tables, possible_stop_modes=possible_stop_modes, default_stop_mode=default_stop_mode
        )
        self.tasks: dict[str, TaskControl] = {
            name: TaskControl(
                name,
                equipment,
                library,
                tables=tables,
                system=self.system,
                motion_devices=motion_devices,
                possible_stop_modes=possible_stop_modes,
                default_stop_mode=default_stop_mode,
                bounds=bounds,
            )
            for name in task_names
        }

    def machines(self) -> list[StateMachine]:
        return self.system.machines() + [m for t in self.tasks.values() for m in t.machines()]

    def add_listener(self, listener: Listener) -> None:
        """Call ``listener`` after any change (state, data, executability) anywhere in the cell."""
        self.system.listeners.append(listener)
        for machine in self.machines():
            machine.listeners.append(lambda _change: listener())

    async def close(self) -> None:
        for task in self.tasks.values():
            await task.close()
        await self.system.close()
