"""A snapshot of the prepared address space, so that later starts skip building it.

Building the address space is most of a start: asyncua creates its ~6,000 standard nodes one by one,
the four companion NodeSets are parsed and imported with their inverse references, and the cell's
instances are created member by member (15,000 nodes for 100 PackML units). All of it depends only
on the NodeSet files, the cell's shape and the versions of the code. So the first start writes what
they produced (every node, without the Python callbacks bound to them) to a file in the cache
directory, and later starts read the nodes from it on demand instead (``LazyNodes``): a node is
unpickled the first time something asks for it, and most standard nodes are never asked for. What
the bindings add and write (values, methods, their callbacks) is done on every start, as before.

The file is a cache, never a source of truth:

- it is keyed (``snapshot_key``) by everything that shapes it: the SHA-256 of every NodeSet file,
  the snapshot format, the digest of the code that builds it, and the uacell, asyncua and Python
  versions; a different key is stale;
- it carries the CRC-32 of its content and is verified before any node is read from it (a check
  against damage, a disk's or a copy's, as in zip and PNG files: the cache directory is the
  server's own, mode 0700, so whoever could forge the file could forge any digest beside it);
- it is written to a private temporary file (mode 0600, in a 0700 directory), flushed to disk and
  renamed over the old one, so a reader sees the old file or the new one, never half of one;
- a missing, stale or damaged file makes the server build the address space as if there were no
  cache (logged at INFO) and write a new one: it never fails a start.

Layout: ``MAGIC``, a 4-byte big-endian length and that many bytes of JSON metadata (key, namespace
URIs, index length, content CRC-32), then the content: a pickled index (``{(namespace index,
identifier): chunk}``, the chunks' ``(offset, length)``, extras) followed by the chunks, each a
pickled list of ``NodeData``.
Each key has its own file (``snapshot_path``); the few most recent are kept (``prune``).
"""

from __future__ import annotations

import contextlib
import copyreg
import hashlib
import io
import json
import logging
import mmap
import os
import pickle
import platform
import struct
import tempfile
import time
import zlib
from collections.abc import Callable, Iterator, Mapping, MutableMapping
from dataclasses import dataclass
from importlib.metadata import version
from pathlib import Path
from typing import Any, Protocol

from asyncua import ua
from asyncua.server.address_space import AttributeValue, NodeData

from uacell import __version__
from uacell.ua.door import connection as door_connection

log = logging.getLogger(__name__)

FORMAT = 3  # 3: attribute values pickled as a call with their value (_PICKLE_TABLE)
MAGIC = b"uacell address space snapshot\n"
PREFIX, SUFFIX = "address-space-", ".snapshot"
KEEP = 3  # snapshots kept per cache directory (one per cell and model set recently served)
# Nodes unpickled together. Neighbours are usually wanted together and share the pickle's memo, which
# makes a chunk much cheaper than its nodes one by one: instances (string NodeIds, all wanted by their
# bindings) go in large chunks; standard and NodeSet nodes (numeric NodeIds, a few wanted: 319 of
# 7,400 on a restart of the demo cell) in pairs (unpickling what a restart wants took 30 ms in chunks
# of 8, 24 ms in 4s, 22 ms in pairs, 20 ms one by one, which makes the file a third larger).
CHUNK, INSTANCE_CHUNK = 2, 256
_LENGTH = struct.Struct(">I")


def _reduce_attribute_value(value: AttributeValue) -> tuple[Any, ...]:
    # Only the value: the copies ``stripped_copy`` makes have no callback or setter.
    return AttributeValue, (value.value,)


# How a snapshot pickles an attribute value (a dozen a node): as a call with its value, not as a generic
# object with a state dictionary (its empty callback dictionary included). Unpickling the large cell's
# instances takes about a fifth less, the file is a seventh smaller. (Data values made so too, by a
# Python function, cost more than the generic way saves.)
_PICKLE_TABLE = {**copyreg.dispatch_table, AttributeValue: _reduce_attribute_value}


def _pickled(obj: Any) -> bytes:
    """``obj`` pickled as a snapshot's chunks are (``_PICKLE_TABLE``)."""
    out = io.BytesIO()
    pickler = pickle.Pickler(out, protocol=pickle.HIGHEST_PROTOCOL)
    pickler.dispatch_table = _PICKLE_TABLE
    pickler.dump(obj)
    return out.getvalue()


