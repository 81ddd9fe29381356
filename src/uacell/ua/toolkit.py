"""The binding toolkit: the few address-space operations every binding needs, written once.

- ``find_child``/``child``: a child (any forward reference but HasTypeDefinition) by BrowseName name;
- ``supertype``/``subtypes``/``type_names``: walking the type hierarchy;
- ``ValueWriter``: writes Values typed by the variable's DataType, with timestamps, only when changed;
- ``EventEmitter``: one event of a type, fired to several notifiers (the source, its parents, Server).

Background tasks are run by ``uacell.core.background.Background``.
"""

from __future__ import annotations

import itertools
import os
from collections.abc import Callable, Iterable, Mapping
from datetime import UTC, datetime
from typing import Any

from asyncua import Server, ua
from asyncua.common.event_objects import IMPLEMENTED_EVENTS, Condition
from asyncua.server.address_space import AddressSpace, AttributeValue
from asyncua.server.event_generator import EventGenerator

_A = ua.AttributeIds
_VT_BYTE = ua.VariantType.Byte
_HAS_TYPE_DEFINITION = ua.NodeId(ua.ObjectIds.HasTypeDefinition)
_HAS_SUBTYPE = ua.NodeId(ua.ObjectIds.HasSubtype)


def find_child(aspace: AddressSpace, node: ua.NodeId, name: str) -> ua.NodeId | None:
    """The target of a forward reference of ``node`` (not HasTypeDefinition) whose BrowseName is ``name``."""
    data = aspace.get(node)
    if data is None:
        return None
    for ref in data.references:
        if ref.IsForward and ref.BrowseName.Name == name and ref.ReferenceTypeId != _HAS_TYPE_DEFINITION:
            target: ua.NodeId = ref.NodeId
            return target
    return None


def children(aspace: AddressSpace, node: ua.NodeId) -> list[tuple[str, ua.NodeId]]:
    """``node``'s children as (BrowseName, NodeId): every forward reference but HasTypeDefinition
    (AddIns too), as ``find_child`` follows them; for ``uacell.core.datasets.resolve``."""
    data = aspace.get(node)
    if data is None:
        return []
    return [
        (r.BrowseName.Name, r.NodeId)
        for r in data.references
        if r.IsForward and r.ReferenceTypeId != _HAS_TYPE_DEFINITION
    ]


def child(aspace: AddressSpace, node: ua.NodeId, path: str) -> ua.NodeId:
    """Follow a BrowseName path (``"A/B"``, names without namespace) down from ``node``; KeyError if absent."""
    for name in (p for p in path.split("/") if p):
        found = find_child(aspace, node, name)
        if found is None:
            raise KeyError(f"{node} has no child {name!r}")
        node = found
    return node


def supertype(aspace: AddressSpace, type_id: ua.NodeId) -> ua.NodeId | None:
    """The type ``type_id`` is a subtype of (None for a root or an unknown node)."""
    data = aspace.get(type_id)
    if data is None:
        return None
    for ref in data.references:
        if not ref.IsForward and ref.ReferenceTypeId == _HAS_SUBTYPE:
            parent: ua.NodeId = ref.NodeId
            return parent
    return None


def subtypes(aspace: AddressSpace, root: ua.NodeId) -> set[ua.NodeId]:
    """``root`` and every type below it."""
    out, todo = {root}, [root]
    while todo:
        for ref in aspace[todo.pop()].references:
            if ref.IsForward and ref.ReferenceTypeId == _HAS_SUBTYPE and ref.NodeId not in out:
                out.add(ref.NodeId)
                todo.append(ref.NodeId)
    return out


def type_names(aspace: AddressSpace, root: ua.NodeId) -> dict[tuple[int, str], ua.NodeId]:
    """``root`` and its subtypes by (namespace index, BrowseName name): one walk answers every
    question for a type by name below ``root``."""
    out: dict[tuple[int, str], ua.NodeId] = {}
    for ref in subtypes(aspace, root):
        attr = aspace[ref].attributes.get(_A.BrowseName)
        if attr is not None and attr.value is not None and attr.value.Value is not None:
            out.setdefault((ref.NamespaceIndex, attr.value.Value.Value.Name), ref)
    return out


