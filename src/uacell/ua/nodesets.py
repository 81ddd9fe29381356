"""Load the official NodeSet files into an asyncua server.

The models are imported in dependency order (DI, IA, Robotics, PackML). Nodes marked
``DesignToolOnly`` (DI 1.05 has some) are for modelling tools only and a server must not expose
them: the loader leaves them, everything below them and every reference to them out.
"""

from __future__ import annotations

import logging
import xml.etree.ElementTree as ET
from pathlib import Path

from asyncua import Server

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


async def load_models(server: Server, models_dir: str | None = None) -> dict[str, int]:
    """Import every official model; returns each model's namespace index in this server."""
    paths = locate_models(models_dir)
    indexes: dict[str, int] = {}
    for model in MODELS:
        xml, dropped = without_design_tool_only(paths[model.key])
        if dropped:
            log.debug("%s: left out %d DesignToolOnly nodes", model.filename, dropped)
        await server.import_xml(xmlstring=xml)
        indexes[model.key] = await server.get_namespace_index(model.namespace_uri)
    return indexes
