"""What every concern of a controller's binding shares: its nodes, models and helpers.

``core.RoboticsBinding`` composes the concerns (programs, task controls, SystemOperation, conditions,
arm) on top of ``ControllerBinding``; each concern receives the ``ControllerBinding`` and never
imports ``core`` back.
"""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from typing import TYPE_CHECKING, Any, Protocol

from asyncua import ua

from uacell.binding.cell import BuiltPart
from uacell.core.file_store import FileStore
from uacell.core.fsm import StateMachine
from uacell.core.roles import Family
from uacell.robotics.config import STOP_MODE_NAMES
from uacell.robotics.equipment import StopMode
from uacell.robotics.model import RobotCell

if TYPE_CHECKING:
    from uacell.host import BinderHost

Handler = Callable[..., Awaitable[list[Any]]]


class Concern(Protocol):
    """One concern of a controller's binding (programs, task controls, ...)."""

    async def setup(self) -> None: ...

    async def publish(self) -> None: ...

    async def close(self) -> None: ...


class ControllerBinding:
    """One controller's part, models and nodes, and the helpers its concerns bind them with."""

    def __init__(
        self,
        app: BinderHost,
        controller: BuiltPart,
        tasks: list[BuiltPart],
        arm: BuiltPart | None,
        cell: RobotCell,
        store: FileStore,
    ) -> None:
        self.app = app
        self.controller = controller
        self.task_parts = {t.part.name: t for t in tasks}
        self.arm = arm
        self.cell = cell
        self.store = store
        self.ns: int = app.cell.instantiator.ns
        self.values = app.space.value_writer(app.dispatcher.types.builtin_of)
        self._children: dict[tuple[ua.NodeId, str], ua.NodeId] = {}
        self.compose()

    def compose(self) -> None:
        """Make the concerns (``core.RoboticsBinding``); none here."""

    # --- helpers every concern uses -----------------------------------------------------------
    def child(self, node: ua.NodeId, path: str) -> ua.NodeId:
        """The node at BrowseName ``path`` below ``node`` (KeyError if none), looked up once: the
        publishing concerns ask for the same few after every change (``forget_children`` when nodes
        are deleted)."""
        key = (node, path)
        found = self._children.get(key)
        if found is None:
            found = self._children[key] = self.app.cell.child(node, path)
        return found

    def forget_children(self) -> None:
        self._children.clear()

    async def bind_machine(self, node: ua.NodeId, machine: StateMachine) -> None:
        await self.app.space.bind_machine(node, machine, self.app.publisher, self.app.refs)

    def bind_method(
        self,
        obj: ua.NodeId,
        name: str,
        family: Family,
        handler: Handler,
        executable: Callable[[], bool] | None,
        serialize_on: object,
        element: ua.NodeId,
        scope: object | None = None,
    ) -> None:
        """Bind a method of this controller; its Executable is re-evaluated with ``scope`` (by default
        the controller's cell: whatever changes in it)."""
        d = self.app.dispatcher
        d.bind(
            obj, d.method_of(obj, name), family, handler,
            executable=executable, serialize_on=serialize_on, element=element,
            scope=self.cell if scope is None else scope,
        )  # fmt: skip

    async def publish_stop_modes(
        self, machine_node: ua.NodeId, possible: tuple[StopMode, ...], default: StopMode
    ) -> None:
        values = [
            ua.EnumValueType(
                Value=int(m),
                DisplayName=ua.LocalizedText(STOP_MODE_NAMES.get(m, m.name), "en"),
                Description=ua.LocalizedText(),
            )
            for m in possible
        ]
        for child, value, vtype in (
            ("PossibleStopModes", values, ua.VariantType.ExtensionObject),
            ("ConfiguredDefaultStopMode", int(default), ua.VariantType.Int16),
        ):
            try:
                target = self.child(machine_node, child)
            except KeyError:
                continue
            await self.values.write(target, value, vtype, force=True)
            # Fixed by configuration: a client write would not change the behaviour.
            await self.values.set_access(target, ua.AccessLevel.CurrentRead.mask)


def executable(model: Any, machine: str, method: str) -> Callable[[], bool]:
    return lambda: bool(model.executable(machine, method))
