"""The alarm conditions in ``SystemOperation/Conditions`` (docs/decisions.md 18) and SimulateAlarm."""

from __future__ import annotations

import contextlib
import functools
import logging
import uuid
from collections import deque
from collections.abc import Sequence
from datetime import UTC, datetime
from typing import Any, Protocol, runtime_checkable

from asyncua import ua

from uacell.errors import CallError
from uacell.robotics.binding.shared import ControllerBinding, Handler
from uacell.robotics.model import Condition
from uacell.roles import Family
from uacell.ua.context import Caller
from uacell.ua.instantiate import Selection
from uacell.ua.toolkit import EventEmitter

log = logging.getLogger(__name__)

SIMULATE_ALARM = "SimulateAlarm"
ALARM_SEVERITY = 800


@runtime_checkable
class AlarmSimulation(Protocol):
    """Equipment that can raise and clear alarms on request (the simulator): SimulateAlarm is offered."""

    @property
    def alarm_names(self) -> Sequence[str]: ...

    def raise_alarm(self, name: str, message: str = "") -> None: ...

    def clear_alarm(self, name: str) -> None: ...


def _unacked(condition: Condition) -> bool:
    return condition.enabled and not condition.acked


def _enabled(condition: Condition) -> bool:
    return condition.enabled


def _disabled(condition: Condition) -> bool:
    return not condition.enabled


class ConditionNode:
    """One AlarmConditionType instance mirroring a model ``Condition``."""

    def __init__(self, binding: ControllerBinding, name: str, node: ua.NodeId, source: ua.NodeId) -> None:
        self.binding = binding
        self.name = name
        self.node = node
        self.source = source
        self.event_ids: deque[bytes] = deque(maxlen=32)
        self.emitter: EventEmitter | None = None
        self.reported_enabled = True

    def child(self, path: str) -> ua.NodeId:
        return self.binding.child(self.node, path)


