"""What history keeps, PubSub and Sparkplug publish of a robot's parts, and the commands they take
(``Companion.datasets``, uacell.datasets)."""

from __future__ import annotations

from uacell.datasets import Item, Kind, PartDataSet

_SYSTEM = "SystemOperation/SystemOperationStateMachine"
_TASK = "TaskControlOperation/TaskControlStateMachine"

ROBOT_CONTROLLER = PartDataSet(
    role="controller",
    values=(Item(f"{_SYSTEM}/CurrentState", Kind.STATE),),
    # "": the controller itself, which its alarms (Conditions) are fired through
    notifiers=("", _SYSTEM),
    device=True,  # with its task controls and its robot's motion devices
    commands=(("GetReady", ((_SYSTEM, "GetReady"),)), ("StandDown", ((_SYSTEM, "StandDown"),))),
)

ROBOT_TASK_CONTROL = PartDataSet(
    role="task_control",
    values=(
        Item(f"{_TASK}/CurrentState", Kind.STATE),
        Item("ParameterSet/TaskProgramName", Kind.PROGRAM),
        Item("ParameterSet/ProgramPointer", Kind.PROGRAM),
        Item("ParameterSet/CurrentLine", Kind.PROGRAM),  # uacell's own: the program's source line
        Item("ParameterSet/TaskProgramLoaded", Kind.PROGRAM),
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
        Item("ParameterSet/SpeedOverride", Kind.SPEED),
        Item("Axes/*/ParameterSet/ActualPosition", Kind.POSITION),
    ),
    notifiers=(),
)


DATASETS = (ROBOT_CONTROLLER, ROBOT_TASK_CONTROL, ROBOT_MOTION_DEVICE)