_NULL = ua.Variant(None, ua.VariantType.Null)  # never changed: shared
_UNWRITTEN: Any = object()  # equal to no value
_SEVERITY, _BAD = 0xC0000000, 0x80000000  # a StatusCode's severity bits, and Bad's
_NAMES = (ua.AttributeIds.BrowseName, ua.AttributeIds.DisplayName)  # asyncua's write also renames references


def unwatched(aspace: AddressSpace, nodeid: ua.NodeId, attr: ua.AttributeIds) -> AttributeValue | None:
    """The attribute ``attr`` of ``nodeid`` when a write of it tells nobody (no data change callback:
    no monitored item, no history; no setter) and may be stored as asyncua's write would store it;
    else None (asyncua's ``write_attribute_value`` checks and tells)."""
    data = aspace.get(nodeid)
    attval = data.attributes.get(attr) if data is not None else None
    if attval is None or attval.datachange_callbacks or attval.value_setter is not None:
        return None
    return attval


async def write_attribute(aspace: AddressSpace, nodeid: ua.NodeId, attr: ua.AttributeIds, dv: ua.DataValue) -> None:
    """asyncua's ``write_attribute_value`` of a Good or Uncertain ``dv``, stored at once when nobody is
    told and the Variant's type is the one stored before (what asyncua's write does then, without its
    checks: about fifteen calls fewer for each of the many values and Executable flags a change writes)."""
    attval = unwatched(aspace, nodeid, attr)
    old = attval.value if attval is not None else None
    bad = dv.StatusCode is not None and dv.StatusCode.value & _SEVERITY == _BAD  # asyncua nulls its Value
    plain = attr not in _NAMES and dv.Value is not None and not bad
    if plain and attval is not None and old is not None and old.Value is not None:
        vtype = old.Value.VariantType
        if vtype == dv.Value.VariantType and vtype != ua.VariantType.Null:
            attval.value = dv
            attval.value_callback = None
            return
    await aspace.write_attribute_value(nodeid, attr, dv)


class ValueWriter:
    """Writes variable Values into the address space (not through the services: no access checks).

    The VariantType comes from the variable's DataType unless given; a value equal to the last one
    this writer wrote is skipped unless ``force``. Lists are written as arrays.
    """

    def __init__(self, aspace: AddressSpace, builtin_of: Callable[[ua.NodeId], ua.VariantType | None]) -> None:
        self.aspace = aspace
        self._builtin_of = builtin_of
        self._written: dict[ua.NodeId, Any] = {}

    def vtype(self, nodeid: ua.NodeId) -> ua.VariantType:
        datatype = self.aspace[nodeid].attributes[_A.DataType].value.Value.Value
        return self._builtin_of(datatype) or ua.VariantType.Variant

    async def write(
        self,
        nodeid: ua.NodeId,
        value: Any,
        vtype: ua.VariantType | None = None,
        *,
        force: bool = False,
        status: ua.StatusCode | None = None,
    ) -> None:
        """Write ``value`` (Good, or with ``status``: an Uncertain quality, the value kept)."""
        if not force and self._written.get(nodeid, _UNWRITTEN) == value:  # one lookup: a NodeId hashes in Python
            return
        self._written[nodeid] = value
        variant = (
            value
            if isinstance(value, ua.Variant)
            else ua.Variant(value, vtype or self.vtype(nodeid), is_array=isinstance(value, list))
        )
        now = datetime.now(UTC)
        dv = ua.DataValue(variant, SourceTimestamp=now, ServerTimestamp=now)
        if status is not None:
            dv.StatusCode = status
        await write_attribute(self.aspace, nodeid, _A.Value, dv)

    async def write_status(self, nodeid: ua.NodeId, status: ua.StatusCode) -> None:
        """A Value that is only a status (e.g. Bad_StateNotActive), with timestamps."""
        self._written.pop(nodeid, None)
        now = datetime.now(UTC)
        # A null Value given: DataValue's default makes a Variant through a guessing constructor (3 us).
        dv = ua.DataValue(_NULL, StatusCode=status, SourceTimestamp=now, ServerTimestamp=now)
        attval = unwatched(self.aspace, nodeid, _A.Value)
        if attval is not None and status.is_bad():
            attval.value = dv  # what asyncua's write does with a Bad status (its Value null), nobody to tell
            attval.value_callback = None
            return
        await self.aspace.write_attribute_value(nodeid, _A.Value, dv)

    async def set_access(self, nodeid: ua.NodeId, level: int) -> None:
        """AccessLevel and UserAccessLevel (the security layer narrows the latter per session)."""
        for attr in (_A.AccessLevel, _A.UserAccessLevel):
            await self.aspace.write_attribute_value(nodeid, attr, ua.DataValue(ua.Variant(level, ua.VariantType.Byte)))

    def forget(self, node: ua.NodeId) -> None:
        """Forget what was written to ``node`` (it is deleted; a node of the same id starts afresh)."""
        self._written.pop(node, None)

    def forget_below(self, node: ua.NodeId) -> None:
        """Forget what was written to the variables of a deleted node (string NodeIds below ``node``)."""
        prefix = f"{node.Identifier}."
        for key in [k for k in self._written if isinstance(k.Identifier, str) and k.Identifier.startswith(prefix)]:
            del self._written[key]


