"""Load the official NodeSet files into an asyncua server.

The models are imported in dependency order (DI, IA, Robotics, PackML). Nodes marked
``DesignToolOnly`` (DI 1.05 has some) are for modelling tools only and a server must not expose
them: the loader leaves them, everything below them and every reference to them out.
"""

from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from asyncua import Server, ua

from uacell.models.model_file import ModelFile
from uacell.models.source import locate_models
from uacell.models.source import models_dir as models_directory
from uacell.models.tables import UA_NS
from uacell.ua import data_types, snapshot
from uacell.ua.door.connection import nodes as node_table
from uacell.ua.door.importer import Importer, standard_nodes_from

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


async def load_models(server: Server, models: Sequence[ModelFile], models_dir: str | None = None) -> dict[str, int]:
    """Import every official model (``models``, in order); returns each model's namespace index in this server."""
    paths = locate_models(models, models_dir)
    indexes: dict[str, int] = {}
    for model in models:
        xml, dropped = without_design_tool_only(paths[model.key])
        if dropped:
            log.debug("%s: left out %d DesignToolOnly nodes", model.filename, dropped)
        await Importer(server).import_xml(xmlstring=xml)
        indexes[model.key] = await server.get_namespace_index(model.namespace_uri)
    return indexes


SnapshotJob = Callable[[dict[str, Any], snapshot.Cancel, float], tuple[Path, int]]
"""Writes the snapshot with the given extras, taking the given share of the interpreter
(``snapshot.write_snapshot``); stops early when asked to (WriteCancelled). Returns the file written
and its number of nodes."""

# A writing thread's share of the interpreter while the server runs beside it (the rest is the
# event loop's): the first start serves at once, the snapshot takes a little longer. A forked
# writer (``uacell.core.forked``, where the platform has fork) has the interpreter to itself.
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
    source: str  # "snapshot" (the cell's), "models snapshot" (the models' only) or "nodesets"
    extras: dict[str, Any] | None = None
    capture: Callable[[], Awaitable[SnapshotJob]] | None = None
    # From the models' snapshot: every type by (NodeClass, namespace index, BrowseName name), so that
    # building the cell finds its types without loading the whole type hierarchy (``type_index``)
    types: dict[tuple[int, int, str], ua.NodeId] | None = None


_TYPE_CLASSES = (ua.NodeClass.ObjectType, ua.NodeClass.VariableType, ua.NodeClass.DataType, ua.NodeClass.ReferenceType)


def type_index(nodes: Mapping[ua.NodeId, Any], namespaces: list[str]) -> dict[tuple[int, str, str], Any]:
    """Every type node of ``nodes`` by (NodeClass, namespace URI, BrowseName name) -> its identifier;
    ``namespaces`` from index 2 on (the models'; index 0 is OPC UA's own). A name that two types of
    one class and namespace share is left out (a lookup then walks the hierarchy)."""
    uris = {0: UA_NS, **{i: uri for i, uri in enumerate(namespaces, start=2)}}
    out: dict[tuple[int, str, str], Any] = {}
    shared: set[tuple[int, str, str]] = set()
    for node_id, data in nodes.items():
        node_class = data.attributes.get(ua.AttributeIds.NodeClass)
        name = data.attributes.get(ua.AttributeIds.BrowseName)
        if node_class is None or name is None or node_id.NamespaceIndex not in uris:
            continue
        cls = node_class.value.Value.Value
        if cls not in _TYPE_CLASSES:
            continue
        key = (int(cls), uris[node_id.NamespaceIndex], name.value.Value.Value.Name)
        if key in out:
            shared.add(key)
        out[key] = node_id.Identifier
    for key in shared:
        del out[key]
    return out


def _types_of(found: snapshot.Snapshot) -> dict[tuple[int, int, str], ua.NodeId] | None:
    """The models' snapshot's type index with this server's namespace indexes (the snapshot's)."""
    stored = found.extras.get("types")
    if not isinstance(stored, dict):
        return None  # a snapshot from before the index: types are found by walking
    index = {UA_NS: 0, **{uri: i for i, uri in enumerate(found.namespaces, start=2)}}
    return {(cls, index[uri], name): ua.NodeId(ident, index[uri]) for (cls, uri, name), ident in stored.items()}


def models_snapshot_key(models: Sequence[ModelFile]) -> dict[str, Any]:
    """The key of the models' own snapshot: the standard address space and the official NodeSets
    ``models``, no cell (``cell`` empty)."""
    return snapshot.snapshot_key({m.filename: m.sha256 for m in models}, "")


def models_snapshot_path(models: Sequence[ModelFile], models_dir: str | None) -> Path:
    """Where the models' snapshot lives: beside the NodeSet files it is made of."""
    return snapshot.snapshot_path(models_directory(models_dir), models_snapshot_key(models))


