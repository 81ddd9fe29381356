"""The address-space operations a companion's binder needs, and no more (``BinderHost.space``).

Binders create, find, link and delete nodes and fire events through this object; the asyncua
``Server`` behind it stays inside ``uacell.ua`` (and the server's own parts).
"""

from __future__ import annotations

from collections.abc import Sequence

from asyncua import Node, Server, ua
from asyncua.server.address_space import AddressSpace

from uacell.fsm import StateMachine
from uacell.ua.machine_binding import NodeRefs, StateMachineBinding, bind_tree
from uacell.ua.publisher import Publisher
from uacell.ua.toolkit import EventEmitter


class Space:
    def __init__(self, server: Server) -> None:
        self._server = server

    @property
    def aspace(self) -> AddressSpace:
        """The node store: attributes, references, data-change callbacks."""
        aspace: AddressSpace = self._server.iserver.aspace
        return aspace

    def node(self, nodeid: ua.NodeId | int) -> Node:
        """A client-style handle on a node (browse, add references, read children)."""
        return self._server.get_node(nodeid)

    async def namespace_index(self, uri: str) -> int:
        index: int = await self._server.get_namespace_index(uri)
        return index

    async def delete(self, nodes: Sequence[ua.NodeId], *, recursive: bool = True) -> None:
        """Delete ``nodes`` (and, ``recursive``, everything below them)."""
        await self._server.delete_nodes([self._server.get_node(n) for n in nodes], recursive=recursive)

    def delete_items(self, items: list[ua.DeleteNodesItem]) -> list[ua.StatusCode]:
        """Delete nodes exactly as listed (no recursion): the service call behind ``delete``."""
        results: list[ua.StatusCode] = self._server.iserver.node_mgt_service.delete_nodes(
            ua.DeleteNodesParameters(NodesToDelete=items)
        )
        return results

    async def emitter(self, event_type: int | ua.NodeId, source: ua.NodeId) -> EventEmitter:
        """Fires events of ``event_type`` with SourceNode ``source``."""
        return await EventEmitter.create(self._server, event_type, source)

    async def bind_machine(
        self, node: ua.NodeId, machine: StateMachine, publisher: Publisher, refs: NodeRefs
    ) -> StateMachineBinding:
        """The one state-machine binding of ``machine`` (and its sub-machines) on ``node``."""
        return await bind_tree(self._server, node, machine, publisher, refs)
