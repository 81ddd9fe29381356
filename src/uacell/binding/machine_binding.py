"""The one state-machine binding: publishes a pure ``StateMachine`` on its OPC UA instance.

For every machine (TaskControl, SystemOperation and their sub-machines; the three PackML machines)
it keeps ``CurrentState`` (+``Id``, ``Number``) and ``LastTransition`` (+``Id``, ``Number``,
``TransitionTime``) current, with ``Id`` the State/Transition node *of the type*; fills
``AvailableStates``/``AvailableTransitions``; publishes ``LastTransitionReason`` where the type has
it; answers ``Bad_StateNotActive`` for an inactive sub-machine; and fires a ``TransitionEventType``
event for every transition to subscribers of the machine and of the Server object. A transition
that happens while a client's method call runs (``uacell.ua.context.current_call``) is that
client's: right after its TransitionEvent the machine also fires an ``AuditUpdateStateEventType``
event (OPC 10000-16) naming the user, the method and the old and new state. A transition that
completes a call after it returned runs in a copy of the call's context (decision 38) and is found
the same way.

Changes reach the address space through the one ordered ``Publisher`` (``uacell.binding.publisher``), so
that events and values keep the order in which the model produced them.
"""

from __future__ import annotations

import logging
from datetime import UTC, datetime
from typing import Any

from asyncua import Server, ua

from uacell.binding.publisher import Publisher
from uacell.core.fsm import Change, Reason, StateMachine
from uacell.models.tables import FsmTable, NodeRef
from uacell.ua import toolkit
from uacell.ua.context import MethodCall, current_call
from uacell.ua.toolkit import EventEmitter, ValueWriter

log = logging.getLogger(__name__)
_A = ua.AttributeIds
_VT = ua.VariantType
_NOT_ACTIVE = ua.StatusCode(ua.StatusCodes.BadStateNotActive)
# a machine whose equipment cannot be reached: its last known state, saying so (OPC 10000-4 7.38)
_STALE = ua.StatusCode(ua.StatusCodes.UncertainNoCommunicationLastUsableValue)
_REASON_TEXT = {reason: ua.LocalizedText(reason.name.title()) for reason in Reason}  # ValueAsText


class NodeRefs:
    """Translates NodeSet references (namespace URI, id) into this server's NodeIds."""

    def __init__(self, namespace_array: list[str]) -> None:
        self._index = {uri: i for i, uri in enumerate(namespace_array)}
        self._made: dict[NodeRef, ua.NodeId] = {}  # the states and transitions of the types bound: few

    def __call__(self, ref: NodeRef) -> ua.NodeId:
        node = self._made.get(ref)
        if node is None:
            node = self._made[ref] = ua.NodeId(ref[1], self._index[ref[0]])
        return node


class _DisplayNames(dict[str, ua.LocalizedText]):
    """The DisplayNames of a table's states and transitions by name, each read from its node the
    first time it is asked for (a start reads those of the states its machines are in, not all:
    from a snapshot, each state node read is loaded)."""

    def __init__(self, aspace: Any, table: FsmTable, refs: NodeRefs) -> None:
        super().__init__()
        self._aspace, self._table, self._refs = aspace, table, refs

    def __missing__(self, name: str) -> ua.LocalizedText:
        info = self._table.states.get(name) or self._table.transitions[name]
        data = self._aspace.get(self._refs(info.node))
        text = (
            ua.LocalizedText(str(info.node[1])) if data is None else data.attributes[_A.DisplayName].value.Value.Value
        )
        self[name] = text
        return text


