"""TaskControls: their machines and methods, ParameterSet, TaskModules, MotionDevicesUnderControl.

Beside the standard ParameterSet variables, each TaskControl gets two server-defined read-only ones in
uacell's namespace: ``ParameterSet/CurrentLine`` and ``ParameterSet/ProgramPointer`` (docs/robotics.md).
"""

from __future__ import annotations

import contextlib
import functools
import logging

from asyncua import ua

from uacell.binding.writes import WriteHook
from uacell.core.errors import CallError
from uacell.core.roles import Role
from uacell.robotics.binding.programs import Programs
from uacell.robotics.binding.shared import ControllerBinding, Handler, executable
from uacell.robotics.companion import TASK_CONTROL
from uacell.robotics.model import Status, TaskControl
from uacell.ua.context import Caller
from uacell.ua.instantiate import Selection

log = logging.getLogger(__name__)
_MACHINE = "TaskControlOperation/TaskControlStateMachine"
_A = ua.AttributeIds
# Server-defined ParameterSet variables (uacell's namespace): BrowseName -> Description.
PROGRAM_POSITION = {
    "CurrentLine": "uacell: the source line of the program instruction being executed (0: none is executing)",
    "ProgramPointer": "uacell: the step of the loaded program being executed, or the step Start resumes from"
    " (0: the program start)",
}


