"""``uacell nodeset export``: the configured cell's instances as a NodeSet2 file (OPC 10000-6, Annex F).

The address space is assembled exactly as ``uacell serve`` assembles it (``UacellServer.setup()``:
models, cell, every binder), but nothing listens and nothing of the installation is read or written:
the server is set up in a temporary data directory and every part runs on its simulator, so no
user, password, certificate, program file, stored PackML data or equipment driver can reach the
file. What is exported:

- every node in the cell's namespace (``urn:uacell:cell``) reachable from the cell's parts, with its
  NodeId as served; uacell defines no types of its own, so there are no type nodes;
- left out: the entries of file directories (a controller's ``Programs``): they are the directory's
  contents, which change at run time, not the cell's model;
- all of a node's references (HasTypeDefinition, HasComponent, HasProperty, HasModellingRule,
  Organizes, the companions' own such as Controls), including the inverse ones into the official
  models that attach the parts to ``DeviceSet`` and ``PackMLObjects``;
- DataType, ValueRank, ArrayDimensions, AccessLevel, MinimumSamplingInterval of variables, and their
  values as a freshly started server has them (built-in types, LocalizedText, NodeId and the
  standard structures such as the methods' ``Argument`` arrays). Left out: values of
  companion-specific structures (the PackML Admin counters: run-time data), DateTime values and
  ByteStrings (a condition's Time and EventId: stamps of the moment; bytes could be key material);
- ``<Models>``: the cell's model (``urn:uacell:cell``, uacell's version) requiring each official
  NodeSet with the ModelUri, Version and PublicationDate its file declares, and the OPC UA base model
  in the highest version those files require.

uacell writes the XML itself rather than with asyncua's ``XmlExporter``, which writes no
``<Models>``/RequiredModel, exports each node's references even to nodes left out, writes the
per-session UserAccessLevel and the current Executable, and documents its value export as able to
produce invalid files (decision 32).
"""

from __future__ import annotations

import argparse
import base64
import dataclasses
import datetime
import logging
import math
import sys
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Iterable, Sequence
from copy import deepcopy
from dataclasses import dataclass
from enum import Enum
from pathlib import Path
from typing import Any

from asyncua import ua
from asyncua.server.address_space import AddressSpace

from uacell import __version__
from uacell.binding.cell import CELL_NAMESPACE
from uacell.config import Config
from uacell.core.companion import Companion, models_of
from uacell.host import ServerView
from uacell.models.model_file import ModelFile
from uacell.models.source import locate_models, official_models

log = logging.getLogger(__name__)

__all__ = ["ModelInfo", "export_cell", "model_infos", "nodeset_xml", "run_export"]

BASE_NAMESPACE = "http://opcfoundation.org/UA/"
_UANODESET = "http://opcfoundation.org/UA/2011/03/UANodeSet.xsd"
_TYPES = "http://opcfoundation.org/UA/2008/02/Types.xsd"
_X = "{" + _UANODESET + "}"
_U = "{" + _TYPES + "}"

_A = ua.AttributeIds
_FILE_DIRECTORY_TYPE = ua.NodeId(ua.ObjectIds.FileDirectoryType)
_HIERARCHICAL = {
    ua.NodeId(i)
    for i in (
        ua.ObjectIds.HasComponent,
        ua.ObjectIds.HasProperty,
        ua.ObjectIds.Organizes,
        ua.ObjectIds.HasOrderedComponent,
        ua.ObjectIds.HasAddIn,
    )
}
_ORGANIZES = ua.NodeId(ua.ObjectIds.Organizes)
_HAS_TYPE_DEFINITION = ua.NodeId(ua.ObjectIds.HasTypeDefinition)
# Values of these types are stamps of the moment (a condition's Time, EventId) or opaque bytes (which
# could be key material): never exported.
_RUN_TIME = {ua.VariantType.Null, ua.VariantType.DateTime, ua.VariantType.ByteString, ua.VariantType.Guid}


@dataclass(frozen=True)
class ModelInfo:
    """A model as its NodeSet file declares it (``<Models><Model ...>``)."""

    uri: str
    version: str
    publication_date: str | None


