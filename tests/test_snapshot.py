"""The address-space snapshot (uacell.ua.snapshot): its file, and servers that write and read it.

The completeness test (tests/test_completeness.py) checks the demo cell of a server started from a
snapshot; the rest of the suite shares one snapshot (tests/conftest.py), so most servers in it start
from one. Here: the file format's guarantees, and the server's choice between snapshot and NodeSets.
"""

from __future__ import annotations

import dataclasses
import errno
import functools
import logging
import os
import stat
import threading
import time
from datetime import UTC, datetime
from pathlib import Path

import pytest
from asyncua import Client, ua
from asyncua.server.address_space import AttributeValue, NodeData
from conftest import fast_config, start_app
from helpers import first_start_source, free_port, models_copy, official

import uacell.server
from uacell.core import forked
from uacell.machinery.binding import MACHINES
from uacell.packml.binding import UNITS
from uacell.ua import snapshot
from uacell.ua.snapshot import LazyNodes, SnapshotInvalid, read_snapshot, stripped_copy, write_snapshot

KEY = {"format": 1, "nodesets": {"A.xml": "aa"}, "cell": "c1"}
NAME = "address-space-test.snapshot"


def _node(identifier: int, value: str) -> NodeData:
    node = NodeData(ua.NodeId(identifier, 2))
    attr = AttributeValue(ua.DataValue(ua.Variant(value, ua.VariantType.String)))
    attr.value_callback = lambda nodeid, attr: ua.DataValue()
    attr.datachange_callbacks = {1: print}
    node.attributes[ua.AttributeIds.Value] = attr
    node.references.append(ua.ReferenceDescription(NodeId=ua.NodeId(identifier + 1, 2)))
    node.call = print
    return node


def _nodes(count: int = 5) -> dict[ua.NodeId, NodeData]:
    return {n.nodeid: n for n in (_node(i, f"value {i}") for i in range(1, count + 1))}


def _write(path: Path, nodes: dict[ua.NodeId, NodeData] | None = None) -> None:
    write_snapshot(path, KEY, ["urn:a", "urn:b"], stripped_copy(nodes or _nodes()), {"declarations": {1: 2}})


def _value(node: NodeData) -> object:
    dv = node.attributes[ua.AttributeIds.Value].value
    assert dv is not None and dv.Value is not None
    return dv.Value.Value


def test_a_snapshot_keeps_nodes_without_their_callbacks_and_reads_them_on_demand(tmp_path: Path) -> None:
    path = tmp_path / "cache" / NAME
    _write(path)
    found = read_snapshot(path, KEY)
    assert found is not None
    assert found.namespaces == ["urn:a", "urn:b"]
    assert found.extras == {"declarations": {1: 2}}
    nodes = found.nodes
    assert nodes.stored == 5 and len(nodes) == 0  # nothing unpickled yet
    node = nodes[ua.NodeId(3, 2)]
    assert _value(node) == "value 3"
    assert [r.NodeId for r in node.references] == [ua.NodeId(4, 2)]
    assert node.call is None
    value = node.attributes[ua.AttributeIds.Value]
    assert value.value_callback is None and value.datachange_callbacks == {} and value.value_setter is None
    assert ua.NodeId(5, 2) in nodes and ua.NodeId(6, 2) not in nodes
    assert nodes.get(ua.NodeId(6, 2)) is None


def test_nodes_are_loaded_a_chunk_at_a_time(tmp_path: Path) -> None:
    path = tmp_path / NAME
    assert snapshot.CHUNK >= 2
    count = snapshot.CHUNK * 3
    _write(path, _nodes(count))
    found = read_snapshot(path, KEY)
    assert found is not None and found.nodes.stored == count
    nodes = found.nodes
    last = ua.NodeId(count, 2)
    assert _value(nodes[last]) == f"value {count}"
    assert set(nodes) == {ua.NodeId(i, 2) for i in range(snapshot.CHUNK * 2 + 1, count + 1)}  # its chunk only
    assert _value(nodes[ua.NodeId(1, 2)]) == "value 1"
    assert set(nodes) == {
        ua.NodeId(i, 2) for i in [*range(1, snapshot.CHUNK + 1), *range(snapshot.CHUNK * 2 + 1, count + 1)]
    }