class SnapshotInvalid(Exception):
    """The file is not a usable snapshot for this server (the message says why)."""


# what builds the snapshot
_CODE = (
    "ua/snapshot.py",
    "ua/nodesets.py",
    "ua/data_types.py",
    "ua/instantiate.py",
    "binding/cell.py",
    "models/tables.py",
)


def snapshot_key(nodesets: Mapping[str, str], cell: str) -> dict[str, Any]:
    """Everything that shapes the prepared address space, as a JSON-able mapping.

    ``nodesets`` maps each NodeSet file's name to its SHA-256; ``cell`` is the digest of the cell's
    shape (``uacell.binding.cell.cell_digest``). The code that builds the snapshot is keyed by its own
    digest too, so a changed loader or instantiation never reads a snapshot the old one wrote, even
    within one uacell version.
    """
    package = Path(__file__).parents[1]
    code = hashlib.sha256()
    for source in _CODE:
        code.update((package / source).read_bytes())
    return {
        "format": FORMAT,
        "uacell": __version__,
        "code": code.hexdigest(),
        "asyncua": version("asyncua"),
        "python": f"{platform.python_implementation()} {platform.python_version()}",
        "nodesets": dict(sorted(nodesets.items())),
        "cell": cell,
    }


def snapshot_path(cache: Path, key: Mapping[str, Any]) -> Path:
    """The file of the snapshot keyed ``key``: one per key, so that cells do not evict each other."""
    digest = hashlib.sha256(json.dumps(dict(key), sort_keys=True).encode()).hexdigest()
    return cache / f"{PREFIX}{digest[:16]}{SUFFIX}"


def prune(cache: Path, keep: int = KEEP) -> None:
    """Remove all but the ``keep`` most recently written snapshots."""
    found = sorted(cache.glob(f"{PREFIX}*{SUFFIX}"), key=lambda p: p.stat().st_mtime_ns, reverse=True)
    for old in found[keep:]:
        with contextlib.suppress(FileNotFoundError):
            old.unlink()


def stripped_copy(nodes: Mapping[ua.NodeId, NodeData]) -> list[tuple[ua.NodeId, NodeData]]:
    """Every node as data only: no method callback, value callback, setter or data-change callback.

    Run it on the event loop (nothing may change the nodes meanwhile); the copy can then be pickled
    in another thread while the server goes on. Values are shared, not copied: asyncua replaces a
    ``DataValue`` on write, it never changes one in place.
    """
    copies: list[tuple[ua.NodeId, NodeData]] = []
    for nodeid, data in nodes.items():
        copy = NodeData(nodeid)
        copy.references = list(data.references)
        copy.attributes = {attr: AttributeValue(value.value) for attr, value in data.attributes.items()}
        copies.append((nodeid, copy))
    return copies


@dataclass
class Snapshot:
    """A verified snapshot: its namespace URIs (from index 2 on), its nodes (read on demand) and what
    its writer asked to keep beside them (``extras``, e.g. the cell's instance declarations)."""

    namespaces: list[str]
    nodes: LazyNodes
    extras: dict[str, Any]


