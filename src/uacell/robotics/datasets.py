"""What history keeps and PubSub publishes of a robot's parts (``Companion.datasets``, uacell.datasets)."""

from __future__ import annotations

from uacell.datasets import Item, Kind, PartDataSet

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


DATASETS = (ROBOT_CONTROLLER, ROBOT_TASK_CONTROL, ROBOT_MOTION_DEVICE)
