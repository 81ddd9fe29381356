"""`uacell nodeset export`: the served cell as a NodeSet2 file.

The file is checked by another stack: node-opcua loads the official NodeSets and the export into a
bare server, and its client walks that server and a live uacell serving the same cell.
"""

from __future__ import annotations

import os
import subprocess
import sys
import xml.etree.ElementTree as ET
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from asyncua import ua
from conftest import NodeServer, ServeProcess, fast_config, run_node, start_serve
from helpers import free_port, official
from test_robotics_interop import run_trusted

from uacell.binding.cell import CELL_NAMESPACE
from uacell.cli.main import main
from uacell.cli.nodeset_export import export_cell
from uacell.core.cell_file import builtin_cell_path
from uacell.models.source import locate_models
from uacell.robotics.binding.core import programs_root
from uacell.security.users import UserStore
from uacell.ua.snapshot import every_node_id

X = "{http://opcfoundation.org/UA/2011/03/UANodeSet.xsd}"
U = "{http://opcfoundation.org/UA/2008/02/Types.xsd}"
NODE_TAGS = (X + "UAObject", X + "UAVariable", X + "UAMethod")


def exploding_factory(spec: object) -> object:
    raise AssertionError("the export called an equipment factory")


def declared_models() -> list[dict[str, str | None]]:
    """Each official file's own <Model> element, as the file says it."""
    found = []
    for path in locate_models(official()).values():
        with path.open("rb") as f:
            for _, element in ET.iterparse(f, events=("start",)):
                if element.tag == X + "Model":
                    found.append({k: element.get(k) for k in ("ModelUri", "Version", "PublicationDate")})
                    break
    return found


def test_the_export_requires_each_official_model_as_its_file_declares_it(tmp_path):
    out = tmp_path / "cell.xml"
    assert main(["nodeset", "export", "-o", str(out)]) == 0
    root = ET.parse(out).getroot()
    assert [u.text for u in root.iter(X + "Uri")] == [CELL_NAMESPACE, *(m.namespace_uri for m in official())]
    (model,) = root.iter(X + "Model")
    assert model.get("ModelUri") == CELL_NAMESPACE
    required = [{k: r.get(k) for k in ("ModelUri", "Version", "PublicationDate")} for r in model]
    assert required[0]["ModelUri"] == "http://opcfoundation.org/UA/" and required[0]["Version"]
    assert required[1:] == declared_models()
    # Every alias the nodes use is declared.
    aliases = {a.get("Alias") for a in root.iter(X + "Alias")}
    used = {r.get("ReferenceType") for r in root.iter(X + "Reference")} | {
        v.get("DataType") for v in root.iter(X + "UAVariable")
    }
    assert None not in used  # every reference names its type, every variable its data type
    assert {u for u in used if u is not None and "=" not in u} <= aliases


async def test_the_export_holds_every_served_node_of_the_cell_with_its_nodeid(app, tmp_path):
    """What an in-process server serves and what the file says, node for node (the file directories'
    entries, the Programs folder's files, are data and stay out)."""
    config = fast_config(tmp_path / "export-data")
    root = ET.fromstring(await export_cell(config))
    aspace = app.server.iserver.aspace
    ns = await app.server.get_namespace_index(CELL_NAMESPACE)
    exported = {}
    for element in root:
        if element.tag in NODE_TAGS:
            nodeid = ua.NodeId.from_string(element.get("NodeId"))
            assert nodeid.NamespaceIndex == 1
            exported[ua.NodeId(nodeid.Identifier, ns)] = element
    # Server/CurrentRole (decision 39) is the server's, per session, not the cell's: not exported.
    # (Every node: a server started from a snapshot has not loaded those nobody asked for yet.)
    served = {
        n
        for n in every_node_id(aspace)
        if n.NamespaceIndex == ns and "/" not in str(n.Identifier) and not str(n.Identifier).startswith("Server.")
    }
    assert set(exported) == served
    for nodeid, element in exported.items():
        name = aspace[nodeid].attributes[ua.AttributeIds.BrowseName].value.Value.Value
        index = {0: 0, ns: 1}.get(name.NamespaceIndex)
        prefix = f"{index}:" if index else ""
        if index is None:  # a model's namespace: the file's index for that model
            uri = (await app.server.get_namespace_array())[name.NamespaceIndex]
            prefix = f"{[u.text for u in root.iter(X + 'Uri')].index(uri) + 1}:"
        assert element.get("BrowseName") == prefix + name.Name
    # The server-specific methods have arguments with NodeIds of their own (not a counter's).
    fault = exported[ua.NodeId("Filler1.InjectFault.InputArguments", ns)]
    names = [n.text for n in fault.iter(U + "Name")]
    assert names == ["Id", "Message"]


