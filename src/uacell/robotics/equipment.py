"""The interface between uacell's Robotics behaviour and a robot controller (simulated or real).

``RobotEquipment`` has one hook per operation, like the OPC Foundation .NET Robotics server's
``OnLoadByName``/``OnStart`` builders: the state bookkeeping (TaskControl, SystemOperation, Status
values, events) is done once in ``uacell.robotics.model``; an implementation only moves the robot.
``uacell.robotics.sim.SimulatedRobot`` is the built-in one; docs/equipment.md shows a skeleton for a
real controller.

Failures are reported by raising ``EquipmentError`` (or a subclass); the model turns them into the
Status output of the method the client called.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from enum import IntEnum
from typing import Protocol, runtime_checkable

from uacell.core.equipment_spec import EquipmentSpec
from uacell.robotics.program import Program


class ExecutionMode(IntEnum):
    """Robotics ExecutionModeEnumeration."""

    CYCLE = 0  # run the program once
    CONTINUOUS = 1  # restart at the end until stopped
    STEP = 2  # execute one instruction per Start


class StopMode(IntEnum):
    """The NodeSet's default PossibleStopModes."""

    ON_PATH = 1  # brake along the programmed path within a short distance
    END_OF_CYCLE = 2  # finish the current program cycle
    PROCESS_STOP = 3  # finish the current process step (a routine call), then stop
    QUICK_STOP = 4  # stop at once
    END_OF_INSTRUCTION = 5  # finish the current instruction (move or wait)


@dataclass(frozen=True)
class AxisInfo:
    """One axis of a motion device: name, position limits in degrees, maximum speed in degrees/s."""

    name: str
    min_position: float
    max_position: float
    max_speed: float

    @property
    def limits(self) -> tuple[float, float]:
        return (self.min_position, self.max_position)


@dataclass(frozen=True)
class ControllerEquipmentSpec(EquipmentSpec):
    """What a robot controller's factory gets: the part and its settings, and the configured axes of
    the motion device it moves (empty: the equipment's own)."""

    axes: tuple[AxisInfo, ...] = ()


@dataclass(frozen=True)
class AxisState:
    """An axis's actual position (degrees) and speed (degrees/s, signed, 0 when still)."""

    position: float
    speed: float


@dataclass(frozen=True)
class RunOutcome:
    """How a run ended: where the program pointer is, and whether the program reached its end.

    ``completed`` is true when the program ran to its end (CYCLE, the last STEP, or a CONTINUOUS run
    stopped at the end of its cycle); the pointer is then 0.
    """

    pointer: int
    completed: bool


Progress = Callable[[int, int], None]
"""Called by ``run`` when the program pointer moves: (pointer, source line of that instruction)."""

AlarmListener = Callable[[str, bool, str], None]
"""Called by equipment when an alarm changes: (alarm name, active, message)."""


class EquipmentError(Exception):
    """The controller could not do what was asked (the model answers Status 2 E_UnexpectedError)."""


class ProgramRejected(EquipmentError):
    """The controller refused the program or module content (Status -2, invalid content)."""


class NotPowered(EquipmentError):
    """The operation needs drive power and the robot is powered down."""


class AlarmStop(EquipmentError):
    """An alarm stopped the robot while it was running a program."""


@runtime_checkable
class RobotEquipment(Protocol):
    """What the Robotics model asks of a robot controller. ``task`` names the task control.

    All coroutines may take time; ``run`` lasts as long as the program runs. Implementations raise
    ``EquipmentError`` (or a subclass) for failures and must leave their state unchanged then.
    """

    @property
    def axes(self) -> Sequence[AxisInfo]:
        """The axes of the motion device, in order (a program's ``move`` gives one value per axis)."""
        ...

    @property
    def alarm_names(self) -> Sequence[str]:
        """Names of the alarm conditions the controller can raise (fixed for its lifetime)."""
        ...

    def add_alarm_listener(self, listener: AlarmListener) -> None:
        """Call ``listener`` whenever an alarm becomes active or inactive."""
        ...

    def axis_states(self) -> Sequence[AxisState]:
        """The actual position and speed of every axis, now."""
        ...

    async def power_up(self) -> None:
        """Switch drive power on and prepare to move (GetReady). May take seconds."""
        ...

    async def power_down(self) -> None:
        """Switch drive power off (StandDown); also when a GetReady is cancelled."""
        ...

    async def load(self, task: str, program: Program) -> None:
        """Load a parsed program (replacing the task's program; modules stay) or a module."""
        ...

    async def unload(self, task: str, name: str) -> None:
        """Unload the program or module ``name`` from the task."""
        ...

    async def run(self, task: str, pointer: int, mode: ExecutionMode, progress: Progress) -> RunOutcome:
        """Run the task's program from ``pointer`` until it ends, a step is done, or a stop takes effect.

        Returns when the robot is still. Raises ``EquipmentError`` (``AlarmStop``) if it had to stop
        for a fault; the program stays loaded.
        """
        ...

    async def stop(self, task: str, mode: StopMode) -> None:
        """Ask ``task``'s run to stop in ``mode``; returns at once (``run`` ends later).

        The model calls it only while a run is under way, possibly before the ``run`` coroutine has
        executed its first instruction: the request then applies to that run.
        """
        ...


