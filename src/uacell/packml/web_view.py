"""What the web HMI shows of a PackML unit (``Companion.web_view``): found by type in any server."""

from __future__ import annotations

from typing import Any

from asyncua import ua

from uacell.web.discovery import Child, Discoverer

# What the page shows of a PackML unit's Status and Admin objects (those present are used).
UNIT_STATUS = (
    "UnitModeCurrent",
    "UnitSupportedModes",
    "MachSpeed",
    "CurMachSpeed",
    "StateRequested",
    "StateChangeInProcess",
    "MaterialInterlocked",
    "EquipmentBlocked",
    "EquipmentStarved",
    "StartParameters",
)
UNIT_ADMIN = ("ProdProcessedCount", "ProdDefectiveCount", "ProdConsumedCount", "StopReason", "Alarm", "Warning")
UNIT_METHODS = ("SetUnitMode", "SetMachSpeed")
PACKML_MACHINES = (
    ("BaseStateMachine", ("Abort", "Clear")),
    ("MachineState", ("Reset", "Stop")),
    ("ExecuteState", ("Reset", "Start", "Hold", "Unhold", "Suspend", "Unsuspend", "ToComplete")),
)


async def describe_unit(d: Discoverer, unit: Child, _ns: int) -> dict[str, Any]:
    """A PackML unit: its three state machines with their commands, Status and Admin, SetUnitMode, SetMachSpeed."""
    name = unit.name
    machines: list[dict[str, Any]] = []
    node: ua.NodeId | None = unit.node
    for machine_name, method_names in PACKML_MACHINES:
        node = await d.child(node, machine_name)
        if node is None:
            break
        prefix = f"{name}/{machine_name}"
        machines.append(
            {
                "name": machine_name,
                **await d.machine(prefix, node),
                "methods": await d.methods(prefix, node, method_names),
            }
        )
    status = await d.child(unit.node, "Status")
    admin = await d.child(unit.node, "Admin")
    variables = {n: await d.variable(f"{name}/Status/{n}", status, n) for n in UNIT_STATUS}
    variables |= {n: await d.variable(f"{name}/Admin/{n}", admin, n) for n in UNIT_ADMIN}
    # The speeds the unit accepts, for a refusal in words ("speed must be within 0..600").
    variables["MachSpeedRange"] = await d.variable(f"{name}/Status/MachSpeed/EURange", status, "MachSpeed", "EURange")
    return {
        "name": name,
        "machines": machines,
        "variables": {k: v for k, v in variables.items() if v},
        "methods": await d.methods(name, unit.node, UNIT_METHODS),
    }