def test_the_export_reads_nothing_of_the_installation_and_calls_no_equipment(tmp_path):
    data = tmp_path / "data"
    UserStore.in_data_dir(data).add("alice-in-plant", "operator", "a-long-password-1")
    programs = programs_root(data, "Robot1.Controllers.Controller1")
    programs.mkdir(parents=True)
    (programs / "secret_recipe.robot").write_text("# nothing\n", encoding="utf-8")
    before = sorted(p.relative_to(data) for p in data.rglob("*"))
    config = tmp_path / "cell.toml"
    config.write_text(
        f'[server]\ndata_dir = "{data}"\n\n[robot]\nequipment = "test_nodeset_export:exploding_factory"\n',
        encoding="utf-8",
    )
    out = tmp_path / "cell.xml"
    assert main(["nodeset", "export", "--config", str(config), "-o", str(out)]) == 0
    text = out.read_text(encoding="utf-8")
    assert "<UAObject" in text and 'NodeId="ns=1;s=Robot1.Controllers.Controller1"' in text
    for secret in ("alice-in-plant", "secret_recipe", str(data), str(tmp_path), "BEGIN CERTIFICATE"):
        assert secret not in text
    assert sorted(p.relative_to(data) for p in data.rglob("*")) == before  # nothing written there
    # Two exports of one configuration are the same bytes (a file to keep under version control).
    again = tmp_path / "again.xml"
    assert main(["nodeset", "export", "--config", str(config), "-o", str(again)]) == 0
    assert again.read_bytes() == out.read_bytes()


# --- the independent check: node-opcua ----------------------------------------------------------


def run_export(tmp_path: Path, config: Path | None) -> Path:
    out = tmp_path / "export.xml"
    args = ["--config", str(config)] if config else []
    subprocess.run(
        [sys.executable, "-m", "uacell", "nodeset", "export", *args, "-o", str(out)],
        check=True,
        timeout=300,
        env={**os.environ, "UACELL_DATA_DIR": str(tmp_path / "export-data")},
    )
    return out


@pytest.fixture
def bare_server() -> Iterator[list[NodeServer]]:
    started: list[NodeServer] = []
    yield started
    for server in started:
        server.stop()


def differences(live: dict[str, Any], bare: dict[str, Any]) -> list[str]:
    lines = [f"only served by uacell: {k}" for k in sorted(set(live) - set(bare))]
    lines += [f"only in the export: {k}" for k in sorted(set(bare) - set(live))]
    for key in sorted(set(live) & set(bare)):
        for field in sorted(set(live[key]) | set(bare[key])):
            if live[key].get(field) != bare[key].get(field):
                lines.append(f"{key} {field}: uacell {live[key].get(field)!r}, export {bare[key].get(field)!r}")
    return lines


@pytest.mark.interop
@pytest.mark.parametrize("cell", ["demo", "example"])
def test_node_opcua_sees_the_same_cell_in_the_export_as_in_uacell(cell, tmp_path, bare_server):
    config = None
    if cell == "example":
        config = tmp_path / "example.toml"
        config.write_text(builtin_cell_path("example").read_text(encoding="utf-8"), encoding="utf-8")
    export = run_export(tmp_path, config)
    models = locate_models(official())
    # node-opcua's own server (interop/bench_server.js) with the official NodeSets and the export.
    port = free_port()
    files = [str(p) for p in (*(models[m.key] for m in official()), export)]
    bare_server.append(NodeServer("bench_server.js", [str(port), *files], tmp_path / "node-opcua.log"))
    live: ServeProcess = start_serve(tmp_path / "data", *(["--config", str(config)] if config else []))
    try:
        served = run_trusted(live, "cell_tree.js")["nodes"]
    finally:
        live.stop()
    loaded = run_node("cell_tree.js", f"opc.tcp://127.0.0.1:{port}/")["nodes"]
    found = differences(served, loaded)
    assert not found, "\n".join(found)
    # What was compared: every part, method arguments included.
    exported = sum(1 for e in ET.parse(export).getroot() if e.tag in NODE_TAGS)
    assert len(loaded) == exported > 400
    arguments = [n["arguments"] for n in loaded.values() if "arguments" in n]
    assert any(a and a[0]["name"] == "Name" for a in arguments)  # LoadByName's
    serials = {n["value"] for n in loaded.values() if n["browseName"].endswith("/DI/:SerialNumber")}
    assert {"DEMO-R1", "DEMO-C1", "DEMO-A1"} <= serials if cell == "demo" else {"EX-W-CB", "EX-H-A1"} <= serials
    types = {r[2] for n in loaded.values() for r in n["references"] if r[0] == "i=40"}
    assert {"http://opcfoundation.org/UA/Robotics/;i=1002", "http://opcfoundation.org/UA/PackML/;i=6"} <= types
