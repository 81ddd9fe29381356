"""Find the cell in any server's address space: by type and BrowseName, never by NodeId.

Each companion says what the page shows of its parts (``Companion.web_view``, handed to the HMI by its
composition root, ``uacell.web.hosting``): which type's instances, in which folder of ``Objects``, and
the function that describes one (robots: ``uacell.robotics.web_view``, PackML units:
``uacell.packml.web_view``) with the ``Discoverer`` here, which browses, registers the keys and reads
locks and state machines for all of them. Namespaces are resolved by URI. The HMI runs it
(``uacell.web.discovery.discover``); it lives below the companions so that their web views can use it.

The result, ``Cell``, holds a JSON description for the page (``layout``) in which every value and
method is named by a *key* (its BrowseName path, e.g. ``Filler1/Status/MachSpeed``), and the maps
from those keys to the NodeIds found in this server.
"""

from __future__ import annotations

import logging
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

from asyncua import Client, Node, ua

from uacell.core.companion import WebView

log = logging.getLogger(__name__)

_HIERARCHICAL = ua.NodeId(ua.ObjectIds.HierarchicalReferences)
_HAS_SUBTYPE = ua.NodeId(ua.ObjectIds.HasSubtype)

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
    # An operation method whose first output is a Status value (OPC 40010-1's): the names of its
    # values, as its companion declares them (``WebView.status_names``); None: a plain method.
    status: Mapping[int, str] | None = None


@dataclass
class Cell:
    layout: dict[str, Any] = field(default_factory=dict)
    variables: dict[str, ua.NodeId] = field(default_factory=dict)
    methods: dict[str, MethodRef] = field(default_factory=dict)
    # Robot program directories: key -> FileDirectoryType node.
    directories: dict[str, ua.NodeId] = field(default_factory=dict)
    # TaskModules folders: key -> node (browsed again when the loaded program changes).
    folders: dict[str, ua.NodeId] = field(default_factory=dict)
    # The folders are browsed again when a value whose key ends so changes (set by the view that
    # registers them: a robot's task control, its program name and states).
    rebrowse: tuple[str, ...] = ()
    # Nodes whose TransitionEvents the page lists, by NodeId string -> key of the machine.
    machines: dict[str, str] = field(default_factory=dict)
    # uacell's Server/CurrentRole (decision 39): read once per session, each session its own role;
    # Server/CurrentUser (decision 103): read again and again, to learn that the server ended the login.
    role: ua.NodeId | None = None
    user: ua.NodeId | None = None
    # Per layout key, how a part's history view is read (``WebView.history``), where its companion has one.
    histories: dict[str, Callable[..., Awaitable[dict[str, Any]]]] = field(default_factory=dict)


class Discoverer:
    def __init__(self, client: Client, views: Sequence[WebView] = ()) -> None:
        self.client = client
        self.views = tuple(views)
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

    async def method(
        self, key: str, obj: ua.NodeId | None, name: str, status: Mapping[int, str] | None = None
    ) -> str | None:
        found = await self.child(obj, name)
        if obj is None or found is None:
            return None
        args: list[ua.Argument] = []
        prop = await self.child(found, "InputArguments")
        if prop is not None:
            value = await Node(self.client.uaclient, prop).read_value()
            args = list(value or [])
        self.cell.methods[key] = MethodRef(obj, found, args, status)
        return key

    async def methods(
        self, prefix: str, obj: ua.NodeId | None, names: tuple[str, ...], status: Mapping[int, str] | None = None
    ) -> dict[str, str]:
        out = {}
        for name in names:
            key = await self.method(f"{prefix}/{name}", obj, name, status)
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
        """Each companion's parts (``Companion.web_view``): its type's instances in its root folder."""
        ns = await self.client.get_namespace_array()
        index = {uri: i for i, uri in enumerate(ns)}
        objects = ua.NodeId(ua.ObjectIds.ObjectsFolder)
        top = {c.name: c.node for c in await self.children(objects)}
        layout: dict[str, Any] = {}
        for view in self.views:
            found = layout.setdefault(view.layout_key, [])
            reader = view.history_reader()
            if reader is not None:
                self.cell.histories[view.layout_key] = reader
            if view.namespace not in index:
                continue
            describe = view.describer()
            i = index[view.namespace]
            for part in await self.of_type(top.get(view.root), ua.NodeId(view.type_id, i)):
                found.append(await describe(self, part, i))
        layout["auditing"] = await self.auditing()
        self.cell.layout = layout
        self.cell.role = await self.child(ua.NodeId(ua.ObjectIds.Server), "CurrentRole")
        self.cell.user = await self.child(ua.NodeId(ua.ObjectIds.Server), "CurrentUser")
        log.debug("found %s", ", ".join(f"{len(v)} {k}" for k, v in layout.items() if isinstance(v, list)))
        return self.cell

    async def auditing(self) -> bool:
        """Does the server audit (``Server/Auditing``)? uacell does: it fires AuditUpdateStateEvents naming
        who caused each transition."""
        node = Node(self.client.uaclient, ua.NodeId(ua.ObjectIds.Server_Auditing))
        dv = await node.read_data_value(raise_on_bad_status=False)
        return bool(dv.StatusCode.is_good() and dv.Value is not None and dv.Value.Value)
