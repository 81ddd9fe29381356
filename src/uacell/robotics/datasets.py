"""What history keeps, PubSub and Sparkplug publish of a robot's parts, and the commands they take
(``Companion.datasets``, uacell.core.datasets)."""

from __future__ import annotations

from uacell.core.datasets import SPEED, STATE, Item, Kind, PartDataSet

# A robot's own kinds of value (``uacell.core.datasets.Kind`` is open).
POSITION = Kind("position", optional=True)  # axis positions: many changes; only with axis_positions
PROGRAM = Kind("program")  # which program runs, where it is

_SYSTEM = "SystemOperation/SystemOperationStateMachine"
_TASK = "TaskControlOperation/TaskControlStateMachine"

ROBOT_CONTROLLER = PartDataSet(
    role="controller",
    values=(Item(f"{_SYSTEM}/CurrentState", STATE),),
    # "": the controller itself, which its alarms (Conditions) are fired through
    notifiers=("", _SYSTEM),
    device=True,  # with its task controls and its robot's motion devices
    commands=(("GetReady", ((_SYSTEM, "GetReady"),)), ("StandDown", ((_SYSTEM, "StandDown"),))),
)

ROBOT_TASK_CONTROL = PartDataSet(
    role="task_control",
    values=(
        Item(f"{_TASK}/CurrentState", STATE),
        Item("ParameterSet/TaskProgramName", PROGRAM),
        Item("ParameterSet/ProgramPointer", PROGRAM),
        Item("ParameterSet/CurrentLine", PROGRAM),  # uacell's own: the program's source line
        Item("ParameterSet/TaskProgramLoaded", PROGRAM),
    ),
    notifiers=(_TASK,),
    commands=(
        ("LoadByName", ((_TASK, "LoadByName"),)),
        ("UnloadProgram", ((_TASK, "UnloadProgram"),)),
        ("Start", ((_TASK, "Start"),)),
        ("Stop", ((_TASK, "Stop"),)),
    ),
)

ROBOT_MOTION_DEVICE = PartDataSet(
    role="motion_device",
    values=(
        Item("ParameterSet/SpeedOverride", SPEED),
        Item("Axes/*/ParameterSet/ActualPosition", POSITION),
    ),
    notifiers=(),
)


DATASETS = (ROBOT_CONTROLLER, ROBOT_TASK_CONTROL, ROBOT_MOTION_DEVICE)