def test_instances_are_loaded_in_larger_chunks(tmp_path: Path) -> None:
    numeric = _nodes(3)
    instances = {}
    for i in range(snapshot.INSTANCE_CHUNK + 1):
        node = NodeData(ua.NodeId(f"Cell.Part{i}", 3))
        node.attributes[ua.AttributeIds.Value] = AttributeValue(ua.DataValue(ua.Variant(i, ua.VariantType.Int32)))
        instances[node.nodeid] = node
    path = tmp_path / NAME
    _write(path, {**numeric, **instances})
    found = read_snapshot(path, KEY)
    assert found is not None
    nodes = found.nodes
    assert _value(nodes[ua.NodeId("Cell.Part0", 3)]) == 0
    assert set(nodes) == {ua.NodeId(f"Cell.Part{i}", 3) for i in range(snapshot.INSTANCE_CHUNK)}  # no numeric
    assert _value(nodes[ua.NodeId(f"Cell.Part{snapshot.INSTANCE_CHUNK}", 3)]) == snapshot.INSTANCE_CHUNK
    assert _value(nodes[ua.NodeId(2, 2)]) == "value 2"  # and its numeric neighbours, CHUNK at a time
    assert len(nodes) == snapshot.INSTANCE_CHUNK + 1 + min(3, snapshot.CHUNK)


def test_equal_values_and_references_of_a_chunk_are_read_as_one_object(tmp_path: Path) -> None:
    """Instances are full of equal attribute values (AccessLevel, ValueRank, an empty Description)
    and references (HasTypeDefinition to PropertyType): within a chunk each is stored and read once.
    Values that are equal to Python but encode otherwise (1 and True, one NodeId in two encodings)
    stay apart; the attribute values themselves (what asyncua assigns to) are never shared."""
    A = ua.AttributeIds
    nodes = {}
    for i in range(4):
        node = NodeData(ua.NodeId(f"Cell.Part{i}", 3))
        node.attributes[A.AccessLevel] = AttributeValue(ua.DataValue(ua.Variant(3, ua.VariantType.Byte)))
        node.attributes[A.Description] = AttributeValue(ua.DataValue(ua.Variant(ua.LocalizedText(""))))
        node.attributes[A.Value] = AttributeValue(ua.DataValue(ua.Variant(i, ua.VariantType.Int32)))
        flag = 1 if i % 2 else True
        node.attributes[A.Historizing] = AttributeValue(ua.DataValue(ua.Variant(flag)))
        kind = ua.NodeIdType.Numeric if i % 2 else ua.NodeIdType.FourByte
        node.attributes[A.DataType] = AttributeValue(ua.DataValue(ua.Variant(ua.NodeId(11, 0, kind))))
        zero = -0.0 if i % 2 else 0.0  # equal to Python, another sign bit on the wire
        node.attributes[A.MinimumSamplingInterval] = AttributeValue(ua.DataValue(ua.Variant(zero)))
        node.references.append(ua.ReferenceDescription(ReferenceTypeId=ua.NodeId(40), NodeId=ua.NodeId(68)))
        node.references.append(ua.ReferenceDescription(ReferenceTypeId=ua.NodeId(47), NodeId=node.nodeid))
        nodes[node.nodeid] = node
    _write(tmp_path / NAME, nodes)
    found = read_snapshot(tmp_path / NAME, KEY)
    assert found is not None
    read = [found.nodes[ua.NodeId(f"Cell.Part{i}", 3)] for i in range(4)]

    def objects(attribute: ua.AttributeIds) -> set[int]:
        return {id(n.attributes[attribute].value) for n in read}

    assert len(objects(A.AccessLevel)) == 1 and len(objects(A.Description)) == 1
    assert len(objects(A.Value)) == 4 and [_value(n) for n in read] == [0, 1, 2, 3]
    assert len(objects(A.Historizing)) == 2 and [type(n.attributes[A.Historizing].value.Value.Value) for n in read] == [
        bool,
        int,
        bool,
        int,
    ]
    assert len(objects(A.DataType)) == 2
    assert len(objects(A.MinimumSamplingInterval)) == 2
    signs = [str(n.attributes[A.MinimumSamplingInterval].value.Value.Value) for n in read]
    assert signs == ["0.0", "-0.0", "0.0", "-0.0"]
    assert [n.attributes[A.DataType].value.Value.Value.NodeIdType for n in read] == [
        ua.NodeIdType.FourByte,
        ua.NodeIdType.Numeric,
    ] * 2
    assert len({id(n.references[0]) for n in read}) == 1 and len({id(n.references[1]) for n in read}) == 4
    assert len({id(n.attributes[A.AccessLevel]) for n in read}) == 4  # AttributeValues: each its own


