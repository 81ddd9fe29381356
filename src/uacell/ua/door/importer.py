"""asyncua's NodeSet importer and its standard address space, as uacell loads them (start-up time)."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

from asyncua import Server, ua
from asyncua.common.xmlimporter import XmlImporter

from uacell.ua import door
from uacell.ua.door.connection import set_nodes


@door.subclass("asyncua.common.xmlimporter.XmlImporter")
class Importer(XmlImporter):  # type: ignore[misc]  # asyncua is untyped here (see pyproject)
    """asyncua's importer, with the reference-type subtype closure cached while it adds the missing
    inverse references.

    asyncua recomputes "is R a subtype of T" by walking the type tree for every reference it
    browses there, which is most of a start-up. When that step runs, every node of the file
    (its ReferenceTypes included) is already in the address space, so the closure cannot change.
    """

    async def _add_missing_reverse_references(self, new_nodes: Any) -> Any:
        view = self.session.iserver.view_service
        closure: dict[ua.NodeId, frozenset[ua.NodeId]] = {}
        null = ua.NodeId(ua.ObjectIds.Null)

        def suitable(ref1: ua.NodeId, ref2: ua.NodeId, subtypes: bool) -> bool:
            if ref1 == null or ref1 == ref2:
                return True
            if not subtypes:
                return False
            below = closure.get(ref1)
            if below is None:
                below = closure[ref1] = frozenset(view._get_sub_ref(ref1))
            return ref2 in below

        with door.swapped(view, "ViewService._suitable_reftype", suitable):
            return await super()._add_missing_reverse_references(new_nodes)


@contextmanager
def standard_nodes_from(server: Server, nodes: Any) -> Iterator[None]:
    """While it lasts, asyncua's ``init()`` takes ``nodes`` as the standard address space (a snapshot's
    node table) instead of loading its own."""

    async def from_snapshot(_shelf_file: object) -> None:
        set_nodes(server.iserver.aspace, nodes)

    with door.swapped(server.iserver, "InternalServer.load_standard_address_space", from_snapshot):
        yield
