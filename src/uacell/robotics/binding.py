"""Binds the cell's Robotics controller to its nodes: programs, task controls, system operation, arm.

The pure ``RobotCell`` (``uacell.robotics.model``) owns every rule; this module only translates:

- ``Controller1/Programs``: a ``FileStore`` over ``<data_dir>/programs`` (the sample programs are
  installed when that directory does not exist yet), bound by ``uacell.ua.file_directory`` when it
  is available; the loaded program and modules are protected (Bad_InvalidState on delete/overwrite);
- the TaskControl and SystemOperation machines through the shared state-machine binding, every
  Robotics method through the dispatcher (``element`` = the TaskControl / Controller node, for locks);
- ``ParameterSet`` values, ``TaskModules`` (one TaskModuleType per loaded module),
  ``MotionDevicesUnderControl`` + a ``Controls`` reference, the stop modes, and the alarm conditions
  (AlarmConditionType, an acknowledgeable condition with ActiveState) in ``SystemOperation/Conditions``;
- Arm1's axes (ActualPosition/ActualSpeed/ActualAcceleration) sampled at 10 Hz while they change.

Server-specific additions, in the cell namespace: ``Controller1/SimulateAlarm(String Name, Boolean
Active)`` (admin: raise or clear a simulator alarm), and ``ParameterSet/ExecutionMode`` is writable
by operators while the task control is not executing (Bad_InvalidState otherwise).
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import uuid
from collections import deque
from collections.abc import Awaitable, Callable
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.server.event_generator import EventGenerator

from uacell.config import load_factory
from uacell.errors import CallError
from uacell.robotics.equipment import RobotEquipment, StopMode
from uacell.robotics.model import PROGRAM_SUFFIX, Condition, DirectoryLibrary, RobotCell, Status, TaskControl
from uacell.robotics.program import samples
from uacell.robotics.sim import SimulatedRobot
from uacell.roles import Family, Role
from uacell.ua.context import Caller
from uacell.ua.file_directory import FileDirectoryBinding
from uacell.ua.file_store import FileStore
from uacell.ua.instantiate import Selection
from uacell.ua.state_machine import bind_tree

log = logging.getLogger(__name__)

ROBOTICS_URI = "http://opcfoundation.org/UA/Robotics/"
PROGRAMS_DIR = "programs"
SIMULATE_ALARM = "SimulateAlarm"
AXIS_PERIOD = 0.1  # seconds between axis samples
ALARM_SEVERITY = 800
_A = ua.AttributeIds
_ROTARY = 1  # AxisMotionProfileEnumeration ROTARY
_STOP_MODE_NAMES = {
    StopMode.ON_PATH: "OnPath",
    StopMode.END_OF_CYCLE: "EndOfCycle",
    StopMode.PROCESS_STOP: "ProcessStop",
    StopMode.QUICK_STOP: "QuickStop",
    StopMode.END_OF_INSTRUCTION: "EndOfInstruction",
}
TC_METHODS = ("LoadByNodeId", "LoadByName", "UnloadProgram", "UnloadByNodeId", "UnloadByName", "Start", "Stop")
SO_METHODS = ("GetReady", "StandDown", "Start", "Stop")


def _now() -> datetime:
    return datetime.now(UTC)


# --- programs ------------------------------------------------------------------------------------
def install_samples(root: Path) -> bool:
    """Write the sample programs and modules into ``root`` if it does not exist yet (first start)."""
    if root.exists():
        return False
    root.mkdir(parents=True)
    for name, text in samples().items():
        (root / name).write_text(text, encoding="utf-8")
    log.info("installed %d sample programs in %s", len(samples()), root)
    return True


class StoreLibrary(DirectoryLibrary):
    """The ProgramLibrary over a FileStore: the store's listing hides its temporary files."""

    def __init__(self, store: FileStore) -> None:
        super().__init__(store.root)
        self.store = store

    def _files(self) -> list[Path]:
        return sorted(
            self.root / e.relpath
            for e in self.store.entries()
            if not e.is_dir and e.relpath.endswith(PROGRAM_SUFFIX)
        )


