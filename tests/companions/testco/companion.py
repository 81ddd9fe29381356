"""TestCo: a companion defined only in the tests, to show that a companion is self-contained.

Everything the shared code needs is declared here and in this package: no NodeSet of its own (its
objects are BaseObjectType, its variable a Double of the cell namespace); a binder that gives every
PackML unit a ``Thermometer`` with ``Temperature`` and organizes the units in ``Objects/Thermometers``;
the DataSet history keeps and PubSub publishes (with a kind of value of its own, ``TEMPERATURE``); a
collector for ``/metrics``; a web view (how the HMI finds and describes a unit's thermometer, its
history, and ``static/view.js`` and ``view.css``, which draw them in the page).
"""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path
from typing import Any

from asyncua import Client, ua

from uacell.core.companion import Closer, Companion, WebView
from uacell.core.datasets import Item, Kind, PartDataSet
from uacell.host import BinderHost, Host

NAME = "TestCo"
FOLDER = "Thermometers"  # in Objects: organizes every unit that has a thermometer
THERMOMETER, TEMPERATURE_NAME = "Thermometer", "Temperature"
START_TEMPERATURE = 21.5
BASE_URI = "http://opcfoundation.org/UA/"
HERE = Path(__file__).parent

TEMPERATURE = Kind("temperature")  # a kind of value of its own: the open registry of uacell.core.datasets

DATASET = PartDataSet(
    role="packml_unit", values=(Item(f"{THERMOMETER}/{TEMPERATURE_NAME}", TEMPERATURE),), notifiers=()
)


def temperature_node(path: str, ns: int) -> ua.NodeId:
    return ua.NodeId(f"{path}.{THERMOMETER}.{TEMPERATURE_NAME}", ns)


async def bind(app: BinderHost) -> Closer | None:
    """The thermometers, below each PackML unit of the cell, and the Thermometers folder."""
    units = [b for b in app.cell.built if b.part.role == "packml_unit"]
    if not units:
        return None
    ns = units[0].node.NamespaceIndex
    space = app.space
    folder = await space.add_folder(
        ua.NodeId(ua.ObjectIds.ObjectsFolder), ua.NodeId(FOLDER, ns), ua.QualifiedName(FOLDER, ns)
    )
    writable = ua.Variant(ua.AccessLevel.CurrentRead.mask | ua.AccessLevel.CurrentWrite.mask, ua.VariantType.Byte)
    for built in units:
        thermometer = await space.add_object(
            built.node, ua.NodeId(f"{built.path}.{THERMOMETER}", ns), ua.QualifiedName(THERMOMETER, ns)
        )
        variable = await space.add_variable(
            thermometer,
            temperature_node(built.path, ns),
            ua.QualifiedName(TEMPERATURE_NAME, ns),
            ua.Variant(START_TEMPERATURE, ua.VariantType.Double),
        )
        for level in (ua.AttributeIds.AccessLevel, ua.AttributeIds.UserAccessLevel):
            await space.write(variable, level, writable)
        await space.add_reference(folder, built.node, ua.ObjectIds.Organizes)
    return None


class ThermometerCount:
    """``testco_thermometers``: how many thermometers the server has; ``testco_temperature{unit}``."""

    def __init__(self, app: Host) -> None:
        self.app = app

    def collect(self) -> Iterator[Any]:
        from prometheus_client.core import GaugeMetricFamily

        from uacell.binding.metric_reads import cell_variables, variable_value

        found = {
            path: node for path, node in cell_variables(self.app) if path.endswith(f".{THERMOMETER}.{TEMPERATURE_NAME}")
        }
        yield GaugeMetricFamily("testco_thermometers", "Thermometers of the cell", value=len(found))
        gauge = GaugeMetricFamily("testco_temperature", "Temperature of each unit", labels=["unit"])
        for path, node in sorted(found.items()):
            value = variable_value(self.app, node)
            if isinstance(value, float):
                gauge.add_metric([path.split(".")[0]], value)
        yield gauge


async def describe_thermometer(d: Any, unit: Any, _ns: int) -> dict[str, Any]:
    """What the page gets of a unit's thermometer (``uacell.binding.web_discovery.Discoverer``)."""
    return {
        "name": unit.name,
        "temperature": await d.variable(
            f"{FOLDER}/{unit.name}/{TEMPERATURE_NAME}", unit.node, THERMOMETER, TEMPERATURE_NAME
        ),
    }


async def thermometer_history(client: Client, cell: Any, name: str, w: Any) -> dict[str, Any]:
    """The history view of a unit's thermometer: its temperatures over the window."""
    from uacell.binding.web_history import value_history

    node = cell.variables.get(f"{FOLDER}/{name}/{TEMPERATURE_NAME}")
    changes = await value_history(client, node, w.since, w.end) if node is not None else []
    return {"name": name, "temperatures": [[t, v] for t, v in changes]}


TESTCO = Companion(
    name=NAME,
    datasets=(DATASET,),
    binder=bind,
    metrics=ThermometerCount,
    web_view=WebView(
        "thermometers",
        BASE_URI,
        FOLDER,
        ua.ObjectIds.BaseObjectType,
        f"{__name__}:describe_thermometer",
        script=HERE / "static" / "view.js",
        style=HERE / "static" / "view.css",
        history=f"{__name__}:thermometer_history",
    ),
)
