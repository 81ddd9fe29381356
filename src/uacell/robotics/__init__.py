"""OPC 40010-1 Robotics behaviour: programs, the equipment interface, the simulator and the model.

Nothing here imports the OPC UA stack; ``uacell.robotics.binding`` ties it to nodes.
"""

from uacell.core.conditions import Condition
from uacell.robotics.equipment import (
    AlarmStop,
    AxisInfo,
    AxisState,
    EquipmentError,
    ExecutionMode,
    NotPowered,
    ProgramRejected,
    RobotEquipment,
    RunOutcome,
    StopMode,
)
from uacell.robotics.model import (
    ProgramLibrary,
    RobotCell,
    RoboticsTables,
    Status,
    SystemOperation,
    TaskControl,
    TaskModule,
)
from uacell.robotics.program import Kind, Program, ProgramError, parse
from uacell.robotics.program_cache import DirectoryLibrary
from uacell.robotics.sim import SimulatedRobot

__all__ = [
    "AlarmStop",
    "AxisInfo",
    "AxisState",
    "Condition",
    "DirectoryLibrary",
    "EquipmentError",
    "ExecutionMode",
    "Kind",
    "NotPowered",
    "Program",
    "ProgramError",
    "ProgramLibrary",
    "ProgramRejected",
    "RobotCell",
    "RobotEquipment",
    "RoboticsTables",
    "RunOutcome",
    "SimulatedRobot",
    "Status",
    "StopMode",
    "SystemOperation",
    "TaskControl",
    "TaskModule",
    "parse",
]