_EVENT_ID_PREFIX = os.urandom(8)  # this process's; with the counter, no EventId repeats
_event_ids = itertools.count(1)


def new_event_id() -> bytes:
    """A fresh EventId (OPC 10000-5 6.4.2: unique per event; clients treat it as opaque): 16 bytes, a
    random prefix of this process and a counter, with no system call per event as uuid4 makes."""
    return _EVENT_ID_PREFIX + next(_event_ids).to_bytes(8, "big")


class EventEmitter:
    """Fires events of one type whose SourceNode is ``source``, to each notifier given to ``fire``."""

    def __init__(self, server: Server, event: Any, source: ua.NodeId) -> None:
        self.server = server
        self.event: Any = event
        self.source = source

    @classmethod
    async def create(cls, server: Server, event_type: int | ua.NodeId, source: ua.NodeId) -> EventEmitter:
        """An emitter whose events have SourceNode ``source``, which becomes an event notifier clients
        may subscribe to (SubscribeToEvents added to the bits it had: HistoryRead, set by history for
        the notifiers it keeps, stays)."""
        aspace = server.iserver.aspace
        type_id = event_type if isinstance(event_type, ua.NodeId) else ua.NodeId(event_type)
        before = aspace.read_attribute_value(source, _A.EventNotifier).Value
        made = IMPLEMENTED_EVENTS.get(type_id.Identifier) if type_id.NamespaceIndex == 0 else None
        if made is None:
            # A type asyncua has no class for: its generator reads the type's fields from the address space.
            generator = EventGenerator(server.iserver.isession)
            await generator.init(type_id, source, add_generates_event=False)
            event = generator.event
        else:
            # What asyncua's generator does for such a type, without its two service round trips (more
            # than half of what the large cell's 610 emitters took at start): the event object, its
            # source, its source's name.
            event = made()
            if isinstance(event, Condition):
                event.add_property("NodeId", None, ua.VariantType.NodeId)
            event.emitting_node = source
            if not event.SourceNode:
                event.SourceNode = source
            if not event.SourceName:
                event.SourceName = aspace.read_attribute_value(event.SourceNode, _A.BrowseName).Value.Value.Name
        bits = ((before.Value if before is not None else 0) or 0) | ua.EventNotifier.SubscribeToEvents.mask
        # read again: asyncua's generator set SubscribeToEvents alone
        now = aspace.read_attribute_value(source, _A.EventNotifier).Value
        if now is None or now.Value != bits:
            await aspace.write_attribute_value(source, _A.EventNotifier, ua.DataValue(ua.Variant(bits, _VT_BYTE)))
        return cls(server, event, source)

    async def fire(
        self,
        notifiers: Iterable[ua.NodeId],
        fields: Mapping[str, tuple[Any, ua.VariantType]] = {},
        to: Iterable[int] | None = None,
        **base: Any,
    ) -> None:
        """Fill the base fields (EventId, Time, Message, ...) and the typed ``fields``, then fire: to
        every listener and subscription, or (``to``) to those subscriptions only (nothing else sees it:
        not history, not PubSub)."""
        ev = self.event
        for name, value in base.items():
            setattr(ev, name, value)
        for name, (value, vtype) in fields.items():
            setattr(ev, name, value)
            ev.data_types[name] = vtype
        service = self.server.iserver.isession.subscription_service
        targets: list[int | None] = [None] if to is None else list(to)
        for notifier in notifiers:
            ev.emitting_node = notifier
            for subscription in targets:
                await service.trigger_event(ev, subscription)
        ev.emitting_node = self.source
