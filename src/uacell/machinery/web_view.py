"""What the web HMI shows of a machine (``Companion.web_view``): one tile per object ``Objects/Machines``
organizes, with its MachineryItemState, MachineryOperationMode and a few identification values. Found
by BrowseName in any server that serves OPC 40001-1, whatever the machine's own type."""

from __future__ import annotations

from typing import Any

from uacell.binding.web_discovery import Child, Discoverer

# What the tile shows of the machine's Identification (those present are used).
IDENTIFICATION = ("Manufacturer", "Model", "SerialNumber", "ProductInstanceUri", "YearOfConstruction", "Location")


async def describe_machine(d: Discoverer, machine: Child, _ns: int) -> dict[str, Any]:
    name = machine.name
    blocks = await d.child(machine.node, "MachineryBuildingBlocks")
    ident = await d.child(machine.node, "Identification")
    variables = {n: await d.variable(f"Machines/{name}/Identification/{n}", ident, n) for n in IDENTIFICATION}
    return {
        "name": name,
        "state": await d.machine(f"Machines/{name}/MachineryItemState", await d.child(blocks, "MachineryItemState")),
        "mode": await d.machine(
            f"Machines/{name}/MachineryOperationMode", await d.child(blocks, "MachineryOperationMode")
        ),
        "identification": {k: v for k, v in variables.items() if v},
    }