def _declared_model(path: Path) -> tuple[ModelInfo, list[ModelInfo]]:
    """The first ``<Model>`` of a NodeSet file and its RequiredModels (read up to there only)."""
    model: ModelInfo | None = None
    required: list[ModelInfo] = []
    with path.open("rb") as f:
        for event, element in ET.iterparse(f, events=("start", "end")):
            tag = element.tag.rpartition("}")[2]
            if event == "start" and tag == "Model" and model is None:
                model = _info(element)
            elif event == "start" and tag == "RequiredModel" and model is not None:
                required.append(_info(element))
            elif event == "end" and tag == "Model":
                break
    if model is None:
        raise ValueError(f"{path} declares no <Model>")
    return model, required


def _info(element: ET.Element) -> ModelInfo:
    return ModelInfo(element.get("ModelUri", ""), element.get("Version", ""), element.get("PublicationDate"))


def _version_key(version: str) -> tuple[int, ...]:
    return tuple(int(p) if p.isdigit() else 0 for p in version.split("."))


def model_infos(models: Sequence[ModelFile], models_dir: str | None = None) -> list[ModelInfo]:
    """The OPC UA base model and each official NodeSet uacell loads (``models``), as their files declare them."""
    paths = locate_models(models, models_dir)
    infos: list[ModelInfo] = []
    base: list[ModelInfo] = []
    for model in models:
        declared, required = _declared_model(paths[model.key])
        infos.append(declared)
        base.extend(r for r in required if r.uri == BASE_NAMESPACE)
    if base:
        infos.insert(0, max(base, key=lambda m: _version_key(m.version)))
    return infos


class _Writer:
    """One NodeSet2 document over the server's address space (namespace indexes renumbered for the file)."""

    def __init__(self, aspace: AddressSpace, server_namespaces: list[str], file_namespaces: list[str]) -> None:
        self.aspace = aspace
        # server namespace index -> file namespace index (0 stays 0)
        self.index = {server_namespaces.index(uri): i for i, uri in enumerate(file_namespaces, start=1)}
        self.index[0] = 0
        self.aliases: dict[str, str] = {}

    def nodeid(self, nodeid: ua.NodeId) -> str:
        if nodeid.NamespaceIndex not in self.index:
            raise ValueError(f"{nodeid.to_string()} is in a namespace the file does not declare")
        text: str = ua.NodeId(nodeid.Identifier, self.index[nodeid.NamespaceIndex], nodeid.NodeIdType).to_string()
        return text

    def aliased(self, nodeid: ua.NodeId) -> str:
        """A base-namespace type (reference type, data type) by its name, declared in <Aliases>."""
        if nodeid.NamespaceIndex == 0 and isinstance(nodeid.Identifier, int):
            name: str | None = ua.ObjectIdNames.get(nodeid.Identifier)
            if name is not None:
                self.aliases[name] = nodeid.to_string()
                return name
        return self.nodeid(nodeid)

    def qualified(self, name: ua.QualifiedName) -> str:
        index = self.index.get(name.NamespaceIndex, name.NamespaceIndex)
        return f"{index}:{name.Name}" if index else str(name.Name)

    def attribute(self, nodeid: ua.NodeId, attribute: ua.AttributeIds) -> Any:
        data = self.aspace.read_attribute_value(nodeid, attribute)
        return data.Value.Value if data.Value is not None else None

    # --- values (OPC 10000-6, 5.3: XML encoding) -----------------------------------------------
    def value(self, parent: ET.Element, variant: ua.Variant) -> bool:
        """Write ``variant`` as a <Value>; False (nothing written) for values the file leaves out."""
        if variant.Value is None or variant.VariantType in _RUN_TIME:
            return False
        name = variant.VariantType.name
        element = ET.Element(_X + "Value")
        try:
            if isinstance(variant.Value, list | tuple):
                holder = ET.SubElement(element, _U + "ListOf" + name)
                for item in variant.Value:
                    self.scalar(ET.SubElement(holder, _U + name), name, item)
            else:
                self.scalar(ET.SubElement(element, _U + name), name, variant.Value)
        except _LeftOut:
            return False
        parent.append(element)
        return True

    def scalar(self, el: ET.Element, kind: str, value: Any) -> None:
        if kind == "ExtensionObject":
            self.extension_object(el, value)
        elif kind in ("NodeId", "ExpandedNodeId"):
            ET.SubElement(el, _U + "Identifier").text = self.nodeid(value)
        elif kind == "LocalizedText":
            if value.Locale:
                ET.SubElement(el, _U + "Locale").text = value.Locale
            if value.Text is not None:
                ET.SubElement(el, _U + "Text").text = value.Text
        elif kind == "QualifiedName":
            ET.SubElement(el, _U + "NamespaceIndex").text = str(self.index.get(value.NamespaceIndex, 0))
            ET.SubElement(el, _U + "Name").text = value.Name
        elif kind == "StatusCode":
            ET.SubElement(el, _U + "Code").text = str(value.value)
        elif kind == "Guid":
            ET.SubElement(el, _U + "String").text = str(value)
        else:
            el.text = _text(value)

    def extension_object(self, el: ET.Element, value: Any) -> None:
        """A standard structure, with its Default XML encoding; companion-specific ones are left out."""
        name = type(value).__name__
        encoding = getattr(ua.ObjectIds, f"{name}_Encoding_DefaultXml", None)
        if not dataclasses.is_dataclass(value) or encoding is None:
            raise _LeftOut(name)
        type_id = ET.SubElement(el, _U + "TypeId")
        ET.SubElement(type_id, _U + "Identifier").text = f"i={encoding}"
        body = ET.SubElement(el, _U + "Body")
        self.fields(ET.SubElement(body, _U + name), value)

    def fields(self, el: ET.Element, value: Any) -> None:
        for f in dataclasses.fields(value):
            member = getattr(value, f.name)
            kind = _field_kind(f.type)
            child = ET.SubElement(el, _U + f.name)
            if isinstance(member, list | tuple):
                for item in member:
                    self.member(ET.SubElement(child, _U + kind), kind, item)
            elif member is not None:
                self.member(child, kind, member)

    def member(self, el: ET.Element, kind: str, value: Any) -> None:
        if kind in ("NodeId", "ExpandedNodeId", "LocalizedText", "QualifiedName", "StatusCode", "Guid"):
            self.scalar(el, kind, value)
        elif dataclasses.is_dataclass(value):
            self.fields(el, value)
        else:
            el.text = _text(value)