class TaskControls:
    """Every TaskControl of one controller."""

    def __init__(self, binding: ControllerBinding, programs: Programs) -> None:
        self.binding = binding
        self.programs = programs
        self.module_nodes: dict[str, dict[str, ua.NodeId]] = {name: {} for name in binding.task_parts}
        self._position_pending: set[str] = set()  # tasks with a position write submitted, not yet run

    def machine_node(self, task: str) -> ua.NodeId:
        b = self.binding
        return b.child(b.task_parts[task].node, _MACHINE)

    async def setup(self) -> None:
        b = self.binding
        for name, task in b.cell.tasks.items():
            node = self.machine_node(name)
            await b.bind_machine(node, task.machine)
            # Which methods each machine has is the NodeSet's (HasCause); the handlers are ours.
            nodes = {task.machine.name: node, task.ready.name: b.child(node, task.ready.name)}
            for machine, method in task.methods():
                b.bind_method(
                    nodes[machine], method, TASK_CONTROL, self._handler(task, method),
                    executable(task, machine, method), task.machine, b.task_parts[name].node,
                )  # fmt: skip
            await self._setup_parameters(name, task)
            await self._add_program_position(name)
            await b.publish_stop_modes(node, task.possible_stop_modes, task.default_stop_mode)
            # The model notifies its listeners on every step of a run (and on every other change).
            task.listeners.append(functools.partial(self._position_changed, name))

    async def _setup_parameters(self, name: str, task: TaskControl) -> None:
        b = self.binding
        part = b.task_parts[name]
        op = b.child(part.node, "TaskControlOperation")
        if b.arm is not None:
            await b.values.write(b.child(op, "MotionDevicesUnderControl"), [b.arm.node], ua.VariantType.NodeId)
            controls = self.controls_reference()
            if controls is not None:
                await b.app.space.add_reference(part.node, b.arm.node, controls)
        with contextlib.suppress(KeyError):
            mode_node = b.child(part.node, "ParameterSet/ExecutionMode")
            await b.values.set_access(mode_node, ua.AccessLevel.CurrentRead.mask | ua.AccessLevel.CurrentWrite.mask)
            b.app.writes.route(mode_node, self._execution_mode_writer(task), Role.OPERATOR)

    async def _add_program_position(self, name: str) -> None:
        """``ParameterSet/CurrentLine`` and ``ParameterSet/ProgramPointer``: UInt32, read-only, uacell's."""
        b = self.binding
        part = b.task_parts[name]
        params = b.child(part.node, "ParameterSet")
        for browse_name, text in PROGRAM_POSITION.items():
            var = await b.app.space.add_variable(
                params,
                ua.NodeId(f"{part.path}.ParameterSet.{browse_name}", b.ns),
                ua.QualifiedName(browse_name, b.ns),
                ua.Variant(0, ua.VariantType.UInt32),
                datatype=ua.NodeId(ua.ObjectIds.UInt32),
            )
            description = ua.Variant(ua.LocalizedText(text), ua.VariantType.LocalizedText)
            await b.app.space.write(var, _A.Description, description)

    def _position_changed(self, name: str) -> None:
        # Called on every step of a run: one pending write per task, reading the latest position.
        if name not in self._position_pending:
            self._position_pending.add(name)
            self.binding.app.publisher.submit(functools.partial(self._publish_position, name))

    async def _publish_position(self, name: str) -> None:
        self._position_pending.discard(name)
        b = self.binding
        task = b.cell.tasks[name]
        node = b.task_parts[name].node
        # ValueWriter skips a value equal to the last one written: only changes reach subscribers.
        await b.values.write(b.child(node, "ParameterSet/CurrentLine"), task.current_line, ua.VariantType.UInt32)
        await b.values.write(b.child(node, "ParameterSet/ProgramPointer"), task.pointer, ua.VariantType.UInt32)

    def controls_reference(self) -> ua.NodeId | None:
        """Robotics' ``Controls`` ReferenceType (found by BrowseName, not by a hard-coded id)."""
        try:
            return self.binding.app.cell.type_node("Robotics", "Controls", root=ua.ObjectIds.References)
        except KeyError:
            log.warning("the Robotics model has no Controls reference type")
            return None

    def _handler(self, task: TaskControl, method: str) -> Handler:
        programs = self.programs

        async def load_by_node_id(caller: Caller, id_: ua.ExpandedNodeId) -> list[int]:
            name = programs.controller_program_of(id_)
            if name is not None:
                return [await task.load_controller_program(name)]
            return [await task.load_file(programs.file_of(id_))]

        async def load_by_name(caller: Caller, name: str) -> list[int]:
            return [await task.load_by_name(name or "")]

        async def unload_program(caller: Caller) -> list[int]:
            return [await task.unload_program()]

        async def unload_by_node_id(caller: Caller, id_: ua.ExpandedNodeId) -> list[int]:
            nodeid = programs.local_nodeid(id_)
            for module, node in self.module_nodes[task.name].items():
                if node == nodeid:
                    return [await task.unload_module(module)]
            return [await task.unload_by_file(programs.file_of(id_))]

        async def unload_by_name(caller: Caller, name: str) -> list[int]:
            return [await task.unload_by_name(name or "")]

        async def start(caller: Caller) -> list[int]:
            return [await task.start()]

        async def stop(caller: Caller, mode: int) -> list[int]:
            return [await task.stop(int(mode))]

        async def reset(caller: Caller) -> list[int]:
            return [await task.reset_to_program_start()]

        handlers: dict[str, Handler] = {
            "ResetToProgramStart": reset,
            "LoadByNodeId": load_by_node_id,
            "LoadByName": load_by_name,
            "UnloadProgram": unload_program,
            "UnloadByNodeId": unload_by_node_id,
            "UnloadByName": unload_by_name,
            "Start": start,
            "Stop": stop,
        }
        return handlers[method]

    def _execution_mode_writer(self, task: TaskControl) -> WriteHook:
        app = self.binding.app

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
            await app.settle()
            return ua.StatusCode(ua.StatusCodes.Good)

        return write

    # --- publishing --------------------------------------------------------------------------------
    async def publish(self) -> None:
        b = self.binding
        for name, task in b.cell.tasks.items():
            node = b.task_parts[name].node
            params = {
                "ParameterSet/TaskProgramName": (task.program_name, ua.VariantType.String),
                "ParameterSet/TaskProgramLoaded": (task.program_loaded, ua.VariantType.Boolean),
                "ParameterSet/ExecutionMode": (int(task.execution_mode), ua.VariantType.Int32),
            }
            for path, (value, vtype) in params.items():
                with contextlib.suppress(KeyError):
                    await b.values.write(b.child(node, path), value, vtype)
            await self._publish_position(name)
            await self._sync_modules(name, task)

    async def _sync_modules(self, name: str, task: TaskControl) -> None:
        b = self.binding
        folder = b.child(b.task_parts[name].node, "TaskModules")
        nodes = self.module_nodes[name]
        loaded = {m.name: m for m in task.modules}
        for gone in [m for m in nodes if m not in loaded]:
            node = nodes.pop(gone)
            await b.app.space.delete([node])
            b.values.forget_below(node)
            b.forget_children()
        type_node = b.app.cell.type_node("Robotics", "TaskModuleType")
        for module in loaded.values():
            node = nodes.get(module.name)
            if node is None:
                path = f"{b.task_parts[name].path}.TaskModules.{module.name}"
                node = b.app.cell.instantiator.create(
                    folder, type_node, ua.QualifiedName(module.name, b.ns), Selection(("**",)),
                    reference_type=ua.ObjectIds.Organizes, path=path,
                )  # fmt: skip
                nodes[module.name] = node
            await b.values.write(b.child(node, "Name"), module.name, ua.VariantType.String)
            with contextlib.suppress(KeyError):
                await b.values.write(b.child(node, "Version"), module.version, ua.VariantType.String)
            with contextlib.suppress(KeyError):
                await b.values.write(b.child(node, "IsReferenced"), module.is_referenced, ua.VariantType.Boolean)

    async def close(self) -> None:
        pass
