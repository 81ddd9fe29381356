"""The ``[robot]`` section and the ``[[robots]]`` of a cell: robots, controllers, task controls, motion devices.

Pure: reads and checks the tables (``uacell.core.cell_file.Table``) and turns them into ``Part`` trees
(``uacell.binding.cell``). docs/configuration.md documents every key.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from uacell.core.cell_file import (
    STATE_MACHINE,
    Part,
    Table,
    check_name,
    identification_lines,
    read_identification,
    unique,
)
from uacell.core.drivers import ROBOT_CONTROLLER, drivers_of
from uacell.core.errors import ConfigError
from uacell.robotics.equipment import AxisInfo, ExecutionMode, StopMode
from uacell.robotics.sim import DEFAULT_AXES

STOP_MODES: dict[str, StopMode] = {
    "OnPath": StopMode.ON_PATH,
    "EndOfCycle": StopMode.END_OF_CYCLE,
    "ProcessStop": StopMode.PROCESS_STOP,
    "QuickStop": StopMode.QUICK_STOP,
    "EndOfInstruction": StopMode.END_OF_INSTRUCTION,
}
STOP_MODE_NAMES = {mode: name for name, mode in STOP_MODES.items()}
# ExecutionModeEnumeration's names, as the NodeSet spells them.
EXECUTION_MODES: dict[str, ExecutionMode] = {m.name: m for m in ExecutionMode}
# Limits of an axis beyond the simulator's six defaults: degrees, degrees/s.
EXTRA_AXIS = (-180.0, 180.0, 300.0)
# What a robot has when its table does not say.
_ONE_TASK = [{"name": "TaskControl1"}]
_ONE_ARM = [{"name": "Arm1"}]
_ONE_CONTROLLER = [{"name": "Controller1"}]


# The drivers shipped for robot controllers (docs/equipment.md, "Gateway"): equipment = { driver = ... }.
DRIVERS = drivers_of(ROBOT_CONTROLLER)  # name -> factory (uacell.core.drivers, the one registry)


@dataclass
class RobotConfig:
    """The ``[robot]`` section: defaults for every controller that does not set its own."""

    time_scale: float = 1.0  # simulated robot: >1 runs faster than real time
    equipment: str = ""  # "package.module:factory" for real equipment (docs/equipment.md)


@dataclass
class TaskControlSpec:
    name: str
    execution_mode: ExecutionMode = ExecutionMode.CYCLE


@dataclass
class ControllerSpec:
    name: str
    task_controls: list[TaskControlSpec]
    motion_device: str | None  # the motion device it controls, if any
    equipment: str = ""  # "package.module:factory"; "" = [robot] equipment, else the simulator
    settings: dict[str, Any] = field(default_factory=dict)
    time_scale: float | None = None  # simulator: > 1 runs faster than real time; None = [robot] time_scale
    possible_stop_modes: tuple[StopMode, ...] = tuple(StopMode)
    default_stop_mode: StopMode = StopMode.ON_PATH
    identification: dict[str, str] = field(default_factory=dict)
    software: str = "Software1"


@dataclass
class MotionDeviceSpec:
    name: str
    axes: tuple[AxisInfo, ...]
    identification: dict[str, str] = field(default_factory=dict)


@dataclass
class RobotSpec:
    """One MotionDeviceSystem."""

    name: str
    controllers: list[ControllerSpec]
    motion_devices: list[MotionDeviceSpec]
    safety_states: tuple[str, ...] = ("SafetyState1",)
    identification: dict[str, str] = field(default_factory=dict)

    def motion_device(self, name: str | None) -> MotionDeviceSpec | None:
        return next((m for m in self.motion_devices if m.name == name), None)


# --- reading --------------------------------------------------------------------------------------
def _axis_error(table: Table, index: int, message: str) -> ConfigError:
    return table.error(f"axes[{index + 1}]", message)  # positions count from 1, as a reader counts


def _axes(table: Table) -> tuple[AxisInfo, ...]:
    value = table.raw("axes")
    if value is None:
        value = len(DEFAULT_AXES)
    if isinstance(value, bool) or not isinstance(value, int | list):
        raise table.error("axes", "must be a number of axes or an array of axis names or tables")
    if isinstance(value, int):
        value = [f"Axis{i}" for i in range(1, value + 1)] if value > 0 else []
    if not value:
        raise table.error("axes", "a motion device needs at least one axis")
    axes: list[AxisInfo] = []
    tables: list[Table] = []
    for i, item in enumerate(value):
        low, high, speed = (
            (DEFAULT_AXES[i].min_position, DEFAULT_AXES[i].max_position, DEFAULT_AXES[i].max_speed)
            if (i < len(DEFAULT_AXES))
            else EXTRA_AXIS
        )
        if isinstance(item, str):
            check_name(item, functools.partial(_axis_error, table, i))
            axes.append(AxisInfo(item, low, high, speed))
            tables.append(table)
            continue
        axis = table.child(item, f"axes[{i + 1}]")
        name = axis.name()
        low = axis.number("min_position", low, minimum=None)
        high = axis.number("max_position", high, minimum=None)
        speed = axis.number("max_speed", speed, positive=True)
        if low >= high:
            raise axis.error("max_position", "must be greater than min_position")
        axis.finish()
        axes.append(AxisInfo(name, low, high, speed))
        tables.append(axis)
    seen: set[str] = set()
    for a, t in zip(axes, tables, strict=True):
        if a.name in seen:
            raise t.error("name" if t is not table else "axes", f"an axis named {a.name!r} is declared twice")
        seen.add(a.name)
    return tuple(axes)


def _stop_modes(table: Table) -> tuple[tuple[StopMode, ...], StopMode]:
    names = table.raw("possible_stop_modes")
    if names is None:
        possible = tuple(StopMode)
    else:
        if not isinstance(names, list) or not names or not all(isinstance(n, str) for n in names):
            raise table.error("possible_stop_modes", "must be a non-empty array of stop mode names")
        unknown = [n for n in names if n not in STOP_MODES]
        if unknown:
            raise table.error("possible_stop_modes", f"{unknown[0]!r} is not one of {', '.join(STOP_MODES)}")
        if len(set(names)) != len(names):
            raise table.error("possible_stop_modes", "names a stop mode twice")
        possible = tuple(STOP_MODES[n] for n in names)
    default = table.choice("default_stop_mode", STOP_MODES, STOP_MODE_NAMES[possible[0]])
    if default not in possible:
        raise table.error("default_stop_mode", f"{STOP_MODE_NAMES[default]!r} is not in possible_stop_modes")
    return possible, default


def _task_control(table: Table) -> TaskControlSpec:
    spec = TaskControlSpec(table.name(), table.choice("execution_mode", EXECUTION_MODES, "CYCLE"))
    table.finish()
    return spec


def _controller(table: Table, index: int, robot_devices: list[str]) -> ControllerSpec:
    name = table.name()
    tables = table.entries("task_controls", _ONE_TASK)
    tasks = [_task_control(t) for t in tables]
    if not tasks:
        raise table.error("task_controls", "a controller needs at least one task control")
    unique([(t.name, tt) for t, tt in zip(tasks, tables, strict=True)], "a task control named")
    if table.has("motion_device"):
        device: str | None = table.string("motion_device") or None
        if device is not None and device not in robot_devices:
            raise table.error("motion_device", f"{device!r} is not a motion device of this robot")
    else:
        table.seen.add("motion_device")
        device = robot_devices[index] if index < len(robot_devices) else None
    possible, default = _stop_modes(table)
    equipment, settings = table.equipment(DRIVERS)
    # LoadByName's names -> a signals robot's program numbers, or the names its controller knows them by
    programs = table.free_table("programs")
    if programs:
        bad = next(
            (k for k, v in programs.items() if isinstance(v, bool) or not isinstance(v, int | str) or v in ("", 0)),
            None,
        )
        if bad is not None:
            raise table.error("programs", f"{bad}: must be a program number (1..65535) or a name (a string)")
        settings["programs"] = programs
    spec = ControllerSpec(
        name,
        tasks,
        device,
        equipment=equipment,
        settings=settings,
        time_scale=table.optional_number("time_scale", positive=True),
        possible_stop_modes=possible,
        default_stop_mode=default,
        identification=read_identification(table),
        software=table.name("software", "Software1"),
    )
    table.finish()
    return spec


def _motion_device(table: Table) -> MotionDeviceSpec:
    spec = MotionDeviceSpec(table.name(), _axes(table), read_identification(table))
    table.finish()
    return spec


def _robot(table: Table) -> RobotSpec:
    name = table.name()
    tables = table.entries("motion_devices", _ONE_ARM)
    devices = [_motion_device(t) for t in tables]
    if not devices:
        raise table.error("motion_devices", "a robot needs at least one motion device")
    unique([(d.name, t) for d, t in zip(devices, tables, strict=True)], "a motion device named")
    device_names = [d.name for d in devices]
    tables = table.entries("controllers", _ONE_CONTROLLER)
    controllers = [_controller(t, i, device_names) for i, t in enumerate(tables)]
    if not controllers:
        raise table.error("controllers", "a robot needs at least one controller")
    unique([(c.name, t) for c, t in zip(controllers, tables, strict=True)], "a controller named")
    controlled = [c.motion_device for c in controllers if c.motion_device is not None]
    for device in controlled:
        if controlled.count(device) > 1:
            raise table.error("controllers", f"motion device {device!r} is controlled by two controllers")
    safety = table.raw("safety_states")
    if safety is None:
        safety = ["SafetyState1"]
    if not isinstance(safety, list) or not safety or not all(isinstance(s, str) for s in safety):
        raise table.error("safety_states", "must be a non-empty array of names")
    for s in safety:
        check_name(s, lambda m: table.error("safety_states", m))
    unique([(s, table) for s in safety], "a safety state named")
    spec = RobotSpec(name, controllers, devices, tuple(safety), read_identification(table))
    table.finish()
    return spec


@dataclass
class RobotsSection:
    """Every ``[[robots]]`` entry (a ``uacell.core.cell_file.CellSection``)."""

    robots: list[RobotSpec]
    tables: list[Table]

    def parts(self) -> list[tuple[str, Any]]:
        return [("DeviceSet", robot_part(r)) for r in self.robots]

    def top_names(self) -> list[tuple[str, Table]]:
        return [(r.name, t) for r, t in zip(self.robots, self.tables, strict=True)]

    def describe(self, settings: Mapping[str, Any]) -> list[str]:
        defaults = settings.get("robot", RobotConfig())
        lines = []
        for robot in self.robots:
            lines.append(f"DeviceSet/{robot.name}  MotionDeviceSystemType")
            lines += [f"    {x}" for x in identification_lines(robot.identification)]
            for c in robot.controllers:
                stops = ", ".join(STOP_MODE_NAMES[m] for m in c.possible_stop_modes)
                lines.append(f"  Controllers/{c.name}  ControllerType  equipment: {describe_equipment(c, defaults)}")
                lines.append(f"    stop modes: {stops} (default {STOP_MODE_NAMES[c.default_stop_mode]})")
                lines.append(f"    motion device: {c.motion_device or '(none)'}")
                lines += [f"    {x}" for x in identification_lines(c.identification)]
                for t in c.task_controls:
                    lines.append(f"    TaskControls/{t.name}  TaskControlType  ExecutionMode {t.execution_mode.name}")
            for m in robot.motion_devices:
                names = " ".join(a.name for a in m.axes)
                lines.append(f"  MotionDevices/{m.name}  MotionDeviceType  {len(m.axes)} axes: {names}")
                lines += [f"    {x}" for x in identification_lines(m.identification)]
            for s in robot.safety_states:
                lines.append(f"  SafetyStates/{s}  SafetyStateType")
        return lines


def describe_equipment(c: ControllerSpec, defaults: RobotConfig) -> str:
    """What the controller runs on, with the values in effect (``defaults``: the ``[robot]`` section)."""
    extra = f" settings {c.settings}" if c.settings else ""
    if c.equipment:
        return c.equipment + extra
    if defaults.equipment:
        return f"{defaults.equipment} (from [robot] equipment){extra}"
    if c.time_scale is None:
        return f"simulator (time_scale {defaults.time_scale:g} from [robot]){extra}"
    return f"simulator (time_scale {c.time_scale:g}){extra}"


def parse_robots(root: Table, key: str) -> RobotsSection:
    robots, tables = [], []
    for table in root.entries(key):
        robots.append(_robot(table))
        tables.append(table)
    return RobotsSection(robots, tables)


# --- Part trees -----------------------------------------------------------------------------------
def _values(identification: dict[str, str]) -> dict[str, str]:
    return dict(identification)


def robot_part(robot: RobotSpec) -> Part:
    """The MotionDeviceSystem as a ``Part`` tree (what ``uacell.binding.cell`` instantiates)."""
    controllers = [_controller_part(c) for c in robot.controllers]
    devices = [_motion_device_part(m) for m in robot.motion_devices]
    safety = [Part(s, "Robotics", "SafetyStateType", "SafetyStates") for s in robot.safety_states]
    return Part(
        robot.name,
        "Robotics",
        "MotionDeviceSystemType",
        children=[*controllers, *devices, *safety],
        role="robot",
        values=_values(robot.identification),
        spec=robot,
    )


def _controller_part(c: ControllerSpec) -> Part:
    tasks = [
        Part(
            t.name,
            "Robotics",
            "TaskControlType",
            "TaskControls",
            include=(
                "Lock",
                "ParameterSet/ExecutionMode",
                "TaskModules",
                "TaskControlOperation",
                "TaskControlOperation/**",
                *STATE_MACHINE,
            ),
            role="task_control",
            spec=t,
        )
        for t in c.task_controls
    ]
    return Part(
        c.name,
        "Robotics",
        "ControllerType",
        "Controllers",
        include=("Lock", "Programs", "SystemOperation", "SystemOperation/**", *STATE_MACHINE),
        children=[*tasks, Part(c.software, "DI", "SoftwareType", "Software")],
        role="controller",
        values=_values(c.identification),
        spec=c,
    )


def _motion_device_part(m: MotionDeviceSpec) -> Part:
    axes = [
        Part(
            a.name,
            "Robotics",
            "AxisType",
            "Axes",
            include=("ParameterSet/ActualSpeed", "ParameterSet/ActualAcceleration"),
        )
        for a in m.axes
    ]
    power_trains = [
        Part(
            f"PowerTrain{i}",
            "Robotics",
            "PowerTrainType",
            "PowerTrains",
            children=[Part(f"Motor{i}", "Robotics", "MotorType")],
        )
        for i in range(1, len(m.axes) + 1)
    ]
    return Part(
        m.name,
        "Robotics",
        "MotionDeviceType",
        "MotionDevices",
        include=("ParameterSet/InControl", "ParameterSet/OnPath", "FlangeLoad"),
        children=axes + power_trains,
        role="motion_device",
        values=_values(m.identification),
        spec=m,
    )
