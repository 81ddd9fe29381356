"""The HMI's discovery of the cell: ``discover()`` browses any server for the parts the companions'
web views show, with ``uacell.binding.web_discovery.Discoverer`` (where the companions' web views find
it too); ``list_files()`` lists a program directory."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

from asyncua import Client, ua

from uacell.binding.web_discovery import Cell, Discoverer
from uacell.core.companion import WebView

_FILE_TYPE = ua.NodeId(ua.ObjectIds.FileType)


async def discover(client: Client, views: Sequence[WebView]) -> Cell:
    """Browse ``client``'s server for the parts ``views`` show (see the module docstring)."""
    return await Discoverer(client, views).discover()


async def list_files(client: Client, directory: ua.NodeId, prefix: str = "") -> list[dict[str, Any]]:
    """The files below a FileDirectoryType (recursively), as ``{"name", "path", "node"}``."""
    d = Discoverer(client)
    files: list[dict[str, Any]] = []
    for c in await d.children(directory):
        if c.node_class != ua.NodeClass.Object:
            continue
        path = f"{prefix}{c.name}"
        if await d.is_a(c.type_definition, _FILE_TYPE):
            files.append({"name": c.name, "path": path, "node": c.node})
        elif c.type_definition == ua.NodeId(ua.ObjectIds.FileDirectoryType):
            files += await list_files(client, c.node, f"{path}/")
    return sorted(files, key=lambda f: f["path"])
