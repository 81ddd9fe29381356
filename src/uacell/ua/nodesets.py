"""Load the official NodeSet files into an asyncua server.

The models are imported in dependency order (DI, IA, Robotics, PackML). Nodes marked
``DesignToolOnly`` (DI 1.05 has some) are for modelling tools only and a server must not expose
them: the loader leaves them, everything below them and every reference to them out.
"""

from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Any

from asyncua import Server, ua
from asyncua.common.xmlimporter import XmlImporter

from uacell.models.source import MODELS, locate_models

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
    for model in MODELS:
        xml, dropped = without_design_tool_only(paths[model.key])
        if dropped:
            log.debug("%s: left out %d DesignToolOnly nodes", model.filename, dropped)
        await _Importer(server).import_xml(xmlstring=xml)
        indexes[model.key] = await server.get_namespace_index(model.namespace_uri)
    return indexes