# --- the binding -----------------------------------------------------------------------------------
class _Files:
    """NodeId <-> relpath of the Programs tree: ``uacell.ua.file_directory`` when it is bound."""

    def __init__(self) -> None:
        self.directory: Any = None

    def relpath_of(self, nodeid: ua.NodeId) -> str | None:
        if self.directory is None:
            return None
        try:
            rel = self.directory.relpath_of(nodeid)
        except (KeyError, LookupError):
            return None
        return rel

    def node_of(self, relpath: str) -> ua.NodeId | None:
        if self.directory is None:
            return None
        try:
            return self.directory.node_of(relpath)
        except (KeyError, LookupError):
            return None


class ConditionNode:
    """One AlarmConditionType instance mirroring a model ``Condition``."""

    def __init__(self, binding: RoboticsBinding, name: str, node: ua.NodeId, source: ua.NodeId) -> None:
        self.binding = binding
        self.name = name
        self.node = node
        self.source = source
        self.event_ids: deque[bytes] = deque(maxlen=32)
        self.event: Any = None
        self.reported_enabled = True

    def child(self, path: str) -> ua.NodeId:
        return self.binding.app.cell.child(self.node, path)


class RoboticsBinding:
    """One controller (with its task controls and motion device) on its instance nodes."""

    def __init__(self, app: Any, controller: Any, tasks: list[Any], arm: Any | None, cell: RobotCell) -> None:
        self.app = app
        self.controller = controller
        self.task_parts = {t.part.name: t for t in tasks}
        self.arm = arm
        self.cell = cell
        self.ns: int = app.cell.instantiator.ns
        self.aspace = app.server.iserver.aspace
        self.files = _Files()
        self.store: FileStore | None = None
        self.module_nodes: dict[str, dict[str, ua.NodeId]] = {name: {} for name in self.task_parts}
        self.conditions: dict[str, ConditionNode] = {}
        self._written: dict[ua.NodeId, Any] = {}
        self._pending = False
        self._protected: set[str] = set()
        self._axis_task: asyncio.Task[None] | None = None

    # --- nodes --------------------------------------------------------------------------------
    def child(self, node: ua.NodeId, path: str) -> ua.NodeId:
        return self.app.cell.child(node, path)

    def tc_machine_node(self, task: str) -> ua.NodeId:
        return self.child(self.task_parts[task].node, "TaskControlOperation/TaskControlStateMachine")

    @property
    def so_machine_node(self) -> ua.NodeId:
        return self.child(self.controller.node, "SystemOperation/SystemOperationStateMachine")

    def vtype(self, nodeid: ua.NodeId) -> ua.VariantType:
        datatype = self.aspace[nodeid].attributes[_A.DataType].value.Value.Value
        return self.app.dispatcher.types.builtin_of(datatype) or ua.VariantType.Variant

    async def write(self, nodeid: ua.NodeId, value: Any, vtype: ua.VariantType | None = None, *, force=False) -> None:
        """Write a Value (only when it changed, unless ``force``)."""
        if not force and self._written.get(nodeid, object()) == value:
            return
        self._written[nodeid] = value
        vtype = vtype or self.vtype(nodeid)
        variant = ua.Variant(value, vtype, is_array=isinstance(value, list))
        now = _now()
        await self.aspace.write_attribute_value(
            nodeid, _A.Value, ua.DataValue(variant, SourceTimestamp=now, ServerTimestamp=now)
        )

    async def set_access(self, nodeid: ua.NodeId, level: int) -> None:
        for attr in (_A.AccessLevel, _A.UserAccessLevel):
            await self.aspace.write_attribute_value(nodeid, attr, ua.DataValue(ua.Variant(level, ua.VariantType.Byte)))

    def robotics_ns(self) -> int:
        return self.app.model_indexes["Robotics"]

    # --- set-up -------------------------------------------------------------------------------
    async def setup(self) -> None:
        await self.bind_machines()
        self.bind_methods()
        await self.setup_task_controls()
        await self.setup_stop_modes()
        await self.setup_conditions()
        await self.setup_simulate_alarm()
        await self.setup_arm()
        self.cell.add_listener(self.changed)
        self.cell.system.condition_listeners.append(self.condition_changed)
        await self.publish()

    async def bind_machines(self) -> None:
        app = self.app
        for name, task in self.cell.tasks.items():
            await bind_tree(app.server, self.tc_machine_node(name), task.machine, app.publisher, app.refs)
        await bind_tree(app.server, self.so_machine_node, self.cell.system.machine, app.publisher, app.refs)

    def _bind(self, obj: ua.NodeId, name: str, family: Family, handler, executable, serialize_on, element) -> None:
        d = self.app.dispatcher
        d.bind(
            obj, d.method_of(obj, name), family, handler,
            executable=executable, serialize_on=serialize_on, element=element,
        )

    def bind_methods(self) -> None:
        for name, task in self.cell.tasks.items():
            node = self.tc_machine_node(name)
            element = self.task_parts[name].node
            for method in TC_METHODS:
                self._bind(
                    node, method, Family.TASK_CONTROL, self._tc_handler(task, method),
                    _executable(task, "TaskControlStateMachine", method), task.machine, element,
                )
            ready = self.child(node, "ReadySubstateMachine")

            async def reset(caller, _task: TaskControl = task) -> list[int]:
                return [await _task.reset_to_program_start()]

            self._bind(
                ready, "ResetToProgramStart", Family.TASK_CONTROL, reset,
                _executable(task, "ReadySubstateMachine", "ResetToProgramStart"), task.machine, element,
            )
        system = self.cell.system
        for method in SO_METHODS:
            self._bind(
                self.so_machine_node, method, Family.SYSTEM_OPERATION, self._so_handler(method),
                _executable(system, "SystemOperationStateMachine", method), system.machine, self.controller.node,
            )

    def _tc_handler(self, task: TaskControl, method: str):
        async def load_by_node_id(caller, id_: ua.ExpandedNodeId) -> list[int]:
            relpath = self.file_of(id_)
            return [await task.load_file(relpath)]

        async def load_by_name(caller, name: str) -> list[int]:
            return [await task.load_by_name(name or "")]

        async def unload_program(caller) -> list[int]:
            return [await task.unload_program()]

        async def unload_by_node_id(caller, id_: ua.ExpandedNodeId) -> list[int]:
            nodeid = self.local_nodeid(id_)
            for module, node in self.module_nodes[task.name].items():
                if node == nodeid:
                    return [await task.unload_module(module)]
            relpath = self.file_of(id_)
            return [await task.unload_by_file(relpath)]

        async def unload_by_name(caller, name: str) -> list[int]:
            return [await task.unload_by_name(name or "")]

        async def start(caller) -> list[int]:
            return [await task.start()]

        async def stop(caller, mode: int) -> list[int]:
            return [await task.stop(int(mode))]

        return {
            "LoadByNodeId": load_by_node_id,
            "LoadByName": load_by_name,
            "UnloadProgram": unload_program,
            "UnloadByNodeId": unload_by_node_id,
            "UnloadByName": unload_by_name,
            "Start": start,
            "Stop": stop,
        }[method]

    def _so_handler(self, method: str):
        system = self.cell.system

        async def get_ready(caller) -> list[int]:
            return [await system.get_ready()]

        async def stand_down(caller) -> list[int]:
            return [await system.stand_down()]

        async def start(caller) -> list[int]:
            return [await system.start()]

        async def stop(caller, mode: int) -> list[int]:
            return [await system.stop(int(mode))]

        return {"GetReady": get_ready, "StandDown": stand_down, "Start": start, "Stop": stop}[method]

    # --- NodeIds given by clients (decision 10) ---------------------------------------------------
    def local_nodeid(self, id_: Any) -> ua.NodeId:
        """The local NodeId an ExpandedNodeId names; Bad_NodeIdInvalid if null, remote or of an unknown URI."""
        if id_ is None or not isinstance(id_, ua.NodeId):
            raise CallError("BadNodeIdInvalid", "Id is null", argument=0)
        server_index = getattr(id_, "ServerIndex", 0) or 0
        if server_index != 0:
            raise CallError("BadNodeIdInvalid", f"Id names server {server_index}", argument=0)
        index = id_.NamespaceIndex
        uri = getattr(id_, "NamespaceUri", None)
        if uri:
            array = self.app.server.iserver.aspace.read_attribute_value(
                ua.NodeId(ua.ObjectIds.Server_NamespaceArray), _A.Value
            ).Value.Value
            if uri not in array:
                raise CallError("BadNodeIdInvalid", f"unknown namespace {uri}", argument=0)
            index = array.index(uri)
        nodeid = ua.NodeId(id_.Identifier, index, id_.NodeIdType)
        if nodeid.is_null():
            raise CallError("BadNodeIdInvalid", "Id is null", argument=0)
        return nodeid

    def file_of(self, id_: Any) -> str:
        """The relpath in Programs of the FileType node ``id_``; Bad_NodeIdUnknown if it is none."""
        nodeid = self.local_nodeid(id_)
        relpath = self.files.relpath_of(nodeid)  # None for directories and anything outside Programs
        if relpath is None:
            raise CallError("BadNodeIdUnknown", f"{nodeid.to_string()} is not a file in Programs", argument=0)
        return relpath

    # --- task controls ------------------------------------------------------------------------
    async def setup_task_controls(self) -> None:
        ctrl_ref = self.controls_reference()
        for name, task in self.cell.tasks.items():
            part = self.task_parts[name]
            op = self.child(part.node, "TaskControlOperation")
            if self.arm is not None:
                await self.write(self.child(op, "MotionDevicesUnderControl"), [self.arm.node], ua.VariantType.NodeId)
                if ctrl_ref is not None:
                    await self.app.server.get_node(part.node).add_reference(self.arm.node, ctrl_ref, True, True)
            with contextlib.suppress(KeyError):
                mode_node = self.child(part.node, "ParameterSet/ExecutionMode")
                await self.set_access(mode_node, ua.AccessLevel.CurrentRead.mask | ua.AccessLevel.CurrentWrite.mask)
                self.app.writes.route(mode_node, self._execution_mode_writer(task), Role.OPERATOR)

    def controls_reference(self) -> ua.NodeId | None:
        """Robotics' ``Controls`` ReferenceType (found by BrowseName, not by a hard-coded id)."""
        ns = self.robotics_ns()
        for ref in self.app.cell.instantiator.types._subtypes(ua.NodeId(ua.ObjectIds.References)):
            if ref.NamespaceIndex != ns:
                continue
            name = self.app.cell.instantiator.types.attr(ref, _A.BrowseName)
            if name is not None and name.Name == "Controls":
                return ref
        log.warning("the Robotics model has no Controls reference type")
        return None

    def _execution_mode_writer(self, task: TaskControl):
        async def write(dv: ua.DataValue, caller: Caller) -> ua.StatusCode:
            variant = dv.Value
            if variant is None or variant.VariantType not in (ua.VariantType.Int32,) or variant.is_array:
                return ua.StatusCode(ua.StatusCodes.BadTypeMismatch)
            try:
                status = await task.set_execution_mode(int(variant.Value))
            except CallError:
                return ua.StatusCode(ua.StatusCodes.BadOutOfRange)
            if status != Status.OK:
                return ua.StatusCode(ua.StatusCodes.BadInvalidState)
            log.info("%s: ExecutionMode set to %s by %s", task.name, task.execution_mode.name, caller.display_user)
            await self.app.settle()
            return ua.StatusCode(ua.StatusCodes.Good)

        return write

    async def sync_modules(self, name: str, task: TaskControl) -> None:
        folder = self.child(self.task_parts[name].node, "TaskModules")
        nodes = self.module_nodes[name]
        loaded = {m.name: m for m in task.modules}
        for gone in [m for m in nodes if m not in loaded]:
            node = nodes.pop(gone)
            await self.app.server.delete_nodes([self.app.server.get_node(node)], recursive=True)
            for key in [k for k in self._written if isinstance(k.Identifier, str) and k.Identifier.startswith(
                f"{node.Identifier}."
            )]:
                del self._written[key]
        type_node = self.app.cell.type_node("Robotics", "TaskModuleType")
        for module in loaded.values():
            node = nodes.get(module.name)
            if node is None:
                path = f"{self.task_parts[name].path}.TaskModules.{module.name}"
                node = self.app.cell.instantiator.create(
                    folder, type_node, ua.QualifiedName(module.name, self.ns), Selection(("**",)),
                    reference_type=ua.ObjectIds.Organizes, path=path,
                )
                nodes[module.name] = node
            await self.write(self.child(node, "Name"), module.name, ua.VariantType.String)
            with contextlib.suppress(KeyError):
                await self.write(self.child(node, "Version"), module.version, ua.VariantType.String)
            with contextlib.suppress(KeyError):
                await self.write(self.child(node, "IsReferenced"), module.is_referenced, ua.VariantType.Boolean)

    # --- stop modes ---------------------------------------------------------------------------
    async def setup_stop_modes(self) -> None:
        machines = [(self.so_machine_node, self.cell.system.possible_stop_modes, self.cell.system.default_stop_mode)]
        for name, task in self.cell.tasks.items():
            machines.append((self.tc_machine_node(name), task.possible_stop_modes, task.default_stop_mode))
        for node, possible, default in machines:
            values = [
                ua.EnumValueType(
                    Value=int(m),
                    DisplayName=ua.LocalizedText(_STOP_MODE_NAMES.get(m, m.name), "en"),
                    Description=ua.LocalizedText(),
                )
                for m in possible
            ]
            for child, value, vtype in (
                ("PossibleStopModes", values, ua.VariantType.ExtensionObject),
                ("ConfiguredDefaultStopMode", int(default), ua.VariantType.Int16),
            ):
                with contextlib.suppress(KeyError):
                    target = self.child(node, child)
                    await self.write(target, value, vtype, force=True)
                    # Fixed by configuration: a client write would not change the behaviour.
                    await self.set_access(target, ua.AccessLevel.CurrentRead.mask)

    # --- conditions (decision 18) -----------------------------------------------------------------
    async def setup_conditions(self) -> None:
        system = self.cell.system
        so_node = self.child(self.controller.node, "SystemOperation")
        folder = self.child(so_node, "Conditions")
        type_node = ua.NodeId(ua.ObjectIds.AlarmConditionType)
        for name in system.conditions:
            path = f"{self.controller.path}.SystemOperation.Conditions.{name}"
            node = self.app.cell.instantiator.create(
                folder, type_node, ua.QualifiedName(name, self.ns), Selection(()),
                reference_type=ua.ObjectIds.Organizes, path=path,
            )
            await self.app.server.get_node(so_node).add_reference(node, ua.ObjectIds.HasCondition, True, True)
            cond = ConditionNode(self, name, node, self.controller.node)
            self.conditions[name] = cond
            static = {
                "EventType": (type_node, ua.VariantType.NodeId),
                "SourceNode": (self.controller.node, ua.VariantType.NodeId),
                "SourceName": (self.controller.part.name, ua.VariantType.String),
                "ConditionName": (name, ua.VariantType.String),
                "ConditionClassId": (ua.NodeId(ua.ObjectIds.BaseConditionClassType), ua.VariantType.NodeId),
                "ConditionClassName": (ua.LocalizedText("BaseConditionClass"), ua.VariantType.LocalizedText),
                "BranchId": (ua.NodeId(), ua.VariantType.NodeId),
                "Severity": (ALARM_SEVERITY, ua.VariantType.UInt16),
                "LastSeverity": (ALARM_SEVERITY, ua.VariantType.UInt16),
                "EnabledState": (ua.LocalizedText("Enabled", "en"), ua.VariantType.LocalizedText),
                "EnabledState/Id": (True, ua.VariantType.Boolean),
                "Quality": (ua.StatusCode(ua.StatusCodes.Good), ua.VariantType.StatusCode),
                "InputNode": (ua.NodeId(), ua.VariantType.NodeId),
                "SuppressedOrShelved": (False, ua.VariantType.Boolean),
                "Comment": (ua.LocalizedText(""), ua.VariantType.LocalizedText),
                "ClientUserId": ("", ua.VariantType.String),
            }
            for child, (value, vtype) in static.items():
                with contextlib.suppress(KeyError):
                    await self.write(self.child(node, child), value, vtype, force=True)
            gen = EventGenerator(self.app.server.iserver.isession)
            await gen.init(type_node, node, add_generates_event=False)
            cond.event = gen.event
            await self.publish_condition(cond, system.conditions[name], fire=False)
            model = system.conditions[name]
            self._bind(
                node, "Acknowledge", Family.CONDITION, self._acknowledge(cond),
                lambda c=model: c.enabled and not c.acked, system.machine, self.controller.node,
            )
            # OPC 10000-9 ConditionType AddComment, Enable, Disable
            for method, handler, executable in (
                ("AddComment", self._add_comment(cond), lambda c=model: c.enabled),
                ("Enable", self._set_enabled(cond, True), lambda c=model: not c.enabled),
                ("Disable", self._set_enabled(cond, False), lambda c=model: c.enabled),
            ):
                self._bind(node, method, Family.CONDITION, handler, executable, system.machine, self.controller.node)

    def _add_comment(self, cond: ConditionNode):
        async def add_comment(caller, event_id: bytes, comment: ua.LocalizedText) -> list:
            if event_id not in cond.event_ids:
                raise CallError("BadEventIdUnknown", f"no event {event_id!r} of {cond.name}", argument=0)
            text = (comment.Text or "") if isinstance(comment, ua.LocalizedText) else ""
            self.cell.system.add_comment(cond.name, text)
            await self.write(cond.child("ClientUserId"), caller.display_user, ua.VariantType.String)
            return []

        return add_comment

    def _set_enabled(self, cond: ConditionNode, enabled: bool):
        async def set_enabled(caller) -> list:
            self.cell.system.set_enabled(cond.name, enabled)
            log.warning("%s %s condition %s", caller.display_user, "enables" if enabled else "disables", cond.name)
            return []

        return set_enabled

    def _acknowledge(self, cond: ConditionNode):
        async def acknowledge(caller, event_id: bytes, comment: ua.LocalizedText) -> list:
            if event_id not in cond.event_ids:
                raise CallError("BadEventIdUnknown", f"no event {event_id!r} of {cond.name}", argument=0)
            text = comment.Text if isinstance(comment, ua.LocalizedText) else ""
            self.cell.system.acknowledge(cond.name, text or "")
            node = cond.child("Comment")
            await self.write(node, comment if isinstance(comment, ua.LocalizedText) else ua.LocalizedText(""),
                             ua.VariantType.LocalizedText)
            await self.write(cond.child("ClientUserId"), caller.display_user, ua.VariantType.String)
            return []

        return acknowledge

    def condition_changed(self, cond: Condition) -> None:
        node = self.conditions.get(cond.name)
        if node is not None:
            snapshot = Condition(cond.name, cond.message, cond.active, cond.acked, cond.enabled, cond.comment)
            self.app.publisher.submit(lambda: self.publish_condition(node, snapshot, fire=True))

    async def publish_condition(self, node: ConditionNode, cond: Condition, *, fire: bool) -> None:
        now = _now()
        event_id = uuid.uuid4().bytes
        node.event_ids.append(event_id)
        retain = cond.enabled and (cond.active or not cond.acked)
        # A disabled condition reports nothing, except the event that says it was disabled (OPC 10000-9).
        fire = fire and (cond.enabled or node.reported_enabled)
        node.reported_enabled = cond.enabled
        enabled_state = ua.LocalizedText("Enabled" if cond.enabled else "Disabled", "en")
        message = ua.LocalizedText(
            f"{cond.name}: {cond.message or cond.name}" if cond.active else f"{cond.name} cleared", "en"
        )
        values = {
            "EventId": (event_id, ua.VariantType.ByteString),
            "Time": (now, ua.VariantType.DateTime),
            "ReceiveTime": (now, ua.VariantType.DateTime),
            "Message": (message, ua.VariantType.LocalizedText),
            "Retain": (retain, ua.VariantType.Boolean),
            "ActiveState": (
                ua.LocalizedText("Active" if cond.active else "Inactive", "en"), ua.VariantType.LocalizedText
            ),
            "ActiveState/Id": (cond.active, ua.VariantType.Boolean),
            "AckedState": (
                ua.LocalizedText("Acknowledged" if cond.acked else "Unacknowledged", "en"), ua.VariantType.LocalizedText
            ),
            "AckedState/Id": (cond.acked, ua.VariantType.Boolean),
            "EnabledState": (enabled_state, ua.VariantType.LocalizedText),
            "EnabledState/Id": (cond.enabled, ua.VariantType.Boolean),
            "Comment": (ua.LocalizedText(cond.comment), ua.VariantType.LocalizedText),
        }
        for child, (value, vtype) in values.items():
            with contextlib.suppress(KeyError):
                await self.write(node.child(child), value, vtype)
        if not fire or node.event is None:
            return
        ev = node.event
        ev.EventId = event_id
        ev.Time = now
        ev.ReceiveTime = now
        ev.Severity = ALARM_SEVERITY
        ev.SourceNode = node.source
        ev.SourceName = self.controller.part.name
        ev.Message = message
        fields = {
            "NodeId": (node.node, ua.VariantType.NodeId),
            "ConditionName": (cond.name, ua.VariantType.String),
            "BranchId": (ua.NodeId(), ua.VariantType.NodeId),
            "Retain": (retain, ua.VariantType.Boolean),
            "EnabledState": values["EnabledState"],
            "EnabledState/Id": values["EnabledState/Id"],
            "Comment": values["Comment"],
            "ActiveState": values["ActiveState"],
            "ActiveState/Id": values["ActiveState/Id"],
            "AckedState": values["AckedState"],
            "AckedState/Id": values["AckedState/Id"],
        }
        for name, (value, vtype) in fields.items():
            setattr(ev, name, value)
            ev.data_types[name] = vtype
        service = self.app.server.iserver.isession.subscription_service
        for source in (node.node, self.controller.node, ua.NodeId(ua.ObjectIds.Server)):
            ev.emitting_node = source
            await service.trigger_event(ev)
        ev.emitting_node = node.node

    async def setup_simulate_alarm(self) -> None:
        equipment = self.cell.equipment
        if not hasattr(equipment, "raise_alarm"):
            return
        inputs = (
            ("Name", ua.VariantType.String, "alarm name (a condition in SystemOperation/Conditions)"),
            ("Active", ua.VariantType.Boolean, "true raises the alarm, false clears it"),
        )
        nodeid = ua.NodeId(f"{self.controller.path}.{SIMULATE_ALARM}", self.ns)

        async def simulate(caller, name: str, active: bool) -> list:
            if name not in equipment.alarm_names:
                raise CallError("BadInvalidArgument", f"no alarm {name!r}", argument=0)
            log.warning("%s %s alarm %s", caller.display_user, "raises" if active else "clears", name)
            if active:
                equipment.raise_alarm(name, f"{name} (simulated by {caller.display_user})")
            else:
                equipment.clear_alarm(name)
            return []

        await self.app.dispatcher.add_method(
            self.controller.node, nodeid, ua.QualifiedName(SIMULATE_ALARM, self.ns), inputs, Family.CONDITION, simulate
        )

    # --- the arm ---------------------------------------------------------------------------------
    async def setup_arm(self) -> None:
        if self.arm is None:
            return
        self.axis_nodes: list[dict[str, ua.NodeId]] = []
        for i, _ in enumerate(self.cell.equipment.axes, start=1):
            try:
                axis = self.child(self.arm.node, f"Axes/Axis{i}")
            except KeyError:
                break
            nodes = {}
            for key in ("ActualPosition", "ActualSpeed", "ActualAcceleration"):
                with contextlib.suppress(KeyError):
                    nodes[key] = self.child(axis, f"ParameterSet/{key}")
            self.axis_nodes.append(nodes)
            with contextlib.suppress(KeyError):
                await self.write(self.child(axis, "MotionProfile"), _ROTARY, ua.VariantType.Int32)
        with contextlib.suppress(KeyError):
            await self.write(self.child(self.arm.node, "ParameterSet/SpeedOverride"), 100.0, ua.VariantType.Double)
        self._last_axes: list[tuple[float, float]] | None = None
        await self.publish_axes(0.0)
        self._axis_task = asyncio.get_running_loop().create_task(self._sample_axes())

    async def _sample_axes(self) -> None:
        loop = asyncio.get_running_loop()
        last = loop.time()
        while True:
            await asyncio.sleep(AXIS_PERIOD)
            now = loop.time()
            dt, last = now - last, now
            try:
                states = [(round(a.position, 4), round(a.speed, 4)) for a in self.cell.equipment.axis_states()]
            except Exception:
                log.exception("reading the axes failed")
                continue
            if states != self._last_axes:
                self.app.publisher.submit(lambda dt=dt: self.publish_axes(dt))

    async def publish_axes(self, dt: float) -> None:
        states = [(round(a.position, 4), round(a.speed, 4)) for a in self.cell.equipment.axis_states()]
        previous = self._last_axes
        self._last_axes = states
        scale = getattr(self.cell.equipment, "time_scale", 1.0)
        for i, (nodes, (pos, speed)) in enumerate(zip(self.axis_nodes, states, strict=False)):
            if "ActualPosition" in nodes:
                await self.write(nodes["ActualPosition"], pos, ua.VariantType.Double)
            if "ActualSpeed" in nodes:
                await self.write(nodes["ActualSpeed"], speed, ua.VariantType.Double)
            if "ActualAcceleration" in nodes:
                accel = 0.0
                if previous is not None and dt > 0:
                    # Speeds are per simulated second; dt is real time.
                    accel = round((speed - previous[i][1]) / (dt / scale), 2)
                await self.write(nodes["ActualAcceleration"], accel, ua.VariantType.Double)

    # --- publishing ----------------------------------------------------------------------------
    def changed(self) -> None:
        # Coalesce: one pending publish job reads the latest model state when it runs.
        if not self._pending:
            self._pending = True
            self.app.publisher.submit(self.publish)

    async def publish(self) -> None:
        self._pending = False
        protected = self.protected_files()
        if protected != self._protected and self.files.directory is not None:
            # Writable/UserWritable of the files that became (un)protected.
            for relpath in protected ^ self._protected:
                self.files.directory.refresh(relpath)
        self._protected = protected
        for name, task in self.cell.tasks.items():
            node = self.task_parts[name].node
            params = {
                "ParameterSet/TaskProgramName": (task.program_name, ua.VariantType.String),
                "ParameterSet/TaskProgramLoaded": (task.program_loaded, ua.VariantType.Boolean),
                "ParameterSet/ExecutionMode": (int(task.execution_mode), ua.VariantType.Int32),
            }
            for path, (value, vtype) in params.items():
                with contextlib.suppress(KeyError):
                    await self.write(self.child(node, path), value, vtype)
            await self.sync_modules(name, task)
        if self.arm is not None:
            system = self.cell.system
            in_control = system.state in ("Ready", "Executing")
            for path, value in (("ParameterSet/InControl", in_control), ("ParameterSet/OnPath", in_control)):
                with contextlib.suppress(KeyError):
                    await self.write(self.child(self.arm.node, path), value, ua.VariantType.Boolean)
        # State changes outside calls (program end, power up) must update Executable too.
        await self.app.dispatcher.refresh_executable()

    def protected_files(self) -> set[str]:
        files: set[str] = set()
        for task in self.cell.tasks.values():
            if task.program_file is not None:
                files.add(task.program_file)
            files.update(m.relpath for m in task.modules if m.relpath is not None)
        return files

    def protect(self, relpath: str) -> bool:
        """The loaded programs and modules cannot be deleted, moved or overwritten."""
        return relpath in self.protected_files()

    async def close(self) -> None:
        if self._axis_task is not None:
            self._axis_task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._axis_task
        await self.cell.close()
        if self.files.directory is not None:
            await self.files.directory.close()


