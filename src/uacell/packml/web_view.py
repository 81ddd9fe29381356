"""What the web HMI shows of a PackML unit (``Companion.web_view``): found by type in any server; its
history view; the page draws it with ``static/view.js`` beside this module."""

from __future__ import annotations

from typing import Any

from asyncua import Client, ua

from uacell.binding.web_discovery import Cell, Child, Discoverer
from uacell.binding.web_history import MAXIMUM, TIME_AVERAGE, Window, columns, seconds, text_of, timeline, value_history

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


# The history view of a unit (``WebView.history``, uacell.web.history) -----------------------------

# Trends of a PackML unit: speeds averaged over each column, counts (only ever growing) their maximum.
_TRENDS = {
    "Status/MachSpeed": TIME_AVERAGE,
    "Status/CurMachSpeed": TIME_AVERAGE,
    "Admin/ProdProcessedCount": MAXIMUM,
    "Admin/ProdDefectiveCount": MAXIMUM,
}
_UNIT_MACHINES = ("BaseStateMachine", "MachineState", "ExecuteState")
_OEE = ("Availability", "Performance", "Quality", "OEE", "ProcessedCount", "GoodCount")


async def unit_history(client: Client, cell: Cell, name: str, w: Window) -> dict[str, Any]:
    """A unit's state timeline, its speed and count trends and its OEE figures."""
    s, e = seconds(w.since), seconds(w.end)
    machines = []
    for m in _UNIT_MACHINES:
        node = cell.variables.get(f"{name}/{m}/CurrentState")
        machines.append(await value_history(client, node, w.since, w.end) if node is not None else [])
    trends: dict[str, list[list[float]]] = {}
    series = [(key.split("/")[1], cell.variables.get(f"{name}/{key}"), aggregate) for key, aggregate in _TRENDS.items()]
    nodes = {label: node for label, node, _ in series if node is not None}
    for label, node, aggregate in series:
        if node is not None:
            trends[label] = await columns(client, node, aggregate, w)
    # Each trend ends with the value now (the legend's "now"; the last column is an aggregate).
    now_values = await client.read_values([client.get_node(n) for n in nodes.values()]) if nodes else []
    for label, value in zip(nodes, now_values, strict=True):
        value = text_of(value)
        if isinstance(value, int | float) and not isinstance(value, bool):
            trends[label].append([e, float(value)])
    oee: dict[str, Any] = {}
    base = next((ua.NodeId.from_string(n) for n, k in cell.machines.items() if k == f"{name}/BaseStateMachine"), None)
    if base is not None:
        unit = await client.get_node(base).get_parent()
        if unit is not None:
            try:
                folder = await unit.get_child(f"{base.NamespaceIndex}:OEE")
                for figure in _OEE:
                    node = await folder.get_child(f"{base.NamespaceIndex}:{figure}")
                    oee[figure] = await node.read_value()
                figure_node = (await folder.get_child(f"{base.NamespaceIndex}:OEE")).nodeid
                oee["trend"] = await columns(client, figure_node, TIME_AVERAGE, w)
            except ua.UaError:
                oee = {}
    return {
        "name": name,
        "timeline": [seg.json() for seg in timeline(machines, s, e)],
        "trends": trends,
        "oee": oee,
    }