class _LeftOut(Exception):
    """A value the file does not carry (a companion-specific structure)."""


def _field_kind(annotation: Any) -> str:
    """The type name of a structure field (asyncua annotates with strings such as "'list[ua.UInt32]'")."""
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", str(annotation))
    text = text.strip("'\"")
    if text.startswith(("list[", "List[")):
        text = text[5:-1]
    return text.rpartition(".")[2]


def _text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, Enum):
        return str(value.value)
    if isinstance(value, float):
        if math.isnan(value):
            return "NaN"
        if math.isinf(value):
            return "INF" if value > 0 else "-INF"
        return repr(value)
    if isinstance(value, datetime.datetime):
        if value.tzinfo is None:
            value = value.replace(tzinfo=datetime.UTC)
        stamp: str = value.isoformat()
        return stamp.replace("+00:00", "Z")
    if isinstance(value, bytes):
        return base64.b64encode(value).decode("ascii")
    return str(value)


def cell_nodes(aspace: AddressSpace, tops: Iterable[ua.NodeId], namespace: int) -> dict[ua.NodeId, ua.NodeId | None]:
    """Every node of the cell's namespace reachable from its top-level parts, in walk order, with the
    node it was reached from through a hierarchical reference (its ParentNodeId).

    The entries of a file directory (what a FileDirectoryType node organizes) are left out."""
    found: dict[ua.NodeId, ua.NodeId | None] = {}
    queue: list[tuple[ua.NodeId, ua.NodeId | None]] = [(top, None) for top in tops]
    while queue:
        node, parent = queue.pop(0)
        if node in found:
            continue
        found[node] = parent
        data = aspace[node]
        directory = any(
            r.ReferenceTypeId == _HAS_TYPE_DEFINITION and r.NodeId == _FILE_DIRECTORY_TYPE for r in data.references
        )
        for ref in data.references:
            if not ref.IsForward or ref.NodeId.NamespaceIndex != namespace or ref.NodeId in found:
                continue
            if directory and ref.ReferenceTypeId == _ORGANIZES:
                continue
            queue.append((ref.NodeId, node if ref.ReferenceTypeId in _HIERARCHICAL else None))
    return found