class StateMachineBinding:
    """Publishes one machine (and, through ``bind_tree``, its sub-machines) on its instance node."""

    def __init__(
        self,
        server: Server,
        node: ua.NodeId,
        machine: StateMachine,
        refs: NodeRefs,
        publisher: Publisher,
        root: StateMachine | None = None,
    ) -> None:
        self.server = server
        self.aspace = server.iserver.aspace
        self.values = ValueWriter(self.aspace, lambda _datatype: None)
        self.node = node
        self.machine = machine
        self.root = root or machine  # the top machine of the tree: what the dispatcher knows it by
        self.refs = refs
        self.publisher = publisher
        self.children: list[StateMachineBinding] = []
        c = self._path
        self.current = c("CurrentState")
        self.current_id = c("CurrentState", "Id")
        self.current_number = c("CurrentState", "Number")
        self.last = c("LastTransition")
        self.last_id = c("LastTransition", "Id")
        self.last_number = c("LastTransition", "Number")
        self.last_time = c("LastTransition", "TransitionTime")
        self.reason = c("LastTransitionReason")
        self.reason_text = c("LastTransitionReason", "ValueAsText")
        self.available_states = c("AvailableStates")
        self.available_transitions = c("AvailableTransitions")
        self._event: EventEmitter | None = None
        self._audit: EventEmitter | None = None  # made on the first transition a call causes
        self._written: dict[int, tuple[Any, ...]] = {}  # id(node) -> what was last written there
        self._tree_queued = False  # a publish_tree is submitted and has not started yet
        self._display = _DisplayNames(self.aspace, machine.table, refs)

    def _path(self, *names: str) -> ua.NodeId | None:
        node: ua.NodeId | None = self.node
        for name in names:
            node = toolkit.find_child(self.aspace, node, name) if node is not None else None
        return node

    async def start(self) -> None:
        self._event = await EventEmitter.create(self.server, ua.ObjectIds.TransitionEventType, self.node)
        table = self.machine.table
        if self.available_states is not None:
            ids = [self.refs(s.node) for s in sorted(table.states.values(), key=lambda s: s.number)]
            await self._write([(self.available_states, ids, _VT.NodeId)])
        if self.available_transitions is not None:
            ids = [
                self.refs(t.node)
                for t in sorted(table.transitions.values(), key=lambda t: table.transition_number(t.name))
            ]
            await self._write([(self.available_transitions, ids, _VT.NodeId)])
        self.machine.listeners.append(self._on_change)
        await self.publish()

    def _on_change(self, change: Change) -> None:
        # The parent's state decides whether sub-machines are active: republish the whole subtree,
        # once for the changes made before the publisher gets to it (it reads the states then).
        self.publisher.touch(self.root)
        if not self._tree_queued:
            self._tree_queued = True
            self.publisher.submit(self._publish_queued_tree)
        if change.transition is not None:
            # The model moves its machines synchronously inside the call that causes a transition: the
            # call is known here, not later in the publisher's task.
            call = current_call()
            self.publisher.submit(lambda: self.fire(change, call))

    async def _publish_queued_tree(self) -> None:
        self._tree_queued = False
        await self.publish_tree()

    async def publish_tree(self) -> None:
        await self.publish()
        for child in self.children:
            await child.publish_tree()

    async def _write(
        self,
        values: list[tuple[ua.NodeId | None, Any, ua.VariantType]],
        status: ua.StatusCode | None = None,
        quality: ua.StatusCode | None = None,
    ) -> None:
        """Write each ``(node, value, vtype)`` (a list value: an array), or only ``status`` to each node
        when one is given, the value with ``quality`` when that is given (Uncertain); a node the
        machine's type does not have (None) is skipped."""
        # A machine's whole subtree is republished on every change: write only what changed (and make
        # the Variant only then). Keyed by the node objects of this binding, held for its lifetime.
        written = self._written
        for node, value, vtype in values:
            if node is None:
                continue
            key = (status.value,) if status is not None else (quality.value if quality else 0, vtype, value)
            if written.get(id(node)) == key:
                continue
            written[id(node)] = key
            if status is not None:
                await self.values.write_status(node, status)
            else:
                variant = ua.Variant(value, vtype, is_array=isinstance(value, list))
                await self.values.write(node, variant, force=True, status=quality)

    async def publish(self) -> None:
        m = self.machine
        active = m.active
        bad = None if active else _NOT_ACTIVE
        state = m.table.states[m.current]
        values = [
            (self.current, self._display[m.current], _VT.LocalizedText),
            (self.current_id, self.refs(state.node), _VT.NodeId),
            (self.current_number, state.number, _VT.UInt32),
        ]
        t = m.last_transition
        if t is None:
            # No transition yet: null values (Good for an active machine, as Part 16 allows).
            values += [(node, None, _VT.Null) for node in (self.last, self.last_id, self.last_number, self.last_time)]
        else:
            values += [
                (self.last, self._display[t.name], _VT.LocalizedText),
                (self.last_id, self.refs(t.node), _VT.NodeId),
                (self.last_number, m.table.transition_number(t.name), _VT.UInt32),
                (self.last_time, m.last_transition_time, _VT.DateTime),
            ]
        await self._write(values, bad, _STALE if active and m.stale else None)
        if self.reason is not None:
            reason = m.last_reason
            await self._write(
                [
                    (self.reason, int(reason), _VT.Int16),
                    (self.reason_text, _REASON_TEXT[reason], _VT.LocalizedText),
                ]
            )

    async def fire(self, change: Change, call: MethodCall | None = None) -> None:
        """Fire the TransitionEvent, to the machine's subscribers and to the Server object's; and after
        it, when ``call`` caused the transition, the AuditUpdateStateEvent naming the caller."""
        assert self._event is not None and change.transition is not None
        table = self.machine.table
        t = change.transition
        fields = {
            "Transition": (self._display[t.name], ua.VariantType.LocalizedText),
            "Transition/Id": (self.refs(t.node), ua.VariantType.NodeId),
            "FromState": (self._display[t.from_state], ua.VariantType.LocalizedText),
            "FromState/Id": (self.refs(table.states[t.from_state].node), ua.VariantType.NodeId),
            "ToState": (self._display[t.to_state], ua.VariantType.LocalizedText),
            "ToState/Id": (self.refs(table.states[t.to_state].node), ua.VariantType.NodeId),
        }
        message = f"{self.machine.name}: {t.name} ({t.from_state} to {t.to_state})"
        await self._event.fire(
            (self.node, ua.NodeId(ua.ObjectIds.Server)), fields, **self._base_fields(change, self.machine.name, message)
        )
        if call is not None:
            await self.audit(change, call)

    async def audit(self, change: Change, call: MethodCall) -> None:
        """The AuditUpdateStateEvent (OPC 10000-16 4.4.18) of a transition ``call`` caused."""
        assert change.transition is not None
        if self._audit is None:
            self._audit = await EventEmitter.create(self.server, ua.ObjectIds.AuditUpdateStateEventType, self.node)
        t = change.transition
        states = self.machine.table.states
        user = call.caller.user  # None for an anonymous session (OPC 10000-5 6.4.3: ClientUserId null)
        fields = {
            "ActionTimeStamp": (call.started, ua.VariantType.DateTime),
            "Status": (True, ua.VariantType.Boolean),
            "ServerId": (self.server.get_application_uri(), ua.VariantType.String),
            "ClientAuditEntryId": (call.audit_entry_id or None, ua.VariantType.String),
            "ClientUserId": (user, ua.VariantType.String),
            "ClientApplicationUri": (call.caller.client or None, ua.VariantType.String),
            "MethodId": (call.method_id, ua.VariantType.NodeId),
            "StatusCodeId": (ua.StatusCode(ua.StatusCodes.Good), ua.VariantType.StatusCode),
            "InputArguments": (list(call.inputs), ua.VariantType.Variant),
            "OldStateId": (self.refs(states[t.from_state].node), ua.VariantType.NodeId),
            "NewStateId": (self.refs(states[t.to_state].node), ua.VariantType.NodeId),
        }
        message = (
            f"{self.machine.name}: {t.name} ({t.from_state} to {t.to_state}) by {user or 'anonymous'}"
            f" calling {call.name}"
        )
        source = f"Method/{call.name}"  # OPC 10000-16 4.4.18
        await self._audit.fire(
            (self.node, ua.NodeId(ua.ObjectIds.Server)), fields, **self._base_fields(change, source, message)
        )

    def _base_fields(self, change: Change, source_name: str, message: str) -> dict[str, Any]:
        """The BaseEventType fields both events of a transition carry."""
        return {
            "EventId": ua.Variant(toolkit.new_event_id(), ua.VariantType.ByteString),
            "Time": change.time,
            "ReceiveTime": datetime.now(UTC),
            "Severity": 100,
            "SourceNode": self.node,
            "SourceName": source_name,
            "Message": ua.LocalizedText(message),
        }


async def bind_tree(
    server: Server,
    node: ua.NodeId,
    machine: StateMachine,
    publisher: Publisher,
    refs: NodeRefs | None = None,
    root: StateMachine | None = None,
) -> StateMachineBinding:
    """Bind ``machine`` on ``node`` and each sub-machine on the child of the same BrowseName."""
    refs = refs or NodeRefs(await server.get_namespace_array())
    binding = StateMachineBinding(server, node, machine, refs, publisher, root)
    for sub in machine.children:
        sub_node = toolkit.find_child(server.iserver.aspace, node, sub.name)
        if sub_node is None:
            raise KeyError(f"{machine.name} instance has no {sub.name}")
        binding.children.append(await bind_tree(server, sub_node, sub, publisher, refs, binding.root))
    await binding.start()
    return binding