# --- optional capabilities: equipment declares them by implementing the Protocol -------------------
class StartRefused(EquipmentError):
    """The controller refused a confirmed start (remote control off, drives off, no program, ...):
    Start answers Status 1 (E_SystemState) at once and nothing changes."""


class UnknownProgram(EquipmentError):
    """The controller holds no program of that name (Status -1)."""


@runtime_checkable
class ConfirmedStart(Protocol):
    """Equipment whose start the controller confirms (a gateway robot). The model calls ``begin``
    before it shows Executing and calls ``run`` only once ``begin`` returned; ``start_refusal`` makes
    Start not Executable (and answer 1 with nothing sent) while the controller would refuse it."""

    def start_refusal(self) -> str | None:
        """Why the controller would refuse a start now, from what it last reported (remote control
        off, drives off, ...; a fault is a condition already), or None. When it changes, the equipment
        tells its power listeners (``PowerFeedback``), so that Executable follows."""
        ...

    async def begin(self, task: str, pointer: int, mode: ExecutionMode) -> None:
        """Start the task's program and return once the controller confirms it runs. Raise
        ``StartRefused`` when the controller refuses, ``AlarmStop`` for a fault, ``EquipmentError``
        otherwise (or ``uacell.core.errors.CallError`` for a timeout or a lost connection)."""
        ...


@runtime_checkable
class ModeReporting(Protocol):
    """Equipment that reports the controller's operational mode (OPC 40010-1 OperationalModeEnumeration:
    MANUAL_REDUCED_SPEED 1, MANUAL_HIGH_SPEED 2, AUTOMATIC 3, AUTOMATIC_EXTERNAL 4; 0 OTHER), which
    the machine's MachineryOperationMode follows (uacell.machinery)."""

    @property
    def operational_mode(self) -> int: ...


@runtime_checkable
class PowerFeedback(Protocol):
    """Equipment that reports its drive power as the controller sees it. SystemOperation follows:
    drives that go off by themselves (a fault, the pendant) take Ready to Idle (reason Error), drives
    that come on by themselves take Idle/StandBy to Ready (reason System)."""

    def add_power_listener(self, listener: Callable[[bool], None]) -> None:
        """Call ``listener(drives_on)`` whenever the controller's drive power changes (and whenever
        ``ConfirmedStart.start_refusal`` changes)."""
        ...


@runtime_checkable
class AlarmReset(Protocol):
    """Equipment that resets a latched alarm when a client acknowledges its condition (the gateway's
    ``reset`` handshake)."""

    def alarm_acknowledged(self, name: str) -> None:
        """The condition ``name`` was acknowledged; returns at once (the reset runs in the background)."""
        ...


@runtime_checkable
class ProgramCatalogue(Protocol):
    """Equipment whose controller keeps its own programs (a gateway robot): LoadByName and LoadByNodeId
    select them by name with no file in ``Programs`` (docs/robotics.md, "Programs on the controller")."""

    def program_names(self) -> Sequence[str]:
        """The programs the controller holds, as LoadByName takes them (configured and reported)."""
        ...

    def find_program(self, name: str) -> str | None:
        """The controller's name of the program ``name`` names, or None if it holds none."""
        ...

    async def select(self, task: str, name: str) -> None:
        """Select the program ``name`` (from ``find_program``) on the controller for ``task``; raise
        ``UnknownProgram`` when the controller does not know it, ``EquipmentError`` otherwise."""
        ...


@dataclass(frozen=True)
class SafetyReport:
    """The robot's safety state as its controller reports it (OPC 40010-1 SafetyStateType ParameterSet):
    ``operational_mode`` an OperationalModeEnumeration value (OTHER 0, MANUAL_REDUCED_SPEED 1,
    MANUAL_HIGH_SPEED 2, AUTOMATIC 3, AUTOMATIC_EXTERNAL 4)."""

    operational_mode: int
    emergency_stop: bool
    protective_stop: bool


@runtime_checkable
class SafetyFeedback(Protocol):
    """Equipment that reports the robot's safety state; the binding writes it to the robot's
    ``SafetyStates/<first>/ParameterSet`` (OperationalMode, EmergencyStop, ProtectiveStop)."""

    def safety_report(self) -> SafetyReport | None:
        """The safety state now; None while it is not known (the controller not read yet)."""
        ...

    def add_safety_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` whenever ``safety_report`` changes."""
        ...


@runtime_checkable
class AxisFeed(Protocol):
    """Equipment that reads its axes from the controller: the binding publishes ``axis_states()`` when
    the equipment says they changed, instead of sampling them every 0.1 s."""

    def add_axis_listener(self, listener: Callable[[], None]) -> None:
        """Call ``listener()`` after every read of the axes that changed a position or speed."""
        ...
