"""Alarm conditions on their nodes: each ``uacell.core.conditions.Condition`` of a part as an
AlarmConditionType instance (OPC 10000-9) with its events, Acknowledge, AddComment, Enable and
Disable. The one binding of conditions for every companion: where the nodes go is a
``ConditionPlace``, how a method is bound (its role family, lock and serialization) the companion's
``MethodBinder``."""

from __future__ import annotations

import contextlib
import functools
import logging
from collections import deque
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import TYPE_CHECKING, Any

from asyncua import ua

from uacell.core.conditions import Condition, ConditionSet
from uacell.core.errors import CallError
from uacell.ua import toolkit
from uacell.ua.context import Caller
from uacell.ua.instantiate import Selection
from uacell.ua.toolkit import EventEmitter

if TYPE_CHECKING:
    from uacell.host import BinderHost

log = logging.getLogger(__name__)

ALARM_SEVERITY = 800
Handler = Callable[..., Awaitable[list[Any]]]
# (condition node, method name, handler, executable): binds one of the condition's methods
MethodBinder = Callable[[ua.NodeId, str, Handler, Callable[[], bool]], None]


@dataclass(frozen=True)
class ConditionPlace:
    """Where a part's conditions go."""

    folder: ua.NodeId  # they are organized here
    notifier: ua.NodeId  # the object that has them (HasCondition)
    source: ua.NodeId  # SourceNode of their events
    source_name: str  # SourceName of their events
    path: str  # their NodeIds are "<path>.<name>"


def _unacked(condition: Condition) -> bool:
    return condition.enabled and not condition.acked


def _enabled(condition: Condition) -> bool:
    return condition.enabled


def _disabled(condition: Condition) -> bool:
    return not condition.enabled


class ConditionNode:
    """One AlarmConditionType instance mirroring a model ``Condition``."""

    def __init__(self, app: BinderHost, name: str, node: ua.NodeId, source: ua.NodeId) -> None:
        self.app = app
        self.name = name
        self.node = node
        self.source = source
        self.event_ids: deque[bytes] = deque(maxlen=32)
        self.emitter: EventEmitter | None = None
        self.reported_enabled = True

    def child(self, path: str) -> ua.NodeId:
        return self.app.cell.child(self.node, path)


class ConditionNodes:
    """The conditions of one part (``model``) at ``place``."""

    def __init__(self, app: BinderHost, model: ConditionSet, place: ConditionPlace, bind: MethodBinder) -> None:
        self.app, self.model, self.place, self.bind = app, model, place, bind
        self.values = app.space.value_writer(app.dispatcher.types.builtin_of)
        self.nodes: dict[str, ConditionNode] = {}

    async def setup(self) -> None:
        app, place = self.app, self.place
        ns = app.cell.instantiator.ns
        type_node = ua.NodeId(ua.ObjectIds.AlarmConditionType)
        for name in self.model.conditions:
            node = app.cell.instantiator.create(
                place.folder, type_node, ua.QualifiedName(name, ns), Selection(()),
                reference_type=ua.ObjectIds.Organizes, path=f"{place.path}.{name}",
            )  # fmt: skip
            await app.space.add_reference(place.notifier, node, ua.ObjectIds.HasCondition)
            cond = ConditionNode(app, name, node, place.source)
            self.nodes[name] = cond
            static = {
                "EventType": (type_node, ua.VariantType.NodeId),
                "SourceNode": (place.source, ua.VariantType.NodeId),
                "SourceName": (place.source_name, ua.VariantType.String),
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
                    await self.values.write(cond.child(child), value, vtype, force=True)
            cond.emitter = await app.space.emitter(type_node, node)
            model = self.model.conditions[name]
            await self.publish_condition(cond, model, fire=False)
            self.bind(node, "Acknowledge", self._acknowledge(cond), functools.partial(_unacked, model))
            # OPC 10000-9 ConditionType AddComment, Enable, Disable
            for method, handler, executable in (
                ("AddComment", self._add_comment(cond), functools.partial(_enabled, model)),
                ("Enable", self._set_enabled(cond, True), functools.partial(_disabled, model)),
                ("Disable", self._set_enabled(cond, False), functools.partial(_enabled, model)),
            ):
                self.bind(node, method, handler, executable)
        self.model.condition_listeners.append(self.condition_changed)

    def _acknowledge(self, cond: ConditionNode) -> Handler:

        async def acknowledge(caller: Caller, event_id: bytes, comment: ua.LocalizedText) -> list[Any]:
            if event_id not in cond.event_ids:
                raise CallError("BadEventIdUnknown", f"no event {event_id!r} of {cond.name}", argument=0)
            text = comment.Text if isinstance(comment, ua.LocalizedText) else ""
            self.model.acknowledge(cond.name, text or "")
            written = comment if isinstance(comment, ua.LocalizedText) else ua.LocalizedText("")
            await self.values.write(cond.child("Comment"), written, ua.VariantType.LocalizedText)
            await self.values.write(cond.child("ClientUserId"), caller.display_user, ua.VariantType.String)
            return []

        return acknowledge

    def _add_comment(self, cond: ConditionNode) -> Handler:

        async def add_comment(caller: Caller, event_id: bytes, comment: ua.LocalizedText) -> list[Any]:
            if event_id not in cond.event_ids:
                raise CallError("BadEventIdUnknown", f"no event {event_id!r} of {cond.name}", argument=0)
            text = (comment.Text or "") if isinstance(comment, ua.LocalizedText) else ""
            self.model.add_comment(cond.name, text)
            await self.values.write(cond.child("ClientUserId"), caller.display_user, ua.VariantType.String)
            return []

        return add_comment

    def _set_enabled(self, cond: ConditionNode, enabled: bool) -> Handler:

        async def set_enabled(caller: Caller) -> list[Any]:
            self.model.set_enabled(cond.name, enabled)
            log.warning("%s %s condition %s", caller.display_user, "enables" if enabled else "disables", cond.name)
            return []

        return set_enabled

    def condition_changed(self, cond: Condition) -> None:
        node = self.nodes.get(cond.name)
        if node is not None:
            snapshot = Condition(cond.name, cond.message, cond.active, cond.acked, cond.enabled, cond.comment)

            async def publish() -> None:
                await self.publish_condition(node, snapshot, fire=True)

            self.app.publisher.submit(publish)

    async def publish_condition(self, node: ConditionNode, cond: Condition, *, fire: bool) -> None:
        now = datetime.now(UTC)
        event_id = toolkit.new_event_id()
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
                await self.values.write(node.child(child), value, vtype)
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
            (node.node, self.place.source, ua.NodeId(ua.ObjectIds.Server)),
            fields,
            EventId=event_id,
            Time=now,
            ReceiveTime=now,
            Severity=ALARM_SEVERITY,
            SourceNode=node.source,
            SourceName=self.place.source_name,
            Message=message,
        )
