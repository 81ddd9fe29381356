"""Which values and events of a part matter: the one declaration history and PubSub both read.

Per part role (``uacell.cell.Part.role``), the variables below the part (BrowseName paths, "/"
separated, ``*`` one child of any name) with what they are, and the notifiers below the part whose
events matter (state machines: their TransitionEvents and AuditUpdateStateEvents; a robot
controller's alarms, fired through the controller; history also keeps the Server object's events as
a whole). Pure: resolving a path to a node is the
reader's (``resolve`` takes a child lookup).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import Enum
from typing import TypeVar

N = TypeVar("N")


class Kind(Enum):
    STATE = "state"  # a state machine's CurrentState or a mode
    COUNTER = "counter"  # counts of products
    SPEED = "speed"  # machine speeds, overrides
    POSITION = "position"  # axis positions: many changes; only with [history] axis_positions
    PROGRAM = "program"  # which program runs, where it is
    OEE = "oee"  # OEE figures (uacell's namespace, docs/packml.md)
    ALARM = "alarm"  # a unit's stop reason and alarm list


@dataclass(frozen=True)
class Item:
    path: str
    kind: Kind

    @property
    def optional(self) -> bool:
        """Kept only when configured (axis positions change with every move)."""
        return self.kind is Kind.POSITION


@dataclass(frozen=True)
class PartDataSet:
    role: str  # the part role it applies to
    values: tuple[Item, ...]
    notifiers: tuple[str, ...]  # state machines below the part whose events matter


_PACKML_MACHINES = (
    "BaseStateMachine",
    "BaseStateMachine/MachineState",
    "BaseStateMachine/MachineState/ExecuteState",
)

PACKML_UNIT = PartDataSet(
    role="packml_unit",
    values=(
        *(Item(f"{m}/CurrentState", Kind.STATE) for m in _PACKML_MACHINES),
        Item("Status/UnitModeCurrent", Kind.STATE),
        Item("Status/EquipmentBlocked", Kind.STATE),
        Item("Status/EquipmentStarved", Kind.STATE),
        Item("Status/MachSpeed", Kind.SPEED),
        Item("Status/CurMachSpeed", Kind.SPEED),
        Item("Admin/ProdProcessedCount", Kind.COUNTER),
        Item("Admin/ProdDefectiveCount", Kind.COUNTER),
        Item("Admin/ProdConsumedCount", Kind.COUNTER),
        Item("Admin/StopReason", Kind.ALARM),
        Item("Admin/Alarm", Kind.ALARM),
        Item("OEE/Availability", Kind.OEE),
        Item("OEE/Performance", Kind.OEE),
        Item("OEE/Quality", Kind.OEE),
        Item("OEE/OEE", Kind.OEE),
        Item("OEE/ProcessedCount", Kind.OEE),
        Item("OEE/GoodCount", Kind.OEE),
    ),
    notifiers=_PACKML_MACHINES,
)

ROBOT_CONTROLLER = PartDataSet(
    role="controller",
    values=(Item("SystemOperation/SystemOperationStateMachine/CurrentState", Kind.STATE),),
    # "": the controller itself, which its alarms (Conditions) are fired through
    notifiers=("", "SystemOperation/SystemOperationStateMachine"),
)

ROBOT_TASK_CONTROL = PartDataSet(
    role="task_control",
    values=(
        Item("TaskControlOperation/TaskControlStateMachine/CurrentState", Kind.STATE),
        Item("ParameterSet/TaskProgramName", Kind.PROGRAM),
        Item("ParameterSet/ProgramPointer", Kind.PROGRAM),
        Item("ParameterSet/CurrentLine", Kind.PROGRAM),  # uacell's own: the program's source line
        Item("ParameterSet/TaskProgramLoaded", Kind.PROGRAM),
    ),
    notifiers=("TaskControlOperation/TaskControlStateMachine",),
)

ROBOT_MOTION_DEVICE = PartDataSet(
    role="motion_device",
    values=(
        Item("ParameterSet/SpeedOverride", Kind.SPEED),
        Item("Axes/*/ParameterSet/ActualPosition", Kind.POSITION),
    ),
    notifiers=(),
)

DATASETS: tuple[PartDataSet, ...] = (PACKML_UNIT, ROBOT_CONTROLLER, ROBOT_TASK_CONTROL, ROBOT_MOTION_DEVICE)


def dataset_of(role: str) -> PartDataSet | None:
    return next((d for d in DATASETS if d.role == role), None)


def resolve(path: str, children: Callable[[N], list[tuple[str, N]]], root: N) -> Iterator[tuple[str, N]]:
    """Every node ``path`` names below ``root``: (the path with ``*`` filled in, the node's key).

    ``children(node)`` lists a node's children as (BrowseName, node); a missing name yields nothing;
    ``""`` is ``root`` itself.
    """
    if not path:
        yield "", root
        return

    def walk(node: N, names: list[str], done: list[str]) -> Iterator[tuple[str, N]]:
        if not names:
            yield "/".join(done), node
            return
        head, rest = names[0], names[1:]
        for name, child in children(node):
            if head == "*" or name == head:
                yield from walk(child, rest, [*done, name])

    yield from walk(root, path.split("/"), [])