class Conditions:
    """The conditions of one controller's SystemOperation."""

    def __init__(self, binding: ControllerBinding) -> None:
        self.binding = binding
        self.nodes: dict[str, ConditionNode] = {}

    async def setup(self) -> None:
        b = self.binding
        system = b.cell.system
        so_node = b.child(b.controller.node, "SystemOperation")
        folder = b.child(so_node, "Conditions")
        type_node = ua.NodeId(ua.ObjectIds.AlarmConditionType)
        for name in system.conditions:
            path = f"{b.controller.path}.SystemOperation.Conditions.{name}"
            node = b.app.cell.instantiator.create(
                folder, type_node, ua.QualifiedName(name, b.ns), Selection(()),
                reference_type=ua.ObjectIds.Organizes, path=path,
            )  # fmt: skip
            await b.app.space.node(so_node).add_reference(node, ua.ObjectIds.HasCondition, True, True)
            cond = ConditionNode(b, name, node, b.controller.node)
            self.nodes[name] = cond
            static = {
                "EventType": (type_node, ua.VariantType.NodeId),
                "SourceNode": (b.controller.node, ua.VariantType.NodeId),
                "SourceName": (b.controller.part.name, ua.VariantType.String),
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
                    await b.values.write(b.child(node, child), value, vtype, force=True)
            cond.emitter = await b.app.space.emitter(type_node, node)
            model = system.conditions[name]
            await self.publish_condition(cond, model, fire=False)
            b.bind_method(
                node, "Acknowledge", Family.CONDITION, self._acknowledge(cond),
                functools.partial(_unacked, model), system.machine, b.controller.node,
            )  # fmt: skip
            # OPC 10000-9 ConditionType AddComment, Enable, Disable
            for method, handler, executable in (
                ("AddComment", self._add_comment(cond), functools.partial(_enabled, model)),
                ("Enable", self._set_enabled(cond, True), functools.partial(_disabled, model)),
                ("Disable", self._set_enabled(cond, False), functools.partial(_enabled, model)),
            ):
                b.bind_method(node, method, Family.CONDITION, handler, executable, system.machine, b.controller.node)
        system.condition_listeners.append(self.condition_changed)
        await self._setup_simulate_alarm()

    def _acknowledge(self, cond: ConditionNode) -> Handler:
        b = self.binding

        async def acknowledge(caller: Caller, event_id: bytes, comment: ua.LocalizedText) -> list[Any]:
            if event_id not in cond.event_ids:
                raise CallError("BadEventIdUnknown", f"no event {event_id!r} of {cond.name}", argument=0)
            text = comment.Text if isinstance(comment, ua.LocalizedText) else ""
            b.cell.system.acknowledge(cond.name, text or "")
            written = comment if isinstance(comment, ua.LocalizedText) else ua.LocalizedText("")
            await b.values.write(cond.child("Comment"), written, ua.VariantType.LocalizedText)
            await b.values.write(cond.child("ClientUserId"), caller.display_user, ua.VariantType.String)
            return []

        return acknowledge

    def _add_comment(self, cond: ConditionNode) -> Handler:
        b = self.binding

        async def add_comment(caller: Caller, event_id: bytes, comment: ua.LocalizedText) -> list[Any]:
            if event_id not in cond.event_ids:
                raise CallError("BadEventIdUnknown", f"no event {event_id!r} of {cond.name}", argument=0)
            text = (comment.Text or "") if isinstance(comment, ua.LocalizedText) else ""
            b.cell.system.add_comment(cond.name, text)
            await b.values.write(cond.child("ClientUserId"), caller.display_user, ua.VariantType.String)
            return []

        return add_comment

    def _set_enabled(self, cond: ConditionNode, enabled: bool) -> Handler:
        b = self.binding

        async def set_enabled(caller: Caller) -> list[Any]:
            b.cell.system.set_enabled(cond.name, enabled)
            log.warning("%s %s condition %s", caller.display_user, "enables" if enabled else "disables", cond.name)
            return []

        return set_enabled

    def condition_changed(self, cond: Condition) -> None:
        node = self.nodes.get(cond.name)
        if node is not None:
            snapshot = Condition(cond.name, cond.message, cond.active, cond.acked, cond.enabled, cond.comment)

            async def publish() -> None:
                await self.publish_condition(node, snapshot, fire=True)

            self.binding.app.publisher.submit(publish)

    async def publish_condition(self, node: ConditionNode, cond: Condition, *, fire: bool) -> None:
        b = self.binding
        now = datetime.now(UTC)
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
        active = ua.LocalizedText("Active" if cond.active else "Inactive", "en")
        acked = ua.LocalizedText("Acknowledged" if cond.acked else "Unacknowledged", "en")
        states: dict[str, tuple[Any, ua.VariantType]] = {
            "ActiveState": (active, ua.VariantType.LocalizedText),
            "ActiveState/Id": (cond.active, ua.VariantType.Boolean),
            "AckedState": (acked, ua.VariantType.LocalizedText),
            "AckedState/Id": (cond.acked, ua.VariantType.Boolean),
            "EnabledState": (enabled_state, ua.VariantType.LocalizedText),
            "EnabledState/Id": (cond.enabled, ua.VariantType.Boolean),
            "Comment": (ua.LocalizedText(cond.comment), ua.VariantType.LocalizedText),
        }
        values: dict[str, tuple[Any, ua.VariantType]] = {
            "EventId": (event_id, ua.VariantType.ByteString),
            "Time": (now, ua.VariantType.DateTime),
            "ReceiveTime": (now, ua.VariantType.DateTime),
            "Message": (message, ua.VariantType.LocalizedText),
            "Retain": (retain, ua.VariantType.Boolean),
            **states,
        }
        for child, (value, vtype) in values.items():
            with contextlib.suppress(KeyError):
                await b.values.write(node.child(child), value, vtype)
        if not fire or node.emitter is None:
            return
        fields: dict[str, tuple[Any, ua.VariantType]] = {
            "NodeId": (node.node, ua.VariantType.NodeId),
            "ConditionName": (cond.name, ua.VariantType.String),
            "BranchId": (ua.NodeId(), ua.VariantType.NodeId),
            "Retain": (retain, ua.VariantType.Boolean),
            **states,
        }
        await node.emitter.fire(
            (node.node, b.controller.node, ua.NodeId(ua.ObjectIds.Server)),
            fields,
            EventId=event_id,
            Time=now,
            ReceiveTime=now,
            Severity=ALARM_SEVERITY,
            SourceNode=node.source,
            SourceName=b.controller.part.name,
            Message=message,
        )

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
