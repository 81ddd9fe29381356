"""What a companion's figures for ``/metrics`` (``Companion.metrics``) read of the address space, at
scrape time, exactly as clients see it; ``uacell.services.metrics`` serves them. Here, below the
companions, so that their collectors (``uacell.packml.metrics``, ...) use it without the endpoint."""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any

from asyncua import ua

from uacell.host import Host

_A = ua.AttributeIds


def variable_value(app: Host, node: ua.NodeId) -> Any:
    """A variable's value as clients read it now (None when it has none)."""
    data = app.server.iserver.aspace.get(node)
    if data is None:
        return None
    dv = data.attributes[_A.Value].value
    return None if dv is None or dv.Value is None else dv.Value.Value


def cell_variables(app: Host) -> Iterator[tuple[str, ua.NodeId]]:
    """Every variable of the cell namespace with a string NodeId: (its path, its NodeId)."""
    ns = app.cell.instantiator.ns
    for node in list(app.server.iserver.aspace.keys()):
        if node.NamespaceIndex == ns and isinstance(node.Identifier, str):
            yield node.Identifier, node