async def write_models_snapshot(models: Sequence[ModelFile], models_dir: str | None = None) -> Path:
    """Build the standard address space and the official models once, in a server that never listens,
    and write them as the models' snapshot (``uacell models fetch`` does, after fetching): a first
    start then reads them instead of importing the NodeSets (decision 46)."""
    path = models_snapshot_path(models, models_dir)
    quiet = logging.getLogger("asyncua")
    level = quiet.level
    quiet.setLevel(logging.ERROR)  # asyncua says every node it imports, and what it makes of some
    try:
        server = Server()
        await server.init()
        await load_models(server, models, models_dir)
        nodes = snapshot.stripped_copy(node_table(server.iserver.aspace))
        namespaces = list((await server.get_namespace_array())[2:])
        types = type_index(node_table(server.iserver.aspace), namespaces)
        made = data_types.registered(node_table(server.iserver.aspace))
    finally:
        quiet.setLevel(level)
    snapshot.write_snapshot(path, models_snapshot_key(models), namespaces, nodes, {"types": types, "data_types": made})
    snapshot.prune(path.parent, keep=2)  # one for this uacell, one for another beside it
    return path


async def _restore(server: Server, found: snapshot.Snapshot, models: Sequence[ModelFile]) -> dict[str, int]:
    """asyncua's ``init()`` with the snapshot's nodes instead of the standard ones; the models'
    namespace indexes."""
    nodes = found.nodes

    # asyncua's init() fills the standard nodes here; everything else it does stays as it is.
    with standard_nodes_from(server, nodes):
        await server.init()
    for position, uri in enumerate(found.namespaces, start=2):
        index = await server.register_namespace(uri)
        if index != position:
            raise RuntimeError(f"namespace {uri} got index {index}, the snapshot has it at {position}")
    # The importer registers the models' data type classes (asyncua.ua) as it goes; here they are
    # made before any value of theirs is read from the snapshot: from what its writer kept, or else
    # by asyncua walking every DataType for them.
    await _register_data_types(server, found)
    return {m.key: await server.get_namespace_index(m.namespace_uri) for m in models}


async def _register_data_types(server: Server, found: snapshot.Snapshot) -> None:
    entries = data_types.stored(found.extras)
    if entries is not None:
        try:
            data_types.register(entries)
            return
        except Exception as e:  # the snapshot is a cache: asyncua finds them itself
            log.info("the snapshot's data types could not be made (%s): looking for them in the address space", e)
    await server.load_data_type_definitions()


def _read(path: Path, key: dict[str, Any], what: str) -> snapshot.Snapshot | None:
    """The snapshot at ``path`` if it is there and sound; a damaged one is said and removed."""
    try:
        found = snapshot.read_snapshot(path, key)
        if found is None:
            log.info("no %s yet: building the address space", what)
        return found
    except snapshot.SnapshotInvalid as e:
        log.info("the %s %s %s: building the address space", what, path, e)
        snapshot.discard(path)
        return None


async def init_address_space(
    server: Server, models: Sequence[ModelFile], models_dir: str | None, cache: Path | None, cell: str = ""
) -> PreparedSpace:
    """``server.init()`` and the official ``models``, from the snapshot in ``cache`` when there is one.

    ``cell`` is the digest of the cell that will be built (``uacell.binding.cell.cell_digest``): a snapshot
    holds its instances too. Without one, the models come from the models' snapshot beside the
    NodeSet files (``write_models_snapshot``) when there is one, else from the NodeSet files.
    ``cache`` None: no snapshot is read or written. A stale snapshot has another key, so another
    file: it is not found. A damaged one is logged at INFO and removed. In both cases the address
    space is built as usual.
    """
    locate_models(models, models_dir)  # every file there and verified, even when the snapshot will do
    if cache is None:
        await server.init()
        return PreparedSpace(await load_models(server, models, models_dir), "nodesets")
    key = snapshot.snapshot_key({m.filename: m.sha256 for m in models}, cell)
    target = snapshot.snapshot_path(cache, key)
    found = _read(target, key, "address-space snapshot for this cell and these models")
    if found is not None:
        indexes = await _restore(server, found, models)
        log.info("address space from the snapshot %s (%d nodes stored)", target, found.nodes.stored)
        return PreparedSpace(indexes, "snapshot", found.extras)
    base_path = models_snapshot_path(models, models_dir)
    base = _read(base_path, models_snapshot_key(models), "snapshot of the models") if base_path.exists() else None
    types = None
    if base is not None:
        indexes = await _restore(server, base, models)
        source = "models snapshot"
        types = _types_of(base)
        log.info("the models from their snapshot %s", base_path)
    else:
        await server.init()
        indexes = await load_models(server, models, models_dir)
        source = "nodesets"

    async def capture() -> SnapshotJob:
        # On the event loop, before anything else changes the nodes; the writing can wait. Nodes of
        # the models' snapshot that were never loaded are unchanged: the writer reads them from it.
        nodes = node_table(server.iserver.aspace)
        copy = snapshot.stripped_copy(nodes)
        rest = nodes.rest() if isinstance(nodes, snapshot.LazyNodes) else None
        namespaces = list((await server.get_namespace_array())[2:])
        made = data_types.registered(nodes)

        def write(extras: dict[str, Any], cancel: snapshot.Cancel, share: float) -> tuple[Path, int]:
            every = copy + rest() if rest is not None else copy
            kept = {**extras, "data_types": made}
            snapshot.write_snapshot(target, key, namespaces, every, kept, cancel, share)
            return target, len(every)

        return write

    return PreparedSpace(indexes, source, capture=capture, types=types)
