"""What an address-space snapshot keeps beside its nodes so that a restart reads nothing else: the
models' data types (uacell.ua.data_types) and the state-machine tables (StateTables.adopt).

asyncua's registry of data type classes lives in its module, for the life of the process: a restart
is a new process, so the restores here run in fresh interpreters and report what they registered.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from asyncua import ua
from asyncua.server.address_space import AttributeValue, NodeData
from helpers import free_port, models_copy, official

from uacell.ua import data_types
from uacell.ua.data_types import Enumeration, Structure
from uacell.ua.snapshot import read_snapshot

SRC = str(Path(__file__).parents[1] / "src")

# A fresh interpreter restores the models' snapshot into a server and prints every class asyncua
# then has for a type outside namespace 0. "walk": without the kept entries (asyncua looks for them).
_RESTORE = """
import asyncio, dataclasses, json, sys
from pathlib import Path
from asyncua import Server, ua
from uacell.catalog import companions
from uacell.core.companion import models_of
from uacell.models import official_models
from uacell.ua import data_types, nodesets

walk = sys.argv[2] == "walk"
if walk:
    data_types.stored = lambda extras: None
else:
    async def refuse(self, *args):
        raise AssertionError("asyncua walked for the data types")
    Server.load_data_type_definitions = refuse

async def main():
    server = Server()
    prepared = await nodesets.init_address_space(
        server, official_models(models_of(companions())), sys.argv[1], Path(sys.argv[3])
    )
    assert prepared.source == "models snapshot", prepared.source
    out = {}
    for nodeid, cls in ua.extension_objects_by_datatype.items():
        if nodeid.NamespaceIndex:
            fields = [[f.name, str(f.type)] for f in dataclasses.fields(cls)]
            encoding = ua.typeid_by_extension_objects[cls].to_string()
            out[cls.__name__] = ["structure", nodeid.to_string(), encoding, fields, cls().__class__ is cls]
    for nodeid, cls in ua.enums_by_datatype.items():
        if nodeid.NamespaceIndex:
            members = {n: m.value for n, m in cls.__members__.items()}
            out[cls.__name__] = ["enumeration", nodeid.to_string(), members, getattr(ua, cls.__name__) is cls]
    print(json.dumps(out, sort_keys=True))