def test_every_field_of_a_value_comes_back(tmp_path: Path) -> None:
    """Attribute values are stored as a call with their value (not as generic objects): each field of
    the value, the Encoding mask a decoded value carries included, comes back as it was, and the
    attribute value comes back without callbacks."""
    A = ua.AttributeIds
    at = datetime(2026, 11, 27, 21, 40, 5, 123456, tzinfo=UTC)
    full = ua.DataValue(
        ua.Variant([1.5, 2.5], ua.VariantType.Double, is_array=True),
        StatusCode=ua.StatusCode(ua.StatusCodes.UncertainLastUsableValue),
        SourceTimestamp=at,
        ServerTimestamp=at,
        SourcePicoseconds=7,
        ServerPicoseconds=9,
    )
    full.Encoding = 0x3F
    bare = ua.DataValue(ua.Variant(None))
    node = NodeData(ua.NodeId("Cell.Values", 3))
    node.attributes[A.Value] = AttributeValue(full)
    node.attributes[A.Description] = AttributeValue(bare)
    _write(tmp_path / NAME, {node.nodeid: node})
    found = read_snapshot(tmp_path / NAME, KEY)
    assert found is not None
    read = found.nodes[node.nodeid]
    for attribute, wanted in ((A.Value, full), (A.Description, bare)):
        got = read.attributes[attribute]
        assert isinstance(got, AttributeValue) and isinstance(got.value, ua.DataValue)
        assert got.value_callback is None and got.value_setter is None and got.datachange_callbacks == {}
        for field in dataclasses.fields(ua.DataValue):
            assert getattr(got.value, field.name) == getattr(wanted, field.name), field.name
    assert read.attributes[A.Value].value.Value.is_array


def test_nodes_added_changed_and_deleted_live_beside_the_snapshot(tmp_path: Path) -> None:
    path = tmp_path / NAME
    _write(path)
    found = read_snapshot(path, KEY)
    assert found is not None
    nodes: LazyNodes = found.nodes
    del nodes[ua.NodeId(1, 2)]  # never loaded before
    assert ua.NodeId(1, 2) not in nodes
    assert nodes.get(ua.NodeId(1, 2)) is None and nodes.get(ua.NodeId(1, 2), "gone") == "gone"
    assert nodes.get(ua.NodeId(99, 2)) is None  # never stored
    with pytest.raises(KeyError):
        nodes[ua.NodeId(1, 2)]
    with pytest.raises(KeyError):
        del nodes[ua.NodeId(1, 2)]
    assert _value(nodes.get(ua.NodeId(2, 2))) == "value 2"  # its chunk (node 1's) loads without the deleted node
    assert nodes.get(ua.NodeId(2, 2)) is nodes[ua.NodeId(2, 2)]
    assert ua.NodeId(1, 2) not in nodes
    new = _node(1, "again")
    nodes[ua.NodeId(1, 2)] = new
    assert nodes[ua.NodeId(1, 2)] is new
    nodes[ua.NodeId(40, 2)] = _node(40, "new")
    assert _value(nodes[ua.NodeId(40, 2)]) == "new"
    assert _value(nodes[ua.NodeId(1, 2)]) == "again"  # set after its chunk was loaded: the new one stays
    first_chunk = range(1, min(snapshot.CHUNK, 5) + 1)
    assert set(nodes) == {ua.NodeId(i, 2) for i in (*first_chunk, 40)}


def test_the_file_is_readable_by_its_owner_only(tmp_path: Path) -> None:
    path = tmp_path / "cache" / NAME
    _write(path)
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    assert sorted(p.name for p in path.parent.iterdir()) == [NAME]  # no temporary left


def test_no_file_is_no_snapshot(tmp_path: Path) -> None:
    assert read_snapshot(tmp_path / NAME, KEY) is None


def test_a_snapshot_with_another_key_is_stale(tmp_path: Path) -> None:
    path = tmp_path / NAME
    _write(path)
    other = {**KEY, "nodesets": {"A.xml": "bb"}}
    with pytest.raises(SnapshotInvalid, match="stale"):
        read_snapshot(path, other)


