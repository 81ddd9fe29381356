"""Load the official NodeSet files into an asyncua server.

The models are imported in dependency order (DI, IA, Robotics, PackML). Nodes marked
``DesignToolOnly`` (DI 1.05 has some) are for modelling tools only and a server must not expose
them: the loader leaves them, everything below them and every reference to them out.
"""

from __future__ import annotations

import logging
import threading
import xml.etree.ElementTree as ET
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.common.xmlimporter import XmlImporter

from uacell.models.source import locate_models, official_models
from uacell.ua import snapshot

log = logging.getLogger(__name__)

_NS = "http://opcfoundation.org/UA/2011/03/UANodeSet.xsd"
_X = "{" + _NS + "}"
ET.register_namespace("", _NS)
ET.register_namespace("uax", "http://opcfoundation.org/UA/2008/02/Types.xsd")
ET.register_namespace("xsi", "http://www.w3.org/2001/XMLSchema-instance")
ET.register_namespace("xsd", "http://www.w3.org/2001/XMLSchema")


def without_design_tool_only(path: Path) -> tuple[str, int]:
    """The NodeSet's XML with DesignToolOnly nodes (and their subtrees) removed; and how many went."""
    tree = ET.parse(path)
    root = tree.getroot()
    nodes = [e for e in root if e.get("NodeId") is not None]
    dropped = {e.get("NodeId") for e in nodes if e.get("DesignToolOnly", "").lower() == "true"}
    if not dropped:
        return ET.tostring(root, encoding="unicode"), 0
    # Children of a dropped node go too (found through ParentNodeId, repeatedly).
    grew = True
    while grew:
        grew = False
        for e in nodes:
            if e.get("NodeId") not in dropped and e.get("ParentNodeId") in dropped:
                dropped.add(e.get("NodeId"))
                grew = True
    for e in nodes:
        if e.get("NodeId") in dropped:
            root.remove(e)
            continue
        refs = e.find(_X + "References")
        if refs is not None:
            for r in list(refs):
                if (r.text or "").strip() in dropped:
                    refs.remove(r)
    return ET.tostring(root, encoding="unicode"), len(dropped)


class _Importer(XmlImporter):  # type: ignore[misc]  # asyncua is untyped here (see pyproject)
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

        view._suitable_reftype = suitable
        try:
            return await super()._add_missing_reverse_references(new_nodes)
        finally:
            del view._suitable_reftype  # back to the class's own method


async def load_models(server: Server, models_dir: str | None = None) -> dict[str, int]:
    """Import every official model; returns each model's namespace index in this server."""
    paths = locate_models(models_dir)
    indexes: dict[str, int] = {}
    for model in official_models():
        xml, dropped = without_design_tool_only(paths[model.key])
        if dropped:
            log.debug("%s: left out %d DesignToolOnly nodes", model.filename, dropped)
        await _Importer(server).import_xml(xmlstring=xml)
        indexes[model.key] = await server.get_namespace_index(model.namespace_uri)
    return indexes


SnapshotJob = Callable[[dict[str, Any], threading.Event], None]
"""Writes the snapshot with the given extras; stops early when the event is set."""

# The writing thread's share of the interpreter while the server runs beside it (the rest is the
# event loop's): the first start serves at once, the snapshot takes a little longer.
WRITE_SHARE = 0.5


@dataclass
class PreparedSpace:
    """What ``init_address_space`` did: the models' namespace indexes and where the nodes came from.

    From a snapshot, ``extras`` is what its writer kept beside the nodes (the cell's bookkeeping);
    otherwise ``capture`` (None when the cache is off) copies the nodes (call it once the cell is
    built, before anything else changes them) and returns the job that writes the snapshot with
    the extras it is given: run it in a thread once listening.
    """

    indexes: dict[str, int]
    source: str  # "snapshot" or "nodesets"
    extras: dict[str, Any] | None = None
    capture: Callable[[], Awaitable[SnapshotJob]] | None = None


async def init_address_space(
    server: Server, models_dir: str | None, cache: Path | None, cell: str = ""
) -> PreparedSpace:
    """``server.init()`` and the official models, from the snapshot in ``cache`` when there is one.

    ``cell`` is the digest of the cell that will be built (``uacell.cell.cell_digest``): a snapshot
    holds its instances too. ``cache`` None: no snapshot is read or written. A stale snapshot has
    another key, so another file: it is not found. A damaged one is logged at INFO and removed. In
    both cases the address space is built as usual.
    """
    locate_models(models_dir)  # every file there and verified, even when the snapshot will do
    key = snapshot.snapshot_key({m.filename: m.sha256 for m in official_models()}, cell) if cache is not None else {}
    path = snapshot.snapshot_path(cache, key) if cache is not None else None
    found: snapshot.Snapshot | None = None
    if path is not None:
        try:
            found = snapshot.read_snapshot(path, key)
            if found is None:
                log.info("no address-space snapshot for this cell and these models yet: building the address space")
        except snapshot.SnapshotInvalid as e:
            log.info("the address-space snapshot %s %s: building the address space", path, e)
            snapshot.discard(path)
    if found is not None:
        nodes = found.nodes

        async def from_snapshot(_shelf_file: object) -> None:
            server.iserver.aspace._nodes = nodes

        # asyncua's init() fills the standard nodes here; everything else it does stays as it is.
        server.iserver.load_standard_address_space = from_snapshot
        try:
            await server.init()
        finally:
            del server.iserver.load_standard_address_space
        for position, uri in enumerate(found.namespaces, start=2):
            index = await server.register_namespace(uri)
            if index != position:
                raise RuntimeError(f"namespace {uri} got index {index}, the snapshot has it at {position}")
        # The importer registers the models' structure classes (asyncua.ua) as it goes; here they are
        # made from the DataTypeDefinitions, before any value of theirs is read from the snapshot.
        await server.load_data_type_definitions()
        indexes = {m.key: await server.get_namespace_index(m.namespace_uri) for m in official_models()}
        log.info("address space from the snapshot %s (%d nodes stored)", path, nodes.stored)
        return PreparedSpace(indexes, "snapshot", found.extras)
    await server.init()
    indexes = await load_models(server, models_dir)
    if path is None:
        return PreparedSpace(indexes, "nodesets")
    target = path

    async def capture() -> SnapshotJob:
        # On the event loop, before anything else changes the nodes; the writing can wait.
        copy = snapshot.stripped_copy(server.iserver.aspace._nodes)
        namespaces = list((await server.get_namespace_array())[2:])

        def write(extras: dict[str, Any], cancel: threading.Event) -> None:
            snapshot.write_snapshot(target, key, namespaces, copy, extras, cancel, WRITE_SHARE)
            snapshot.prune(target.parent)
            log.info("wrote the address-space snapshot %s (%d nodes)", target, len(copy))

        return write

    return PreparedSpace(indexes, "nodesets", capture=capture)