def nodeset_xml(
    aspace: AddressSpace,
    server_namespaces: list[str],
    tops: Iterable[ua.NodeId],
    top_parents: dict[ua.NodeId, ua.NodeId],
    models: list[ModelInfo],
) -> bytes:
    """The NodeSet2 document of the cell's nodes (``tops`` and everything below them)."""
    namespace = server_namespaces.index(CELL_NAMESPACE)
    nodes = cell_nodes(aspace, tops, namespace)
    for top, parent in top_parents.items():
        nodes[top] = parent
    file_namespaces = [CELL_NAMESPACE, *(m.uri for m in models if m.uri != BASE_NAMESPACE)]
    w = _Writer(aspace, server_namespaces, file_namespaces)
    root = ET.Element(_X + "UANodeSet")  # no LastModified: the same cell gives the same bytes
    uris = ET.SubElement(root, _X + "NamespaceUris")
    for uri in file_namespaces:
        ET.SubElement(uris, _X + "Uri").text = uri
    models_el = ET.SubElement(root, _X + "Models")
    own = ET.SubElement(models_el, _X + "Model", {"ModelUri": CELL_NAMESPACE, "Version": __version__})
    for m in models:
        attrs = {"ModelUri": m.uri, "Version": m.version}
        if m.publication_date:
            attrs["PublicationDate"] = m.publication_date
        ET.SubElement(own, _X + "RequiredModel", attrs)
    aliases = ET.SubElement(root, _X + "Aliases")
    for node, parent in nodes.items():
        _node(w, root, node, parent, set(nodes))
    for name, target in sorted(w.aliases.items(), key=lambda a: (_alias_order(a[1]), a[0])):
        ET.SubElement(aliases, _X + "Alias", {"Alias": name}).text = target
    ET.register_namespace("", _UANODESET)
    ET.register_namespace("uax", _TYPES)
    ET.indent(root)
    document: bytes = ET.tostring(root, encoding="utf-8", xml_declaration=True)
    return document + b"\n"


def _alias_order(nodeid: str) -> int:
    return int(nodeid[2:]) if nodeid.startswith("i=") and nodeid[2:].isdigit() else 0


_ELEMENTS = {
    ua.NodeClass.Object: "UAObject",
    ua.NodeClass.Variable: "UAVariable",
    ua.NodeClass.Method: "UAMethod",
    ua.NodeClass.ObjectType: "UAObjectType",
    ua.NodeClass.VariableType: "UAVariableType",
}