def test_the_key_names_everything_that_shapes_the_snapshot(tmp_path: Path) -> None:
    key = snapshot.snapshot_key({"B.xml": "22", "A.xml": "11"}, "cell-1")
    assert set(key) == {"format", "uacell", "code", "asyncua", "python", "nodesets", "cell"}
    assert list(key["nodesets"]) == ["A.xml", "B.xml"]
    others = [
        snapshot.snapshot_key({"A.xml": "11", "B.xml": "23"}, "cell-1"),
        snapshot.snapshot_key({"A.xml": "11", "B.xml": "22"}, "cell-2"),
    ]
    assert all(other != key for other in others)
    # One file per key: serving another cell does not evict this one's snapshot.
    paths = {snapshot.snapshot_path(tmp_path, k) for k in [key, *others]}
    assert len(paths) == 3 and all(p.parent == tmp_path for p in paths)
    assert snapshot.snapshot_path(tmp_path, dict(key)) == snapshot.snapshot_path(tmp_path, key)


def test_the_cell_digest_follows_the_cells_shape_only() -> None:
    from uacell.binding.cell import cell_digest, demo_cell
    from uacell.catalog import companions

    roots = [root for c in companions() for root in c.roots]
    cell_digest = functools.partial(cell_digest, roots=roots)
    demo = demo_cell()
    assert cell_digest(demo) == cell_digest(demo_cell()) == cell_digest(None)
    renamed = demo_cell()
    renamed[1][1].name = "Filler9"
    assert cell_digest(renamed) != cell_digest(demo)
    respecified = demo_cell()
    respecified[1][1].spec = object()  # equipment settings are the binders' business
    assert cell_digest(respecified) == cell_digest(demo)
    # history's HA Configuration nodes are in the snapshot: [history] on or off is another snapshot
    from uacell.history.config import HistoryConfig
    from uacell.history.setup import history_shape

    on, off = HistoryConfig(), HistoryConfig(enabled=False)
    assert cell_digest(demo, history_shape(on)) != cell_digest(demo, history_shape(off))


def test_only_the_most_recent_snapshots_are_kept(tmp_path: Path) -> None:
    for i in range(snapshot.KEEP + 2):
        path = tmp_path / f"{snapshot.PREFIX}{i}{snapshot.SUFFIX}"
        path.write_bytes(b"x")
        os.utime(path, ns=(i * 10**9, i * 10**9))
    snapshot.prune(tmp_path)
    kept = sorted(p.name for p in tmp_path.iterdir())
    assert kept == [f"{snapshot.PREFIX}{i}{snapshot.SUFFIX}" for i in range(2, snapshot.KEEP + 2)]


