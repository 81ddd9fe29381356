"""OPC 40010-1 Robotics as a uacell companion: everything the shared code needs to know, in one place."""

from __future__ import annotations

from typing import TYPE_CHECKING

from uacell.core.companion import Companion, LockRule, WebView, lazy_binder, package_file
from uacell.core.roles import Family, Role
from uacell.models.model_file import ModelFile
from uacell.robotics.config import RobotConfig, parse_robots
from uacell.robotics.datasets import DATASETS

if TYPE_CHECKING:  # the server's view, for the annotation only: loading the configuration stays light
    from uacell.host import ServerView

TASK_CONTROL = Family("TaskControl")
SYSTEM_OPERATION = Family("SystemOperation")

# Part roles in the cell (``uacell.binding.cell.Part.role``) the Robotics binder binds.
CONTROLLER, TASK_CONTROL_PART, MOTION_DEVICE = "controller", "task_control", "motion_device"

_TASK_CONTROL_METHODS = (
    "LoadByNodeId", "LoadByName", "UnloadProgram", "UnloadByNodeId", "UnloadByName",
    "Start", "Stop", "ResetToProgramStart",
)  # fmt: skip


ROBOTICS_URI = "http://opcfoundation.org/UA/Robotics/"

# OPC 40010-1 builds on DI and on OPC 30001 Industrial Automation (IA).
MODELS = (
    ModelFile(
        "IA",
        "http://opcfoundation.org/UA/IA/",
        "Opc.Ua.IA.NodeSet2.xml",
        "8ac55e581540258ee8de67617c2d3ef26e9d828dfceabb10f6ba5704c476357d",
        "package/nodesets/Opc.Ua.IA.NodeSet2.xml",
        requires=("DI",),
    ),
    ModelFile(
        "Robotics",
        "http://opcfoundation.org/UA/Robotics/",
        "Opc.Ua.Robotics.NodeSet2.xml",
        "487243c1ec85e0b747c087ed96c0e1d824629789055e74854f07d19099c08803",
        "package/nodesets/Opc.Ua.Robotics.NodeSet2.xml",
        requires=("DI", "IA"),
    ),
)

ROBOTICS: Companion[ServerView] = Companion(
    name="Robotics",
    models=MODELS,
    datasets=DATASETS,
    # Robots: MotionDeviceSystemType (i=1002) instances in DeviceSet.
    web_view=WebView(
        "robots",
        ROBOTICS_URI,
        "DeviceSet",
        1002,
        "uacell.robotics.web_view:describe_robot",
        script=package_file(__package__, "static/view.js"),
        style=package_file(__package__, "static/view.css"),
        history="uacell.robotics.web_view:robot_history",
    ),
    binder=lazy_binder("uacell.robotics.binding", "bind_robotics"),
    section="robot",
    settings=RobotConfig,
    cell_section="robots",
    cell_parser=parse_robots,
    roles={
        **{(TASK_CONTROL, m): Role.OPERATOR for m in _TASK_CONTROL_METHODS},
        **{(SYSTEM_OPERATION, m): Role.OPERATOR for m in ("GetReady", "StandDown", "Start", "Stop")},
        # uacell's own simulation method: raising a fault on purpose is an engineer's test.
        (Family.CONDITION, "SimulateAlarm"): Role.ENGINEER,
    },
    type_hints={
        "TaskControlStateMachineType": TASK_CONTROL,
        "TaskControlOperation": TASK_CONTROL,
        "TaskControlType": TASK_CONTROL,
        "ReadySubstateMachineType": TASK_CONTROL,
        "OperationStateMachineType": TASK_CONTROL,
        "SystemOperationStateMachineType": SYSTEM_OPERATION,
        "SystemOperation": SYSTEM_OPERATION,
        "Programs": Family.DIRECTORY,
    },
    # docs/decisions.md 20: Controllers and their TaskControls carry the DI Lock; a Controller's
    # SystemOperation is guarded by the Controller's lock.
    locks=(
        LockRule(CONTROLLER, members=("SystemOperation",)),
        LockRule(TASK_CONTROL_PART, parent_role=CONTROLLER),
    ),
    lock_guarded=frozenset({TASK_CONTROL, SYSTEM_OPERATION}),
)