asyncio.run(main())
"""


def _restore(models: str, cache: Path, how: str) -> dict[str, list[object]]:
    done = subprocess.run(
        [sys.executable, "-c", _RESTORE, models, how, str(cache)],
        capture_output=True,
        text=True,
        timeout=120,
        check=False,
        env={**os.environ, "PYTHONPATH": SRC},
    )
    assert done.returncode == 0, done.stderr[-3000:]
    result: dict[str, list[object]] = json.loads(done.stdout.splitlines()[-1])
    return result


async def test_a_restore_makes_the_models_data_types_asyncua_would_find(tmp_path: Path) -> None:
    """From the kept entries, a fresh process has every structure and enumeration of the models
    that asyncua's own walk through the address space gives it, the same classes (fields and their
    types, members, NodeIds, encodings), without the walk."""
    from uacell.ua.nodesets import models_snapshot_key, models_snapshot_path, write_models_snapshot

    models = models_copy(tmp_path / "models")
    await write_models_snapshot(official(), models)
    snapshot = read_snapshot(models_snapshot_path(official(), models), models_snapshot_key(official()))
    assert snapshot is not None
    found = data_types.stored(snapshot.extras)
    assert found is not None
    kept = {e.name: e for e in found}
    descriptor = kept["PackMLDescriptorDataType"]
    assert isinstance(descriptor, Structure)
    assert descriptor.data_type.Identifier == 16
    assert descriptor.encoding.NamespaceIndex == descriptor.data_type.NamespaceIndex
    assert [f.Name for f in descriptor.definition.Fields] == ["ID", "Name", "Unit", "Value"]
    assert isinstance(kept["ExecutionModeEnumeration"], Enumeration)

    made = _restore(models, tmp_path / "cache-kept", "kept")
    walked = _restore(models, tmp_path / "cache-walked", "walk")
    assert made == walked
    ids = [descriptor.data_type.to_string(), descriptor.encoding.to_string()]
    assert made["PackMLDescriptorDataType"][:3] == ["structure", *ids]
    assert made["PackMLDescriptorDataType"][3] == [
        ["ID", "ua.Int32"],
        ["Name", "ua.String"],
        ["Unit", "ua.EUInformation"],
        ["Value", "ua.Float"],
    ]
    assert made["ExecutionModeEnumeration"][2] == {"CONTINUOUS": 1, "CYCLE": 0, "STEP": 2}
    assert {name for name, (kind, *_rest) in made.items() if kind == "structure"} >= {
        "PackMLAlarmDataType",
        "PackMLCountDataType",
        "PackMLIngredientsDataType",
        "PackMLProductDataType",
    }


def _data_type_node(nodeid: ua.NodeId, definition: object) -> NodeData:
    node = NodeData(nodeid)
    node.attributes[ua.AttributeIds.DataTypeDefinition] = AttributeValue(ua.DataValue(ua.Variant(definition)))
    return node


def _field(name: str, data_type: int) -> ua.StructureField:
    return ua.StructureField(Name=name, DataType=ua.NodeId(data_type), ValueRank=-1, IsOptional=False)


def test_a_class_that_is_not_what_its_definition_makes_is_not_described(monkeypatch: pytest.MonkeyPatch) -> None:
    """A registered structure whose fields differ from its node's definition (or a union, which
    the description does not cover) makes ``registered`` say None: a restart then walks."""

    @dataclasses.dataclass
    class Pair:
        A: int = 0

    nodeid, encoding = ua.NodeId(9001, 7), ua.NodeId(9002, 7)
    sdef = ua.StructureDefinition(DefaultEncodingId=encoding, Fields=[_field("A", 6), _field("B", 6)])
    nodes = {nodeid: _data_type_node(nodeid, sdef)}
    monkeypatch.setitem(ua.extension_objects_by_datatype, nodeid, Pair)
    monkeypatch.setitem(ua.typeid_by_extension_objects, Pair, encoding)
    assert data_types.registered(nodes) is None

    sdef.Fields = [_field("A", 6)]
    assert [e for e in data_types.registered(nodes) or [] if e.data_type == nodeid] == [
        Structure("Pair", nodeid, encoding, sdef)
    ]
    sdef.StructureType = ua.StructureType.Union
    assert data_types.registered(nodes) is None


def test_an_entry_is_made_once_and_one_asyncua_cannot_make_raises() -> None:
    pair = Structure(
        "UacellTestPair",
        ua.NodeId(9011, 7),
        ua.NodeId(9012, 7),
        ua.StructureDefinition(DefaultEncodingId=ua.NodeId(9012, 7), Fields=[_field("A", 6), _field("B", 12)]),
    )
    assert data_types.register([pair]) == 1
    made = ua.extension_objects_by_datatype[pair.data_type]
    assert ua.UacellTestPair is made and made.data_type == pair.data_type
    assert ua.extension_objects_by_typeid[pair.encoding] is made
    assert [(f.name, f.type) for f in dataclasses.fields(made)] == [("A", "ua.Int32"), ("B", "ua.String")]
    assert data_types.register([pair]) == 0 and ua.extension_objects_by_datatype[pair.data_type] is made

    # a field of a type asyncua does not know: it cannot make the class
    broken = Structure(
        "UacellTestBroken",
        ua.NodeId(9101, 7),
        ua.NodeId(9102, 7),
        ua.StructureDefinition(Fields=[ua.StructureField(Name="X", DataType=ua.NodeId(9999, 7))]),
    )
    with pytest.raises(RuntimeError, match="Unknown datatype"):
        data_types.register([broken])
    assert broken.data_type not in ua.extension_objects_by_datatype


async def test_entries_that_cannot_be_made_make_asyncua_walk_for_them() -> None:
    from types import SimpleNamespace

    from uacell.ua.nodesets import _register_data_types

    walked: list[bool] = []

    class Server:
        async def load_data_type_definitions(self) -> None:
            walked.append(True)

    broken = Structure(
        "UacellTestBroken2",
        ua.NodeId(9201, 7),
        ua.NodeId(9202, 7),
        ua.StructureDefinition(Fields=[ua.StructureField(Name="X", DataType=ua.NodeId(9999, 7))]),
    )
    await _register_data_types(Server(), SimpleNamespace(extras={"data_types": [broken]}))  # type: ignore[arg-type]
    assert walked == [True]
    await _register_data_types(Server(), SimpleNamespace(extras={"data_types": []}))  # type: ignore[arg-type]
    await _register_data_types(Server(), SimpleNamespace(extras={}))  # type: ignore[arg-type]  # an older snapshot
    assert walked == [True, True]


# --- the state-machine tables kept the same way ---------------------------------------------------


def test_state_tables_take_tables_made_before_and_read_files_only_for_the_others(tmp_path: Path) -> None:
    """``StateTables.adopt`` takes an earlier server's tables (a snapshot's ``fsm_tables``): asked
    for, they are not read again; one it was not given is read from the files (here: none)."""
    from uacell.models import StateTables
    from uacell.models.source import ModelError

    made = StateTables(official())
    task_control = made("Robotics", "TaskControlStateMachineType")
    assert list(made.made()) == [("Robotics", "TaskControlStateMachineType")]

    later = StateTables(official(), str(tmp_path / "no-models-here"))
    junk: dict[Any, Any] = {
        ("Robotics", "Nonsense"): task_control,
        "x": task_control,
        ("PackML", "PackMLBaseStateMachineType"): 1,
    }
    assert later.adopt({**made.made(), **junk}) == 1 and later.adopt(None) == 0
    assert later("Robotics", "TaskControlStateMachineType") is task_control
    with pytest.raises(ModelError):
        later("Robotics", "ReadySubstateMachineType")


async def test_a_restart_takes_its_state_tables_from_the_snapshot(tmp_path: Path) -> None:
    from conftest import fast_config, start_app

    from uacell.ua import snapshot as snap

    config = fast_config(tmp_path / "data")
    config.server.cache_dir = tmp_path / "cache"
    first = await start_app(config)
    try:
        await first.snapshot_written()
        tables = first.tables.made()
        key = snap.snapshot_key({m.filename: m.sha256 for m in official()}, first.snapshot_digest)
    finally:
        await first.stop()
    assert config.server.snapshot_dir is not None  # the cache is on
    kept = read_snapshot(snap.snapshot_path(config.server.snapshot_dir, key), key)
    assert kept is not None and kept.extras["fsm_tables"] == tables
    assert {type_name for _model, type_name in tables} >= {
        "TaskControlStateMachineType",
        "PackMLExecuteStateMachineType",
    }
    config.server.port = free_port()
    second = await start_app(config)
    try:
        assert second.address_space_source == "snapshot"
        for key_, table in tables.items():  # the very objects the snapshot held, not read again
            assert second.tables.made()[key_] == table
    finally:
        await second.stop()