def _executable(model: Any, machine: str, method: str) -> Callable[[], bool]:
    return lambda: model.executable(machine, method)


# --- client writes ---------------------------------------------------------------------------------
# --- the binder ------------------------------------------------------------------------------------
def make_equipment(cfg: Any) -> RobotEquipment:
    """``[robot] equipment = "module:factory"`` called with the [robot] section, else the simulator."""
    if cfg.equipment:
        return load_factory(cfg.equipment, "robot")(cfg)  # type: ignore[return-value]
    # [robot] time_scale > 1 runs faster than real time; the simulator's scale is real s per simulated s.
    return SimulatedRobot(time_scale=1.0 / cfg.time_scale)


async def bind_robotics(app: Any) -> Callable[[], Awaitable[None]] | None:
    """Bind every controller of the cell (role ``controller``) with its task controls and arm."""
    controllers = app.cell.by_role("controller")
    if not controllers:
        return None
    bindings: list[RoboticsBinding] = []
    for controller in controllers:
        tasks = [t for t in app.cell.by_role("task_control") if t.path.startswith(controller.path + ".")]
        system_path = controller.path.split(".Controllers.")[0]
        arms = [m for m in app.cell.by_role("motion_device") if m.path.startswith(system_path + ".")]
        arm = arms[0] if arms else None
        root = Path(app.data_dir) / PROGRAMS_DIR
        if len(controllers) > 1:
            root = root / controller.part.name
        install_samples(root)
        store = FileStore(root)
        library = StoreLibrary(store)
        equipment = make_equipment(app.config.robot)
        cell = RobotCell(
            equipment,
            library,
            task_names=[t.part.name for t in tasks],
            motion_devices=[arm.part.name] if arm else (),
        )
        binding = RoboticsBinding(app, controller, tasks, arm, cell)
        binding.store = store
        store.protect = binding.protect
        await bind_programs(app, binding, store)
        await binding.setup()
        bindings.append(binding)
    # In-process tests and tools reach the model here.
    app.robot_cell = bindings[0].cell
    app.robotics = bindings[0]

    async def close() -> None:
        for b in bindings:
            await b.close()

    return close


async def bind_programs(app: Any, binding: RoboticsBinding, store: FileStore) -> None:
    """Bind Controller/Programs (a FileDirectoryType) to ``store``."""
    programs = binding.child(binding.controller.node, "Programs")
    binding.files.directory = await FileDirectoryBinding.create(app, programs, store)


__all__ = ["RoboticsBinding", "StoreLibrary", "bind_robotics", "install_samples", "make_equipment"]
