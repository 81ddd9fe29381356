"""The Robotics rules every remote-operation object shares, free of OPC UA and of files: the NodeSet's
names, the Int32 ``Status`` of the Robotics methods, the tables, and the one refusal path (``Guarded``).

``uacell.robotics.model`` builds TaskControl, SystemOperation and the cell on them (and re-exports
them); ``uacell.robotics.loading`` is TaskControl's program loading.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, fields
from enum import IntEnum

from uacell.core.capabilities import reachable
from uacell.core.errors import CallError
from uacell.core.fsm import StateMachine
from uacell.models import FsmTable, TableLoader
from uacell.robotics.equipment import RobotEquipment, StopMode


class Status(IntEnum):
    """Values of the Robotics methods' Int32 ``Status`` output (negative: uacell vendor codes)."""

    OK = 0
    E_SYSTEM_STATE = 1
    E_UNEXPECTED_ERROR = 2
    E_ACTIVE_ALARM = 3
    E_ACKNOWLEDGE_REQUIRED = 4
    NOT_FOUND = -1  # no such program/module file (load), or not loaded (unload)
    INVALID_CONTENT = -2  # the file is not a valid program or module
    UNRESOLVED_REFERENCE = -3  # Start: a used module is not loaded, or a called routine is missing
    MODULE_REFERENCED = -4  # unload of a module the program or another module uses


# --- the NodeSet's names ----------------------------------------------------------------------------
# Machines (BrowseNames of the instance machines) and their states, as OPC 40010-1 names them.
# ``RoboticsTables`` checks every one against the NodeSet when the tables are loaded; transitions are
# never named: they are looked up in the table by cause (method) or by from/to state.
TASK_CONTROL = "TaskControlStateMachine"
READY_SUB = "ReadySubstateMachine"
SYSTEM_OPERATION = "SystemOperationStateMachine"
IDLE_SUB = "IdleSubstateMachine"
EXECUTING_SUB = "ExecutingSubstateMachine"
IDLE, READY, EXECUTING = "Idle", "Ready", "Executing"  # TaskControl and SystemOperation
AT_PROGRAM_START, SUSPENDED = "AtProgramStart", "Suspended"  # ReadySubstateMachineType
STAND_BY, GETTING_READY = "StandBy", "GettingReady"  # IdleSubstateMachineType
RUNNING, STOPPING = "Running", "Stopping"  # ExecutingSubstateMachineType

# Calls that act in a state without taking a transition (docs/decisions.md 11, 15, 16): the one place
# Robotics adds to the NodeSet's HasCause table. Everything else a method may do, the table says.
STAYS: frozenset[tuple[str, str]] = frozenset(
    {
        ("LoadByName", READY),  # 11: replaces the program or adds a module
        ("LoadByNodeId", READY),
        ("UnloadByName", IDLE),  # 15: a module loaded without a program
        ("UnloadByNodeId", IDLE),
        ("ResetToProgramStart", AT_PROGRAM_START),  # 16: Status 0, no transition
    }
)


@dataclass(frozen=True)
class RoboticsTables:
    """The five Robotics state-machine tables, handed to the models by whoever knows the NodeSets."""

    task_control: FsmTable
    ready: FsmTable
    system_operation: FsmTable
    idle: FsmTable
    executing: FsmTable

    @classmethod
    def load(cls, tables: TableLoader) -> RoboticsTables:
        """Read the tables through ``tables`` and check every name this module uses against them."""
        loaded = cls(
            task_control=tables("Robotics", "TaskControlStateMachineType"),
            ready=tables("Robotics", "ReadySubstateMachineType"),
            system_operation=tables("Robotics", "SystemOperationStateMachineType"),
            idle=tables("Robotics", "IdleSubstateMachineType"),
            executing=tables("Robotics", "ExecutingSubstateMachineType"),
        )
        loaded.task_control.check_names((IDLE, READY, EXECUTING))
        loaded.ready.check_names((AT_PROGRAM_START, SUSPENDED))
        loaded.system_operation.check_names((IDLE, READY, EXECUTING))
        loaded.idle.check_names((STAND_BY, GETTING_READY))
        loaded.executing.check_names((RUNNING, STOPPING))
        every = {m for f in fields(cls) for m in getattr(loaded, f.name).methods}
        unknown = sorted({m for m, _ in STAYS} - every)
        if unknown:
            raise LookupError(f"the Robotics NodeSet has no method {', '.join(unknown)}")
        return loaded


# --- observable data -------------------------------------------------------------------------------
@dataclass(frozen=True)
class TaskModule:
    """A module loaded on a task control (TaskModuleType: Name, Version, IsReferenced)."""

    name: str
    version: str
    is_referenced: bool
    relpath: str | None


Listener = Callable[[], None]


def resolve_stop_mode(value: int, possible: Sequence[StopMode], default: StopMode) -> StopMode:
    if value == 0:
        return default
    if value not in [int(m) for m in possible]:
        raise CallError("BadInvalidArgument", f"StopMode {value} is not in PossibleStopModes", argument=0)
    return StopMode(value)


def notify(listeners: Iterable[Listener]) -> None:
    for listener in list(listeners):
        listener()


class Guarded:
    """The one refusal path of a Robotics object (docs/decisions.md 4 and 8).

    A method may act when its machine ``allows`` it (the NodeSet's HasCause table plus ``STAYS``) and
    the method's entry in ``_conditions`` (if any) has no objection. Operations answer the Status this
    returns; ``Executable`` is true exactly when it returns None.
    """

    _machines: dict[str, StateMachine]
    _conditions: dict[str, Callable[[], Status | None]]

    equipment: RobotEquipment

    def _refusal(self, machine_name: str, method: str) -> Status | None:
        """Why ``method`` of machine ``machine_name`` cannot act now (a Status), or None if it can.

        Equipment that says it cannot reach its controller (``reachable`` false, e.g. the gateway's
        drivers) refuses every method with Bad_CommunicationError (a CallError): nothing is tried.
        """
        if not reachable(self.equipment):
            raise CallError("BadCommunicationError", "the robot controller cannot be reached")
        machine = self._machines.get(machine_name)
        if machine is None or method not in machine.table.methods or not machine.allows(method, STAYS):
            return Status.E_SYSTEM_STATE
        condition = self._conditions.get(method)
        return condition() if condition is not None else None

    def executable(self, machine_name: str, method: str) -> bool:
        try:
            return self._refusal(machine_name, method) is None
        except CallError:
            return False

    def methods(self) -> list[tuple[str, str]]:
        """Every (machine name, method) the NodeSet gives this object's machines."""
        return [(name, m) for name, machine in self._machines.items() for m in sorted(machine.table.methods)]
