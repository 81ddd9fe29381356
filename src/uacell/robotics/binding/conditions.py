"""The alarm conditions in ``SystemOperation/Conditions`` (docs/decisions.md 18), bound by the shared
condition binding (``uacell.binding.conditions``), and SimulateAlarm."""

from __future__ import annotations

import logging
from collections.abc import Sequence
from typing import Any, Protocol, runtime_checkable

from asyncua import ua

from uacell.binding.conditions import ConditionNode, ConditionNodes, ConditionPlace
from uacell.core.errors import CallError
from uacell.core.roles import Family
from uacell.robotics.binding.shared import ControllerBinding, Handler
from uacell.ua.context import Caller

log = logging.getLogger(__name__)

SIMULATE_ALARM = "SimulateAlarm"


@runtime_checkable
class AlarmSimulation(Protocol):
    """Equipment that can raise and clear alarms on request (the simulator): SimulateAlarm is offered."""

    @property
    def alarm_names(self) -> Sequence[str]: ...

    def raise_alarm(self, name: str, message: str = "") -> None: ...

    def clear_alarm(self, name: str) -> None: ...


class Conditions:
    """The conditions of one controller's SystemOperation."""

    def __init__(self, binding: ControllerBinding) -> None:
        self.binding = binding
        self.bound: ConditionNodes | None = None

    @property
    def nodes(self) -> dict[str, ConditionNode]:
        """The condition nodes by name (none before ``setup``)."""
        return self.bound.nodes if self.bound is not None else {}

    async def setup(self) -> None:
        b = self.binding
        system = b.cell.system
        so_node = b.child(b.controller.node, "SystemOperation")
        place = ConditionPlace(
            folder=b.child(so_node, "Conditions"),
            notifier=so_node,
            source=b.controller.node,
            source_name=b.controller.part.name,
            path=f"{b.controller.path}.SystemOperation.Conditions",
        )

        # Their Executable depends on the conditions alone: a scope of their own, refreshed after their
        # calls and whenever a condition changes, not after every change of the controller (as PackML's).
        def bind(node: ua.NodeId, method: str, handler: Handler, executable: Any) -> None:
            b.bind_method(
                node, method, Family.CONDITION, handler, executable, system.machine, b.controller.node, scope=system
            )

        system.condition_listeners.append(lambda _condition: b.app.dispatcher.touch(system))

        self.bound = ConditionNodes(b.app, system, place, bind)
        await self.bound.setup()
        await self._setup_simulate_alarm()

    async def _setup_simulate_alarm(self) -> None:
        b = self.binding
        equipment = b.cell.equipment
        if not isinstance(equipment, AlarmSimulation):
            return
        inputs = (
            ("Name", ua.VariantType.String, "alarm name (a condition in SystemOperation/Conditions)"),
            ("Active", ua.VariantType.Boolean, "true raises the alarm, false clears it"),
        )
        nodeid = ua.NodeId(f"{b.controller.path}.{SIMULATE_ALARM}", b.ns)

        async def simulate(caller: Caller, name: str, active: bool) -> list[Any]:
            if name not in equipment.alarm_names:
                raise CallError("BadInvalidArgument", f"no alarm {name!r}", argument=0)
            log.warning("%s %s alarm %s", caller.display_user, "raises" if active else "clears", name)
            if active:
                equipment.raise_alarm(name, f"{name} (simulated by {caller.display_user})")
            else:
                equipment.clear_alarm(name)
            return []

        await b.app.dispatcher.add_method(
            b.controller.node, nodeid, ua.QualifiedName(SIMULATE_ALARM, b.ns), inputs, Family.CONDITION, simulate
        )

    async def publish(self) -> None:
        pass

    async def close(self) -> None:
        pass