class LazyNodes(MutableMapping[ua.NodeId, NodeData]):
    """The address space's node table, backed by a snapshot's content.

    Nodes are stored in chunks of neighbours (in the order they were created: a type's members, an
    instance's children; ``CHUNK`` and ``INSTANCE_CHUNK``); a chunk is unpickled into ``cache`` the
    first time one of its nodes is asked for. New and changed nodes live in ``cache`` only. Iteration and ``len``
    cover the nodes loaded so far (as asyncua's own shelf-backed table does): a node that was never
    loaded cannot hold a reference to a node created since, so code that scans for references
    (asyncua's DeleteNodes) still finds every one.
    """

    def __init__(self, chunks: memoryview, where: dict[tuple[int, Any], int], spans: list[tuple[int, int]]) -> None:
        self._chunks = chunks
        self._where = where  # node (namespace index, identifier) -> its chunk
        self._spans = spans  # chunk -> (offset, length) in ``chunks``
        self._loaded: set[int] = set()
        self._deleted: set[ua.NodeId] = set()
        self.cache: dict[ua.NodeId, NodeData] = {}

    def __getitem__(self, key: ua.NodeId) -> NodeData:
        try:
            return self.cache[key]
        except KeyError:
            chunk = self._where.get((key.NamespaceIndex, key.Identifier))
            if chunk is None or chunk in self._loaded or key in self._deleted:
                raise
            self._load(chunk)
            return self.cache[key]

    def get(self, key: ua.NodeId, default: Any = None) -> Any:  # Mapping's: one Python call, not two
        """The node, loading its chunk if need be, else ``default``: what ``Mapping.get`` answers,
        without its ``__getitem__`` call and raised KeyError for a node that is loaded (asyncua asks
        ``get`` for every value it writes, several times a call)."""
        node = self.cache.get(key)
        if node is not None:
            return node
        try:
            return self[key]
        except KeyError:
            return default

    def _load(self, chunk: int) -> None:
        self._loaded.add(chunk)
        offset, length = self._spans[chunk]
        nodes: list[NodeData] = pickle.loads(self._chunks[offset : offset + length])
        for node in nodes:
            if node.nodeid not in self._deleted:
                self.cache.setdefault(node.nodeid, node)  # a node set since wins

    def __setitem__(self, key: ua.NodeId, value: NodeData) -> None:
        self._deleted.discard(key)
        self.cache[key] = value

    def __delitem__(self, key: ua.NodeId) -> None:
        if key not in self:
            raise KeyError(key)
        self.cache.pop(key, None)
        self._deleted.add(key)

    def __contains__(self, key: object) -> bool:
        if key in self.cache:
            return True
        if not isinstance(key, ua.NodeId) or key in self._deleted:
            return False
        return (key.NamespaceIndex, key.Identifier) in self._where

    def __iter__(self) -> Iterator[ua.NodeId]:
        return iter(self.cache)

    def __len__(self) -> int:
        return len(self.cache)

    def rest(self) -> Callable[[], list[tuple[ua.NodeId, NodeData]]]:
        """The nodes not loaded now, as they are stored: a function another thread may call later.

        Nodes that were never loaded have not changed, so what the file holds is what they are now;
        with the loaded ones (``stripped_copy`` of this table: its cache) it is every node. The
        file's bytes never change under a mapping (writers replace files), so the function may run
        while the event loop goes on loading and changing nodes."""
        pending = [i for i in range(len(self._spans)) if i not in self._loaded]
        skip = set(self.cache) | set(self._deleted)
        chunks, spans = self._chunks, self._spans

        def load() -> list[tuple[ua.NodeId, NodeData]]:
            out: list[tuple[ua.NodeId, NodeData]] = []
            for chunk in pending:
                offset, length = spans[chunk]
                nodes: list[NodeData] = pickle.loads(chunks[offset : offset + length])
                out.extend((node.nodeid, node) for node in nodes if node.nodeid not in skip)
            return out

        return load

    @property
    def stored(self) -> int:
        """How many nodes the snapshot holds."""
        return len(self._where)

    def node_ids(self) -> set[ua.NodeId]:
        """Every node of the table, loaded or not (iteration covers the loaded ones only)."""
        stored = {ua.NodeId(identifier, ns) for ns, identifier in self._where}
        return (stored - self._deleted) | set(self.cache)


def every_node_id(aspace: Any) -> set[ua.NodeId]:
    """Every node of an asyncua address space, also those of a snapshot not loaded yet."""
    nodes = door_connection.nodes(aspace)
    return nodes.node_ids() if isinstance(nodes, LazyNodes) else set(nodes.keys())


def _chunks(nodes: list[tuple[ua.NodeId, NodeData]]) -> Iterator[list[tuple[ua.NodeId, NodeData]]]:
    """Consecutive nodes of one kind (instance or not), at most that kind's chunk size at a time."""
    group: list[tuple[ua.NodeId, NodeData]] = []
    kind = False
    for item in nodes:
        instance = isinstance(item[0].Identifier, str)
        if group and (instance != kind or len(group) == (INSTANCE_CHUNK if kind else CHUNK)):
            yield group
            group = []
        group.append(item)
        kind = instance
    if group:
        yield group