@pytest.mark.parametrize(
    "damage, reason",
    [
        (lambda data: data[:-1] + bytes([data[-1] ^ 1]), "damaged"),  # one bit of the last node
        (lambda data: data[: len(data) // 2], "damaged"),  # cut short
        (lambda data: b"not a snapshot at all", "not a snapshot"),
        (lambda data: snapshot.MAGIC + b"\x00\x00\x00\x05{oops", "metadata"),
        (lambda data: b"", "cannot be read"),
    ],
    ids=["flipped-bit", "truncated", "foreign", "bad-metadata", "empty"],
)
def test_a_damaged_snapshot_is_refused(tmp_path: Path, damage, reason: str) -> None:
    path = tmp_path / NAME
    _write(path)
    path.write_bytes(damage(path.read_bytes()))
    with pytest.raises(SnapshotInvalid, match=reason):
        read_snapshot(path, KEY)


def test_a_write_that_fails_leaves_the_old_snapshot_whole(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path = tmp_path / NAME
    _write(path, _nodes(3))
    before = path.read_bytes()

    def fail(fd: int) -> None:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "fsync", fail)  # the os module the snapshot writer calls
    with pytest.raises(OSError, match="No space"):
        _write(path, _nodes(7))
    monkeypatch.undo()
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == [NAME]
    found = read_snapshot(path, KEY)
    assert found is not None and found.nodes.stored == 3


def test_a_cancelled_write_writes_nothing(tmp_path: Path) -> None:
    cancel = threading.Event()
    cancel.set()
    with pytest.raises(snapshot.WriteCancelled):
        write_snapshot(tmp_path / NAME, KEY, [], stripped_copy(_nodes()), cancel=cancel)
    assert list(tmp_path.iterdir()) == []


def test_a_writer_beside_a_server_sleeps_after_each_chunk(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    slept: list[float] = []
    monkeypatch.setattr(time, "sleep", slept.append)  # the time module the snapshot writer calls
    write_snapshot(tmp_path / NAME, KEY, [], stripped_copy(_nodes(snapshot.CHUNK * 3)), share=0.5)
    assert len(slept) == 3 and all(s >= 0 for s in slept)
    slept.clear()
    write_snapshot(tmp_path / NAME, KEY, [], stripped_copy(_nodes(snapshot.CHUNK * 3)))  # share 1: no pause
    assert slept == []


def test_discard_removes_the_snapshot_and_leftovers_of_a_crash(tmp_path: Path) -> None:
    path = tmp_path / NAME
    _write(path)
    leftover = tmp_path / f".{NAME}.x1y2.tmp"
    leftover.write_bytes(b"half")
    snapshot.discard(path)
    assert list(tmp_path.iterdir()) == []


# --- servers ---------------------------------------------------------------------------------


async def _start(tmp_path: Path, cache: Path | None, enabled: bool = True, fork: bool = True, files: bool = False):
    """The demo cell. Its models come from the installed models (their own snapshot where `uacell
    models fetch` wrote it: ``first_start_source()``), or with ``files`` from the NodeSet files (a
    models directory without their snapshot: the slowest first start, a few seconds more)."""
    config = fast_config(tmp_path / "data")
    config.server.cache_dir = cache
    config.server.address_space_cache = enabled
    config.server.snapshot_fork = fork
    if files:
        models = tmp_path / "models"
        config.server.models_dir = str(models) if models.exists() else models_copy(models)
    return await start_app(config)


async def _mach_speed(app) -> float:
    async with Client(app.endpoint, timeout=30) as client:
        ns = await client.get_namespace_index("urn:uacell:cell")
        packml = await client.get_namespace_index("http://opcfoundation.org/UA/PackML/")
        node = await client.nodes.objects.get_child(
            [f"{packml}:PackMLObjects", f"{ns}:Filler1", f"{packml}:Status", f"{packml}:MachSpeed"]
        )
        value: float = await node.read_value()
        return value


def _conditions(app) -> dict[object, object]:
    """The nodes of the robot's alarm conditions: their attributes but values, and references."""
    aspace = app.server.iserver.aspace
    ns = app.cell.instantiator.ns
    out: dict[object, object] = {}
    for nodeid in list(aspace.keys()):
        if nodeid.NamespaceIndex == ns and ".SystemOperation.Conditions." in str(nodeid.Identifier):
            data = aspace[nodeid]
            attributes = {a: v.value.Value for a, v in data.attributes.items() if a != ua.AttributeIds.Value}
            out[nodeid] = (attributes, sorted(map(repr, data.references)))
    return out


def _snapshots(cache: Path) -> list[Path]:
    return sorted(cache.glob(f"{snapshot.PREFIX}*{snapshot.SUFFIX}"))


@pytest.mark.parametrize("writer", ["forked", "thread", "fork fails", "configured thread"])
async def test_the_first_start_writes_the_snapshot_and_the_next_starts_from_it(
    tmp_path: Path, writer: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Written by a forked child where the platform has fork, else, or when the fork fails, by a
    thread (the same file)."""
    if writer == "thread":
        monkeypatch.setattr(uacell.server, "forking", lambda: False)
    elif writer == "configured thread":
        monkeypatch.setattr(uacell.server, "run_forked", None)  # a fork would fail the test
    elif not forked.forking():
        pytest.skip("the platform has no fork")
    elif writer == "fork fails":

        def no_memory() -> int:
            raise OSError(errno.ENOMEM, "Cannot allocate memory")

        monkeypatch.setattr(os, "fork", no_memory)
    cache = tmp_path / "cache"
    # the default writer's first start builds from the NodeSet files, the others' from the models
    first = await _start(tmp_path, cache, fork=writer != "configured thread", files=writer == "forked")
    try:
        assert first.address_space_source == ("nodesets" if writer == "forked" else first_start_source())
        await first.snapshot_written()
        [path] = _snapshots(cache)
        speed = await _mach_speed(first)
        conditions = _conditions(first)
    finally:
        await first.stop()
    written = path.stat().st_mtime_ns
    second = await _start(tmp_path, cache)
    try:
        assert second.address_space_source == "snapshot"
        assert await _mach_speed(second) == speed
        # what binders make at every start (the robot's alarm conditions, its programs' file nodes)
        # is copied from the templates kept in the snapshot: the same nodes as the first start's walk
        assert second.cell.instantiator.walked == 0 and second.cell.instantiator.copied >= 2
        assert (ua.NodeId(ua.ObjectIds.AlarmConditionType), (), ()) in second.cell.instantiator.templates
        assert _conditions(second) == conditions and len(conditions) > 20
        # a kept variable's HA Configuration came with the snapshot, its history is on as before
        aspace = second.server.iserver.aspace
        ns = second.cell.instantiator.ns
        assert ua.NodeId("Filler1.Status.MachSpeed.HAConfiguration.Stepped", ns) in aspace
        assert second.history is not None
        # ... and it is stored marked as historized (a restart writes no such attribute again)
        key = snapshot.snapshot_key({m.filename: m.sha256 for m in official()}, second.snapshot_digest)
        stored = read_snapshot(path, key)
        assert stored is not None
        kept = stored.nodes[ua.NodeId("Filler1.Status.MachSpeed", ns)].attributes
        assert kept[ua.AttributeIds.Historizing].value.Value.Value is True
        for attr in (ua.AttributeIds.AccessLevel, ua.AttributeIds.UserAccessLevel):
            assert kept[attr].value.Value.Value & ua.AccessLevel.HistoryRead.mask
        await second.snapshot_written()  # nothing to write
    finally:
        await second.stop()
    assert _snapshots(cache) == [path] and path.stat().st_mtime_ns == written  # read, not rewritten


async def test_the_nodes_companions_give_their_parts_come_with_the_snapshot(tmp_path: Path) -> None:
    """A PackML unit's OEE folder, StartParameters and InjectFault, and a machine's building blocks
    (``Companion.shape``) are made with the cell, before the snapshot is taken: a restart finds them
    and their HA Configurations stored there, not made again, and the binders write into them (the
    unit's figures, the machine's states). A machine's Identification, whose members come from its
    equipment too, is made by the binder at every start."""
    cache = tmp_path / "cache"
    first = await _start(tmp_path, cache)
    try:
        await first.snapshot_written()
    finally:
        await first.stop()
    second = await _start(tmp_path, cache)
    try:
        assert second.address_space_source == "snapshot"
        ns = second.cell.instantiator.ns
        nodes = second.server.iserver.aspace._nodes
        assert isinstance(nodes, LazyNodes)
        made_with_the_cell = (
            *("OEE", "OEE.Availability", "OEE.GoodCount", "OEE.OEE.HAConfiguration"),
            *("Status.StartParameters", "InjectFault", "InjectFault.InputArguments"),
        )
        for name in made_with_the_cell:
            node = ua.NodeId(f"Filler1.{name}", ns)
            assert (node.NamespaceIndex, node.Identifier) in nodes._where, name  # stored, not made here
        blocks = ("MachineryBuildingBlocks", "MachineryItemState", "MachineryOperationMode")
        for machine in ("Filler1", "Robot1"):
            stored = (blocks[0], *(f"{blocks[0]}.{name}.CurrentState" for name in blocks[1:]))
            for name in stored:
                node = ua.NodeId(f"{machine}.{name}", ns)
                assert (node.NamespaceIndex, node.Identifier) in nodes._where, (machine, name)
            identification = ua.NodeId(f"{machine}.Identification", ns)
            assert (identification.NamespaceIndex, identification.Identifier) not in nodes._where
            assert identification in nodes  # made by the binder
        binding = second.registry(UNITS).get("Filler1")
        assert binding is not None
        expected = binding.unit.oee_values()
        async with Client(second.endpoint, timeout=30) as client:
            for machine, bound in second.registry(MACHINES).items():
                for name, model in (("MachineryItemState", bound.machine.item_state),
                                    ("MachineryOperationMode", bound.machine.operation_mode)):  # fmt: skip
                    node = client.get_node(ua.NodeId(f"{machine}.{blocks[0]}.{name}.CurrentState", ns))
                    assert (await node.read_value()).Text == model.current, (machine, name)
            for key, value in expected.items():
                node = client.get_node(ua.NodeId(f"Filler1.OEE.{key.split('/')[1]}", ns))
                assert await node.read_value() == value
                vtype = (await node.read_data_value()).Value.VariantType
                assert vtype == (ua.VariantType.Double if isinstance(value, float) else ua.VariantType.UInt32)
    finally:
        await second.stop()


def test_the_code_of_a_shape_function_is_part_of_the_snapshot_key(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from uacell.core.companion import shapes_digest

    module = tmp_path / "uacell_test_shape.py"
    module.write_text("async def shape(space, cell):\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    before = shapes_digest(["uacell_test_shape:shape"])
    assert shapes_digest(["uacell_test_shape:shape"]) == before
    module.write_text("async def shape(space, cell):\n    return None\n")
    assert shapes_digest(["uacell_test_shape:shape"]) != before
    assert shapes_digest([]) != before


async def test_another_cell_gets_its_own_snapshot(tmp_path: Path) -> None:
    from uacell.config import load_cell
    from uacell.core.cell_file import builtin_cell_path

    cache = tmp_path / "cache"
    demo = await _start(tmp_path, cache)
    await demo.snapshot_written()
    await demo.stop()
    config = fast_config(tmp_path / "data")
    config.server.cache_dir = cache
    config.cell = load_cell(builtin_cell_path("example"))
    example = await start_app(config)
    try:
        assert example.address_space_source == first_start_source()
        await example.snapshot_written()
    finally:
        await example.stop()
    assert len(_snapshots(cache)) == 2
    again = await _start(tmp_path, cache)
    try:
        assert again.address_space_source == "snapshot"  # the demo cell's is still there
    finally:
        await again.stop()


@pytest.mark.parametrize("spoil", ["damage", "stale"])
async def test_a_damaged_or_stale_snapshot_is_rebuilt_silently(
    tmp_path: Path, spoil: str, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    cache = tmp_path / "cache"
    first = await _start(tmp_path, cache)
    await first.snapshot_written()
    await first.stop()
    [path] = _snapshots(cache)
    if spoil == "damage":
        data = bytearray(path.read_bytes())
        data[len(data) // 2] ^= 0xFF
        path.write_bytes(bytes(data))
    else:
        monkeypatch.setattr(snapshot, "__version__", "0.0.0-older")
    with caplog.at_level(logging.INFO, logger="uacell.ua.nodesets"):
        again = await _start(tmp_path, cache)
    try:
        assert again.address_space_source == first_start_source()
        assert await _mach_speed(again) > 0
        await again.snapshot_written()
    finally:
        await again.stop()
    said = [r.getMessage() for r in caplog.records if r.levelno == logging.INFO and "snapshot" in r.getMessage()]
    # A damaged file is named and removed; a stale one is keyed differently: it is simply not found.
    expected = "is damaged" if spoil == "damage" else "no address-space snapshot for this cell"
    assert any(expected in m for m in said), said
    assert not [r for r in caplog.records if r.levelno >= logging.WARNING and "snapshot" in r.getMessage()]
    key = snapshot.snapshot_key(_pinned(), again.snapshot_digest)
    assert read_snapshot(snapshot.snapshot_path(cache, key), key) is not None  # a good one again


def _pinned() -> dict[str, str]:
    return {m.filename: m.sha256 for m in official()}


async def test_a_stop_does_not_wait_for_the_snapshot_and_leaves_no_half_file(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    app = await _start(tmp_path, cache)
    assert app.address_space_source == first_start_source()
    await app.stop()  # at once: the snapshot is still being written
    assert not list(cache.glob(".*.tmp"))
    key = snapshot.snapshot_key(_pinned(), app.snapshot_digest)
    for path in _snapshots(cache):  # whole, if the write won the race
        assert read_snapshot(path, key) is not None


async def test_with_the_cache_off_nothing_is_read_or_written(tmp_path: Path) -> None:
    cache = tmp_path / "cache"
    app = await _start(tmp_path, cache, enabled=False, files=True)
    try:
        assert app.address_space_source == "nodesets"
        await app.snapshot_written()
        # what a companion's shape makes with the cell, its binder made (no snapshot was captured)
        ns = app.cell.instantiator.ns
        aspace = app.server.iserver.aspace
        for name in ("OEE.Availability", "Status.StartParameters", "InjectFault.InputArguments"):
            assert ua.NodeId(f"Filler1.{name}", ns) in aspace, name
        assert ua.NodeId("Filler1.InjectFault", ns) in app.dispatcher.methods  # and bound
    finally:
        await app.stop()
    assert not cache.exists()


async def test_the_default_cache_is_in_the_data_directory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("UACELL_CACHE_DIR", raising=False)
    config = fast_config(tmp_path / "data")
    assert config.server.snapshot_dir == tmp_path / "data" / "cache"
    monkeypatch.setenv("UACELL_CACHE_DIR", os.fspath(tmp_path / "elsewhere"))
    assert fast_config(tmp_path / "data").server.snapshot_dir == tmp_path / "elsewhere"


# --- the models' snapshot (decision 46) ----------------------------------------------------------


async def test_a_first_start_takes_the_models_from_their_snapshot_and_writes_the_whole_cell(tmp_path: Path) -> None:
    """With the models' snapshot beside the NodeSet files, a first start reads the models from it,
    builds the cell and writes the cell's snapshot: every node of it, also those of the models'
    snapshot it never loaded; a restart from that has exactly the nodes a build from the files has."""
    from uacell.ua.nodesets import models_snapshot_path, write_models_snapshot

    models = models_copy(tmp_path / "models")
    written = await write_models_snapshot(official(), models)
    assert written == models_snapshot_path(official(), models) and written.parent == Path(models)
    config = fast_config(tmp_path / "data")
    config.server.cache_dir = tmp_path / "cache"
    config.server.models_dir = models
    first = await start_app(config)
    try:
        assert first.address_space_source == "models snapshot"
        speed = await _mach_speed(first)
        first_types = first.cell.extras()["types"]  # found in the models' type index
        await first.snapshot_written()
    finally:
        await first.stop()
    config.server.port = free_port()
    second = await start_app(config)
    try:
        assert second.address_space_source == "snapshot"
        assert await _mach_speed(second) == speed
        restored = snapshot.every_node_id(second.server.iserver.aspace)
    finally:
        await second.stop()
    plain = fast_config(tmp_path / "plain")
    plain.server.address_space_cache = False
    built = await start_app(plain)
    try:
        assert built.address_space_source == "nodesets"
        assert restored == snapshot.every_node_id(built.server.iserver.aspace)
        assert first_types == built.cell.extras()["types"] and len(first_types) >= 5  # found by walking
    finally:
        await built.stop()


def test_the_type_index_has_each_type_once_by_class_namespace_and_name() -> None:
    """``type_index`` keeps type nodes only, by (NodeClass, namespace URI, name); a name two types of
    one class share in a namespace is left out, so that a lookup walks the hierarchy instead."""
    from types import SimpleNamespace

    from asyncua import ua

    from uacell.models.tables import UA_NS
    from uacell.ua.nodesets import type_index

    def node(cls: ua.NodeClass, name: str) -> SimpleNamespace:
        wrap = lambda v: SimpleNamespace(value=SimpleNamespace(Value=SimpleNamespace(Value=v)))  # noqa: E731
        A = ua.AttributeIds
        return SimpleNamespace(attributes={A.NodeClass: wrap(cls), A.BrowseName: wrap(ua.QualifiedName(name))})

    nodes = {
        ua.NodeId(58, 0): node(ua.NodeClass.ObjectType, "BaseObjectType"),
        ua.NodeId(1002, 2): node(ua.NodeClass.ObjectType, "ControllerType"),
        ua.NodeId(3001, 2): node(ua.NodeClass.DataType, "ControllerType"),  # another class: its own entry
        ua.NodeId(5001, 2): node(ua.NodeClass.Object, "Controller1"),  # an instance: not a type
        ua.NodeId(1003, 2): node(ua.NodeClass.ObjectType, "Twice"),
        ua.NodeId(1004, 2): node(ua.NodeClass.ObjectType, "Twice"),
        ua.NodeId(7, 9): node(ua.NodeClass.ObjectType, "Elsewhere"),  # a namespace not given
    }
    index = type_index(nodes, ["urn:a"])
    assert index == {
        (int(ua.NodeClass.ObjectType), UA_NS, "BaseObjectType"): 58,
        (int(ua.NodeClass.ObjectType), "urn:a", "ControllerType"): 1002,
        (int(ua.NodeClass.DataType), "urn:a", "ControllerType"): 3001,
    }


async def test_a_damaged_models_snapshot_is_removed_and_the_files_are_read(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    from uacell.ua.nodesets import write_models_snapshot

    models = models_copy(tmp_path / "models")
    path = await write_models_snapshot(official(), models)
    data = bytearray(path.read_bytes())
    data[len(data) // 2] ^= 0xFF
    path.write_bytes(bytes(data))
    config = fast_config(tmp_path / "data")
    config.server.cache_dir = tmp_path / "cache"
    config.server.models_dir = models
    with caplog.at_level(logging.INFO, logger="uacell.ua.nodesets"):
        app = await start_app(config)
    try:
        assert app.address_space_source == "nodesets"
        assert await _mach_speed(app) > 0
    finally:
        await app.stop()
    assert not path.exists()
    assert any("snapshot of the models" in r.getMessage() and "is damaged" in r.getMessage() for r in caplog.records)