def _node(w: _Writer, root: ET.Element, node: ua.NodeId, parent: ua.NodeId | None, exported: set[ua.NodeId]) -> None:
    node_class = ua.NodeClass(w.attribute(node, _A.NodeClass))
    tag = _ELEMENTS.get(node_class)
    if tag is None:
        raise ValueError(f"{node.to_string()}: cannot export a {node_class.name} node")
    el = ET.SubElement(
        root, _X + tag, {"NodeId": w.nodeid(node), "BrowseName": w.qualified(w.attribute(node, _A.BrowseName))}
    )
    if parent is not None:
        el.set("ParentNodeId", w.nodeid(parent))
    if node_class == ua.NodeClass.Object:
        notifier = w.attribute(node, _A.EventNotifier)
        if notifier:
            el.set("EventNotifier", str(int(notifier)))
    if node_class == ua.NodeClass.Variable:
        el.set("DataType", w.aliased(w.attribute(node, _A.DataType)))
        rank = w.attribute(node, _A.ValueRank)
        if rank is not None and rank != -1:
            el.set("ValueRank", str(int(rank)))
        dims = w.attribute(node, _A.ArrayDimensions)
        if dims:
            el.set("ArrayDimensions", ",".join(str(d) for d in dims))
        access = w.attribute(node, _A.AccessLevel)
        if access is not None and int(access) != 1:
            el.set("AccessLevel", str(int(access)))
        interval = w.attribute(node, _A.MinimumSamplingInterval)
        if interval:
            el.set("MinimumSamplingInterval", repr(float(interval)))
        if w.attribute(node, _A.Historizing):
            el.set("Historizing", "true")
    for name in ("DisplayName", "Description"):
        text = w.attribute(node, getattr(_A, name))
        if text is not None and text.Text:
            child = ET.SubElement(el, _X + name)
            child.text = text.Text
            if text.Locale:
                child.set("Locale", text.Locale)
    refs = ET.SubElement(el, _X + "References")
    data = w.aspace[node]
    for ref in sorted(
        data.references, key=lambda r: (r.ReferenceTypeId.to_string(), not r.IsForward, r.NodeId.to_string())
    ):
        if ref.NodeId.NamespaceIndex == node.NamespaceIndex and ref.NodeId not in exported:
            continue  # a file directory's entry
        attrs = {"ReferenceType": w.aliased(ref.ReferenceTypeId)}
        if not ref.IsForward:
            attrs["IsForward"] = "false"
        ET.SubElement(refs, _X + "Reference", attrs).text = w.nodeid(ref.NodeId)
    if node_class == ua.NodeClass.Variable:
        data_value = w.aspace.read_attribute_value(node, _A.Value)
        if data_value.Value is not None:
            w.value(el, data_value.Value)


def _simulated(config: Config, data_dir: Path) -> Config:
    """``config`` served from ``data_dir``, every part on its simulator, no snapshot, nothing listening."""
    copy = deepcopy(config)
    copy.server.data_dir = data_dir
    copy.server.address_space_cache = False
    copy.server.cache_dir = None
    copy.logging.audit = False
    copy.logging.file = None
    copy.metrics.enabled = False
    for settings in copy.sections.values():
        if hasattr(settings, "equipment"):
            settings.equipment = ""
    for section in copy.cell.sections.values():
        for _, part in section.parts():
            stack = [part]
            while stack:
                p = stack.pop()
                if hasattr(p.spec, "equipment"):
                    p.spec.equipment = ""
                stack.extend(p.children)
    return copy


async def export_cell(config: Config, companions: Sequence[Companion[ServerView]] | None = None) -> bytes:
    """The NodeSet2 file of the cell ``config`` serves with ``companions`` (default: this build's),
    assembled without listening."""
    from uacell.catalog import companions as catalog_companions
    from uacell.server import UacellServer

    served = tuple(companions) if companions is not None else catalog_companions()
    models = model_infos(official_models(models_of(served)), config.server.models_dir)
    with tempfile.TemporaryDirectory(prefix="uacell-export-") as tmp:
        app = UacellServer(_simulated(config, Path(tmp)), companions=served)
        try:
            await app.setup()
            aspace = app.server.iserver.aspace
            namespaces = list(await app.server.get_namespace_array())
            tops: dict[ua.NodeId, ua.NodeId] = {}
            for built in app.cell.built:
                parents = [
                    r.NodeId
                    for r in aspace[built.node].references
                    if not r.IsForward and r.ReferenceTypeId in _HIERARCHICAL
                ]
                if parents and parents[0].NamespaceIndex != built.node.NamespaceIndex:
                    tops[built.node] = parents[0]
            return nodeset_xml(aspace, namespaces, tops, tops, models)
        finally:
            await app.stop()


def run_export(args: argparse.Namespace, config: Config) -> int:
    """``uacell nodeset export [-o FILE]``: the file, or the XML on standard output."""
    import asyncio

    from uacell.core.files import atomic_write

    own = logging.getLogger("uacell")
    saved = own.level
    if getattr(args, "log_level", None) is None:
        # Set-up talks about its temporary data directory and simulators: not the export's business.
        own.setLevel(logging.ERROR)
    try:
        data = asyncio.run(export_cell(config))
    finally:
        own.setLevel(saved)
    if args.output is None:
        sys.stdout.buffer.write(data)
        sys.stdout.flush()
    else:
        atomic_write(args.output, data, 0o644)
        print(f"uacell: wrote {args.output}", file=sys.stderr)
    return 0