_PLAIN = (int, str, bool, bytes, type(None))


def _node_id_key(node: ua.NodeId) -> tuple[Any, ...]:
    # NodeId's own equality ignores its encoding (NodeIdType) and an ExpandedNodeId's URI and server:
    # two that differ there are not merged
    uri, server = getattr(node, "NamespaceUri", None), getattr(node, "ServerIndex", None)
    return (type(node), node.Identifier, node.NamespaceIndex, node.NodeIdType, uri, server)


def _value_key(dv: ua.DataValue) -> tuple[Any, ...] | None:
    """Equal keys for DataValues that encode alike: a scalar of a plain type, a NodeId, a
    LocalizedText or a QualifiedName, with their status and timestamps. None for anything else."""
    variant = dv.Value
    if variant is None or variant.is_array or variant.Dimensions is not None:
        return None
    value = variant.Value
    if isinstance(value, float):
        key: tuple[Any, ...] = (float, value.hex())  # 0.0 == -0.0, their encodings differ
    elif isinstance(value, _PLAIN):
        key = (type(value), value)  # 1, 1.0 and True are equal; their types are not
    elif isinstance(value, ua.NodeId):
        key = _node_id_key(value)
    elif isinstance(value, ua.LocalizedText):
        key = (ua.LocalizedText, value.Locale, value.Text)
    elif isinstance(value, ua.QualifiedName):
        key = (ua.QualifiedName, value.NamespaceIndex, value.Name)
    else:
        return None
    status = dv.StatusCode.value if dv.StatusCode is not None else None
    times = (dv.SourceTimestamp, dv.ServerTimestamp, dv.SourcePicoseconds, dv.ServerPicoseconds)
    return (key, variant.VariantType, status, times, dv.Encoding)


def _reference_key(ref: ua.ReferenceDescription) -> tuple[Any, ...]:
    return (
        "reference",
        _node_id_key(ref.ReferenceTypeId),
        ref.IsForward,
        _node_id_key(ref.NodeId),
        ref.BrowseName.NamespaceIndex,
        ref.BrowseName.Name,
        ref.DisplayName.Locale,
        ref.DisplayName.Text,
        ref.NodeClass,
        _node_id_key(ref.TypeDefinition),
    )


def share_equal_values(nodes: list[NodeData]) -> None:
    """Make equal attribute values (AccessLevel 3, ValueRank -1, an empty Description, ...) and equal
    references of ``nodes`` one object each, so that a chunk pickles each once and a reader makes each
    once: unpickling the demo cell's instances takes about 40 % less.

    Only values and references are shared, never an ``AttributeValue`` (asyncua assigns to those);
    asyncua replaces a ``DataValue`` on write and appends or removes references, it changes neither
    in place (``stripped_copy`` relies on the same). ``nodes``: copies (``stripped_copy``), whose
    attribute values and reference lists are their own."""
    seen: dict[tuple[Any, ...], Any] = {}
    for node in nodes:
        for attribute in node.attributes.values():
            key = _value_key(attribute.value) if attribute.value is not None else None
            if key is not None:
                attribute.value = seen.setdefault(key, attribute.value)
        refs = node.references
        for i, ref in enumerate(refs):
            refs[i] = seen.setdefault(_reference_key(ref), ref)


class Cancel(Protocol):
    """What ``write_snapshot`` asks between chunks: a ``threading.Event``, or a forked writer's
    ``uacell.core.forked.Cancelled``."""

    def is_set(self) -> bool: ...


class WriteCancelled(Exception):
    """``write_snapshot`` was asked to stop; nothing was written."""


