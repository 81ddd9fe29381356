"""Find the cell in any server's address space: by type and BrowseName, never by NodeId.

Robots are the ``MotionDeviceSystemType`` instances (or subtypes) in ``Objects/DeviceSet``, with their
``Controllers``, each controller's ``TaskControls`` and the robot's ``MotionDevices``; PackML units
are the ``PackMLBaseObjectType`` instances in ``Objects/PackMLObjects``. Namespaces are resolved by URI.

The result, ``Cell``, holds a JSON description for the page (``layout``) in which every value and
method is named by a *key* (its BrowseName path, e.g. ``Filler1/Status/MachSpeed``), and the maps
from those keys to the NodeIds found in this server.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from typing import Any

from asyncua import Client, Node, ua

log = logging.getLogger(__name__)

DI = "http://opcfoundation.org/UA/DI/"
ROBOTICS = "http://opcfoundation.org/UA/Robotics/"
PACKML = "http://opcfoundation.org/UA/PackML/"

_HIERARCHICAL = ua.NodeId(ua.ObjectIds.HierarchicalReferences)
_HAS_SUBTYPE = ua.NodeId(ua.ObjectIds.HasSubtype)
_CONDITION_TYPE = ua.NodeId(ua.ObjectIds.ConditionType)
_FILE_TYPE = ua.NodeId(ua.ObjectIds.FileType)

# What the page shows of a PackML unit's Status and Admin objects (those present are used).
UNIT_STATUS = (
    "UnitModeCurrent",
    "UnitSupportedModes",
    "MachSpeed",
    "CurMachSpeed",
    "StateRequested",
    "StateChangeInProcess",
    "MaterialInterlocked",
    "EquipmentBlocked",
    "EquipmentStarved",
    "StartParameters",
)
UNIT_ADMIN = ("ProdProcessedCount", "ProdDefectiveCount", "ProdConsumedCount", "StopReason", "Alarm", "Warning")
UNIT_METHODS = ("SetUnitMode", "SetMachSpeed")
PACKML_MACHINES = (
    ("BaseStateMachine", ("Abort", "Clear")),
    ("MachineState", ("Reset", "Stop")),
    ("ExecuteState", ("Reset", "Start", "Hold", "Unhold", "Suspend", "Unsuspend", "ToComplete")),
)
SYSOP_METHODS = ("GetReady", "StandDown", "Start", "Stop")
# CurrentLine and ProgramPointer are uacell's own (docs/robotics.md): absent on other servers.
TASK_VARIABLES = ("TaskProgramName", "TaskProgramLoaded", "ExecutionMode", "CurrentLine", "ProgramPointer")
TASK_METHODS = ("LoadByName", "UnloadProgram", "UnloadByName", "Start", "Stop")
LOCK_VARIABLES = ("Locked", "LockingUser", "LockingClient", "RemainingLockTime")
LOCK_METHODS = ("InitLock", "RenewLock", "ExitLock", "BreakLock")
CONDITION_VARIABLES = ("ActiveState/Id", "AckedState/Id", "Message", "EventId", "Severity", "Time", "Retain")


@dataclass(frozen=True)
class Child:
    name: str
    node: ua.NodeId
    node_class: ua.NodeClass
    type_definition: ua.NodeId


@dataclass
class MethodRef:
    """A method the page may call: the object it is called on, the method, its input arguments."""

    object: ua.NodeId
    method: ua.NodeId
    arguments: list[ua.Argument] = field(default_factory=list)
    robotics: bool = False  # an OPC 40010-1 operation method: its first output is a Status value


@dataclass
class Cell:
    layout: dict[str, Any] = field(default_factory=dict)
    variables: dict[str, ua.NodeId] = field(default_factory=dict)
    methods: dict[str, MethodRef] = field(default_factory=dict)
    # Robot program directories: key -> FileDirectoryType node.
    directories: dict[str, ua.NodeId] = field(default_factory=dict)
    # TaskModules folders: key -> node (browsed again when the loaded program changes).
    folders: dict[str, ua.NodeId] = field(default_factory=dict)
    # Nodes whose TransitionEvents the page lists, by NodeId string -> key of the machine.
    machines: dict[str, str] = field(default_factory=dict)
    # uacell's Server/CurrentRole (decision 39): read once per session, each session its own role.
    role: ua.NodeId | None = None


class Discoverer:
    def __init__(self, client: Client) -> None:
        self.client = client
        self.cell = Cell()
        self._supertypes: dict[ua.NodeId, ua.NodeId | None] = {}

    async def children(self, node: ua.NodeId) -> list[Child]:
        refs = await Node(self.client.uaclient, node).get_references(
            refs=_HIERARCHICAL, direction=ua.BrowseDirection.Forward
        )
        return [Child(r.BrowseName.Name, r.NodeId, r.NodeClass, r.TypeDefinition) for r in refs]

    async def child(self, node: ua.NodeId | None, *path: str) -> ua.NodeId | None:
        for name in path:
            if node is None:
                return None
            node = next((c.node for c in await self.children(node) if c.name == name), None)
        return node

    async def is_a(self, type_definition: ua.NodeId, target: ua.NodeId) -> bool:
        """True when ``type_definition`` is ``target`` or one of its subtypes."""
        current: ua.NodeId | None = type_definition
        seen = 0
        while current is not None and seen < 32:
            if current == target:
                return True
            if current not in self._supertypes:
                refs = await Node(self.client.uaclient, current).get_references(
                    refs=_HAS_SUBTYPE, direction=ua.BrowseDirection.Inverse, includesubtypes=False
                )
                self._supertypes[current] = refs[0].NodeId if refs else None
            current = self._supertypes[current]
            seen += 1
        return False

    async def of_type(self, folder: ua.NodeId | None, type_id: ua.NodeId) -> list[Child]:
        if folder is None:
            return []
        return [
            c
            for c in await self.children(folder)
            if c.node_class == ua.NodeClass.Object and await self.is_a(c.type_definition, type_id)
        ]

    # registering what the page uses ----------------------------------------------------------

    async def variable(self, key: str, node: ua.NodeId | None, *path: str) -> str | None:
        found = await self.child(node, *path) if path else node
        if found is None:
            return None
        self.cell.variables[key] = found
        return key

    async def method(self, key: str, obj: ua.NodeId | None, name: str, robotics: bool = False) -> str | None:
        found = await self.child(obj, name)
        if obj is None or found is None:
            return None
        args: list[ua.Argument] = []
        prop = await self.child(found, "InputArguments")
        if prop is not None:
            value = await Node(self.client.uaclient, prop).read_value()
            args = list(value or [])
        self.cell.methods[key] = MethodRef(obj, found, args, robotics)
        return key

    async def methods(
        self, prefix: str, obj: ua.NodeId | None, names: tuple[str, ...], robotics: bool = False
    ) -> dict[str, str]:
        out = {}
        for name in names:
            key = await self.method(f"{prefix}/{name}", obj, name, robotics)
            if key:
                out[name] = key
        return out

    async def machine(self, prefix: str, node: ua.NodeId | None) -> dict[str, Any]:
        """A state machine: its CurrentState (and LastTransitionReason), events keyed by ``prefix``."""
        if node is None:
            return {}
        self.cell.machines[node.to_string()] = prefix
        return {
            "key": prefix,
            "state": await self.variable(f"{prefix}/CurrentState", node, "CurrentState"),
            "reason": await self.variable(f"{prefix}/LastTransitionReason", node, "LastTransitionReason"),
            "reason_text": await self.variable(
                f"{prefix}/LastTransitionReason/ValueAsText", node, "LastTransitionReason", "ValueAsText"
            ),
        }

    async def lock(self, prefix: str, obj: ua.NodeId) -> dict[str, Any] | None:
        node = await self.child(obj, "Lock")
        if node is None:
            return None
        variables = {n: await self.variable(f"{prefix}/Lock/{n}", node, n) for n in LOCK_VARIABLES}
        return {"variables": variables, "methods": await self.methods(f"{prefix}/Lock", node, LOCK_METHODS)}

    # the cell ---------------------------------------------------------------------------------

    async def discover(self) -> Cell:
        ns = await self.client.get_namespace_array()
        index = {uri: i for i, uri in enumerate(ns)}
        objects = ua.NodeId(ua.ObjectIds.ObjectsFolder)
        top = {c.name: c.node for c in await self.children(objects)}
        robots: list[dict[str, Any]] = []
        units: list[dict[str, Any]] = []
        if ROBOTICS in index:
            r = index[ROBOTICS]
            for robot in await self.of_type(top.get("DeviceSet"), ua.NodeId(1002, r)):
                robots.append(await self.robot(robot, r))
        if PACKML in index:
            for unit in await self.of_type(top.get("PackMLObjects"), ua.NodeId(6, index[PACKML])):
                units.append(await self.unit(unit))
        self.cell.layout = {"robots": robots, "units": units, "auditing": await self.auditing()}
        self.cell.role = await self.child(ua.NodeId(ua.ObjectIds.Server), "CurrentRole")
        log.debug("found %d robots and %d PackML units", len(robots), len(units))
        return self.cell

    async def auditing(self) -> bool:
        """Does the server audit (``Server/Auditing``)? uacell does: it fires AuditUpdateStateEvents naming
        who caused each transition."""
        node = Node(self.client.uaclient, ua.NodeId(ua.ObjectIds.Server_Auditing))
        dv = await node.read_data_value(raise_on_bad_status=False)
        return bool(dv.StatusCode.is_good() and dv.Value is not None and dv.Value.Value)

    async def unit(self, unit: Child) -> dict[str, Any]:
        name = unit.name
        machines: list[dict[str, Any]] = []
        node: ua.NodeId | None = unit.node
        for machine_name, method_names in PACKML_MACHINES:
            node = await self.child(node, machine_name)
            if node is None:
                break
            prefix = f"{name}/{machine_name}"
            machines.append(
                {
                    "name": machine_name,
                    **await self.machine(prefix, node),
                    "methods": await self.methods(prefix, node, method_names),
                }
            )
        status = await self.child(unit.node, "Status")
        admin = await self.child(unit.node, "Admin")
        variables = {n: await self.variable(f"{name}/Status/{n}", status, n) for n in UNIT_STATUS}
        variables |= {n: await self.variable(f"{name}/Admin/{n}", admin, n) for n in UNIT_ADMIN}
        # The speeds the unit accepts, for a refusal in words ("speed must be within 0..600").
        variables["MachSpeedRange"] = await self.variable(
            f"{name}/Status/MachSpeed/EURange", status, "MachSpeed", "EURange"
        )
        return {
            "name": name,
            "machines": machines,
            "variables": {k: v for k, v in variables.items() if v},
            "methods": await self.methods(name, unit.node, UNIT_METHODS),
        }

    async def robot(self, robot: Child, r: int) -> dict[str, Any]:
        controllers = [
            await self.controller(f"{robot.name}/{c.name}", c, r)
            for c in await self.of_type(await self.child(robot.node, "Controllers"), ua.NodeId(1003, r))
        ]
        devices = []
        for device in await self.of_type(await self.child(robot.node, "MotionDevices"), ua.NodeId(1004, r)):
            prefix = f"{robot.name}/{device.name}"
            axes = []
            for axis in await self.of_type(await self.child(device.node, "Axes"), ua.NodeId(16601, r)):
                key = await self.variable(
                    f"{prefix}/{axis.name}/ActualPosition", axis.node, "ParameterSet", "ActualPosition"
                )
                if key:
                    axes.append({"name": axis.name, "position": key})
            devices.append(
                {
                    "name": device.name,
                    "axes": axes,
                    "in_control": await self.variable(f"{prefix}/InControl", device.node, "ParameterSet", "InControl"),
                }
            )
        return {"name": robot.name, "controllers": controllers, "motion_devices": devices}

    async def controller(self, prefix: str, controller: Child, r: int) -> dict[str, Any]:
        sysop = await self.child(controller.node, "SystemOperation")
        machine = await self.child(sysop, "SystemOperationStateMachine")
        conditions = []
        for cond in await self.of_type(await self.child(sysop, "Conditions"), _CONDITION_TYPE):
            key = f"{prefix}/Conditions/{cond.name}"
            conditions.append(
                {
                    "name": cond.name,
                    "variables": {
                        v: await self.variable(f"{key}/{v}", cond.node, *v.split("/")) for v in CONDITION_VARIABLES
                    },
                    "methods": await self.methods(key, cond.node, ("Acknowledge",)),
                }
            )
        programs = await self.child(controller.node, "Programs")
        program_methods: dict[str, str] = {}
        if programs is not None:
            self.cell.directories[f"{prefix}/Programs"] = programs
            program_methods = await self.methods(f"{prefix}/Programs", programs, ("CreateFile", "Delete"))
        tasks = []
        for task in await self.of_type(await self.child(controller.node, "TaskControls"), ua.NodeId(1011, r)):
            tasks.append(await self.task_control(f"{prefix}/{task.name}", task))
        sysop_prefix = f"{prefix}/SystemOperation"
        return {
            "name": controller.name,
            "system_operation": {
                **await self.machine(sysop_prefix, machine),
                "substates": [
                    await self.machine(f"{sysop_prefix}/{sub}", await self.child(machine, sub))
                    for sub in ("IdleSubstateMachine", "ExecutingSubstateMachine")
                ],
                "methods": await self.methods(sysop_prefix, machine, SYSOP_METHODS, robotics=True),
            },
            "conditions": conditions,
            "lock": await self.lock(prefix, controller.node),
            "programs": f"{prefix}/Programs" if programs is not None else None,
            "program_methods": program_methods,
            "task_controls": tasks,
            "simulate_alarm": await self.method(f"{prefix}/SimulateAlarm", controller.node, "SimulateAlarm"),
        }

    async def task_control(self, prefix: str, task: Child) -> dict[str, Any]:
        machine = await self.child(task.node, "TaskControlOperation", "TaskControlStateMachine")
        ready = await self.child(machine, "ReadySubstateMachine")
        params = await self.child(task.node, "ParameterSet")
        modules = await self.child(task.node, "TaskModules")
        if modules is not None:
            self.cell.folders[f"{prefix}/TaskModules"] = modules
        methods = await self.methods(prefix, machine, TASK_METHODS, robotics=True)
        methods |= await self.methods(f"{prefix}/ReadySubstateMachine", ready, ("ResetToProgramStart",), True)
        return {
            "name": task.name,
            **await self.machine(prefix, machine),
            "ready": await self.machine(f"{prefix}/ReadySubstateMachine", ready),
            "variables": {n: await self.variable(f"{prefix}/{n}", params, n) for n in TASK_VARIABLES},
            "modules": f"{prefix}/TaskModules" if modules is not None else None,
            "lock": await self.lock(prefix, task.node),
            "methods": methods,
        }


async def discover(client: Client) -> Cell:
    """Browse ``client``'s server for robots and PackML units (see the module docstring)."""
    return await Discoverer(client).discover()


async def list_files(client: Client, directory: ua.NodeId, prefix: str = "") -> list[dict[str, Any]]:
    """The files below a FileDirectoryType (recursively), as ``{"name", "path", "node"}``."""
    d = Discoverer(client)
    files: list[dict[str, Any]] = []
    for c in await d.children(directory):
        if c.node_class != ua.NodeClass.Object:
            continue
        path = f"{prefix}{c.name}"
        if await d.is_a(c.type_definition, _FILE_TYPE):
            files.append({"name": c.name, "path": path, "node": c.node})
        elif c.type_definition == ua.NodeId(ua.ObjectIds.FileDirectoryType):
            files += await list_files(client, c.node, f"{path}/")
    return sorted(files, key=lambda f: f["path"])
