"""The address-space operations a companion's binder needs, and no more (``BinderHost.space``).

Binders create, find, link and delete nodes, read and write attributes, and fire events through this
object, by NodeId: the asyncua ``Server``, its ``AddressSpace`` and its ``Node`` handles stay inside
``uacell.ua`` (``address_space(space)`` hands the node store to the adapter's own modules only;
tests/test_asyncua_door.py checks no binder imports it).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Any

from asyncua import Server, ua
from asyncua.server.address_space import AddressSpace

from uacell.binding.dispatch import add_method_node
from uacell.binding.machine_binding import NodeRefs, StateMachineBinding, bind_tree
from uacell.binding.publisher import Publisher
from uacell.core.fsm import StateMachine
from uacell.ua import toolkit
from uacell.ua.toolkit import EventEmitter, ValueWriter

_A = ua.AttributeIds


class Space:
    def __init__(self, server: Server) -> None:
        self._server = server
        self._aspace: AddressSpace = server.iserver.aspace

    # --- reading --------------------------------------------------------------------------------
    def __contains__(self, nodeid: object) -> bool:
        """Is there a node ``nodeid``?"""
        return nodeid in self._aspace

    def attribute(self, nodeid: ua.NodeId, attribute: ua.AttributeIds = _A.Value) -> Any:
        """The value of a node's attribute (its Value's value by default), as the server reads it."""
        return self._aspace.read_attribute_value(nodeid, attribute).Value.Value

    def references(self, nodeid: ua.NodeId) -> Sequence[ua.ReferenceDescription]:
        """A node's references (forward and inverse); none for a node that does not exist."""
        data = self._aspace.get(nodeid)
        return data.references if data is not None else ()

    def find_child(self, nodeid: ua.NodeId, name: str) -> ua.NodeId | None:
        """The node's child (a forward reference, not HasTypeDefinition) whose BrowseName is ``name``."""
        return toolkit.find_child(self._aspace, nodeid, name)

    async def namespace_index(self, uri: str) -> int:
        index: int = await self._server.get_namespace_index(uri)
        return index

    # --- writing --------------------------------------------------------------------------------
    def value_writer(self, builtin_of: Callable[[ua.NodeId], ua.VariantType | None]) -> ValueWriter:
        """A writer of Values into the node store (the hot path of every binding's publishing)."""
        return ValueWriter(self._aspace, builtin_of)

    async def write(self, nodeid: ua.NodeId, attribute: ua.AttributeIds, variant: ua.Variant) -> None:
        """Set a node's attribute (no access checks: the server's own doing)."""
        await self._aspace.write_attribute_value(nodeid, attribute, ua.DataValue(variant))

    # --- making nodes ---------------------------------------------------------------------------
    async def add_object(self, parent: ua.NodeId, nodeid: ua.NodeId, name: ua.QualifiedName) -> ua.NodeId:
        made: ua.NodeId = (await self._server.get_node(parent).add_object(nodeid, name)).nodeid
        return made

    async def add_folder(self, parent: ua.NodeId, nodeid: ua.NodeId, name: ua.QualifiedName) -> ua.NodeId:
        made: ua.NodeId = (await self._server.get_node(parent).add_folder(nodeid, name)).nodeid
        return made

    async def add_variable(
        self,
        parent: ua.NodeId,
        nodeid: ua.NodeId,
        name: ua.QualifiedName,
        value: ua.Variant,
        datatype: ua.NodeId | None = None,
    ) -> ua.NodeId:
        node = self._server.get_node(parent)
        made = await node.add_variable(nodeid, name, value, datatype=datatype)
        result: ua.NodeId = made.nodeid
        return result

    async def add_method(
        self,
        parent: ua.NodeId,
        nodeid: ua.NodeId,
        name: ua.QualifiedName,
        inputs: Sequence[tuple[str, ua.VariantType, str]],
    ) -> None:
        """A server-specific method node with its InputArguments, unbound (``dispatcher.bind`` binds it)."""
        await add_method_node(self._server.get_node(parent), nodeid, name, inputs)

    async def add_reference(
        self, source: ua.NodeId, target: ua.NodeId, reference: int | ua.NodeId, *, bidirectional: bool = True
    ) -> None:
        """``source --reference--> target`` (and, ``bidirectional``, its inverse)."""
        await self._server.get_node(source).add_reference(target, reference, True, bidirectional)

    async def notify_events(self, nodeid: ua.NodeId) -> None:
        """Make ``nodeid`` an event notifier clients may subscribe to (the bits it had are kept)."""
        node = self._server.get_node(nodeid)
        notifier = await node.read_event_notifier()
        await node.set_event_notifier([*notifier, ua.EventNotifier.SubscribeToEvents])

    async def delete(self, nodes: Sequence[ua.NodeId], *, recursive: bool = True) -> None:
        """Delete ``nodes`` (and, ``recursive``, everything below them)."""
        await self._server.delete_nodes([self._server.get_node(n) for n in nodes], recursive=recursive)

    def delete_items(self, items: list[ua.DeleteNodesItem]) -> list[ua.StatusCode]:
        """Delete nodes exactly as listed (no recursion): the service call behind ``delete``."""
        results: list[ua.StatusCode] = self._server.iserver.node_mgt_service.delete_nodes(
            ua.DeleteNodesParameters(NodesToDelete=items)
        )
        return results

    # --- events and machines --------------------------------------------------------------------
    async def emitter(self, event_type: int | ua.NodeId, source: ua.NodeId) -> EventEmitter:
        """Fires events of ``event_type`` with SourceNode ``source``."""
        return await EventEmitter.create(self._server, event_type, source)

    async def bind_machine(
        self, node: ua.NodeId, machine: StateMachine, publisher: Publisher, refs: NodeRefs
    ) -> StateMachineBinding:
        """The one state-machine binding of ``machine`` (and its sub-machines) on ``node``."""
        return await bind_tree(self._server, node, machine, publisher, refs)


def address_space(space: Space) -> AddressSpace:
    """The node store behind ``space``: for the adapter's own modules (``uacell.ua``), never a binder."""
    return space._aspace