def write_snapshot(
    path: Path,
    key: Mapping[str, Any],
    namespaces: list[str],
    nodes: list[tuple[ua.NodeId, NodeData]],
    extras: Mapping[str, Any] | None = None,
    cancel: Cancel | None = None,
    share: float = 1.0,
) -> None:
    """Write ``nodes`` (from ``stripped_copy``) as the snapshot at ``path``, atomically, owner-only.

    Within a chunk, equal values and references of the copies are made one object (``share_equal_values``).

    ``extras``: picklable data kept beside the nodes (``Snapshot.extras``). Run in a thread beside
    a serving event loop, ``share`` (0 to 1) is the part of the time it keeps the interpreter busy:
    after each chunk it sleeps so that the loop gets the rest. ``cancel`` set: it stops before the
    file is created (``WriteCancelled``)."""
    where: dict[tuple[int, Any], int] = {}
    spans: list[tuple[int, int]] = []
    blobs: list[bytes] = []
    offset = 0
    for group in _chunks(nodes):
        if cancel is not None and cancel.is_set():
            raise WriteCancelled
        started = time.perf_counter()
        chunk = [data for _nodeid, data in group]
        share_equal_values(chunk)
        blob = _pickled(chunk)
        if share < 1.0:
            time.sleep((time.perf_counter() - started) * (1.0 - share) / share)
        for nodeid, _data in group:
            where[nodeid.NamespaceIndex, nodeid.Identifier] = len(spans)
        spans.append((offset, len(blob)))
        blobs.append(blob)
        offset += len(blob)
    index = pickle.dumps((where, spans, dict(extras or {})), protocol=pickle.HIGHEST_PROTOCOL)
    crc = zlib.crc32(index)
    for blob in blobs:
        crc = zlib.crc32(blob, crc)
    meta = json.dumps(
        {"key": dict(key), "namespaces": namespaces, "index_length": len(index), "crc32": crc},
        sort_keys=True,
    ).encode()
    path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)  # mode 0600
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(MAGIC)
            f.write(_LENGTH.pack(len(meta)))
            f.write(meta)
            f.write(index)
            for blob in blobs:
                f.write(blob)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise
    dir_fd = os.open(path.parent, os.O_RDONLY)
    try:
        os.fsync(dir_fd)
    finally:
        os.close(dir_fd)


def read_snapshot(path: Path, key: Mapping[str, Any]) -> Snapshot | None:
    """The verified snapshot at ``path``; None if there is none; ``SnapshotInvalid`` if unusable."""
    try:
        data = _map(path)
    except FileNotFoundError:
        return None
    except (OSError, ValueError) as e:
        raise SnapshotInvalid(f"cannot be read: {e}") from e
    if len(data) < len(MAGIC) + _LENGTH.size or data[: len(MAGIC)] != MAGIC:
        raise SnapshotInvalid("is not a snapshot file")
    start = len(MAGIC) + _LENGTH.size
    (meta_length,) = _LENGTH.unpack_from(data, len(MAGIC))
    try:
        meta = json.loads(data[start : start + meta_length])
        stored_key, namespaces = meta["key"], meta["namespaces"]
        index_length, expected = int(meta["index_length"]), int(meta["crc32"])
    except (ValueError, KeyError, TypeError) as e:
        raise SnapshotInvalid("has unreadable metadata") from e
    if stored_key != dict(key):
        raise SnapshotInvalid("is stale (NodeSets or versions changed)")
    content = memoryview(data)[start + meta_length :]
    if zlib.crc32(content) != expected:
        raise SnapshotInvalid("is damaged (its content does not match its checksum)")
    # The check read every page: give them back; the chunks that are loaded come in again from the page
    # cache, the rest never count in the server's memory.
    data.madvise(mmap.MADV_DONTNEED)
    if not isinstance(namespaces, list) or not all(isinstance(n, str) for n in namespaces):
        raise SnapshotInvalid("has unreadable metadata")
    try:
        where, spans, extras = pickle.loads(content[:index_length])
    except Exception as e:  # a digest match makes this unlikely; never fail a start over a cache
        raise SnapshotInvalid(f"has an unreadable index: {e}") from e
    return Snapshot(namespaces, LazyNodes(content[index_length:], where, spans), extras)


def _map(path: Path) -> mmap.mmap:
    """The file, mapped read-only. Writers replace the file (a new inode), never change it in place,
    so a mapping stays what was verified."""
    with path.open("rb") as f:
        return mmap.mmap(f.fileno(), 0, access=mmap.ACCESS_READ)


def discard(path: Path) -> None:
    """Remove the snapshot and any temporary file a crash left beside it."""
    for stale in [path, *path.parent.glob(f".{path.name}.*.tmp")]:
        with contextlib.suppress(FileNotFoundError):
            stale.unlink()
