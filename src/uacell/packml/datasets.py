"""What history keeps and PubSub publishes of a PackML unit (``Companion.datasets``, uacell.datasets)."""

from __future__ import annotations

from uacell.datasets import Item, Kind, PartDataSet

_PACKML_MACHINES = (
    "BaseStateMachine",
    "BaseStateMachine/MachineState",
    "BaseStateMachine/MachineState/ExecuteState",
)

PACKML_UNIT = PartDataSet(
    role="packml_unit",
    values=(
        *(Item(f"{m}/CurrentState", Kind.STATE) for m in _PACKML_MACHINES),
        Item("Status/UnitModeCurrent", Kind.STATE),
        Item("Status/EquipmentBlocked", Kind.STATE),
        Item("Status/EquipmentStarved", Kind.STATE),
        Item("Status/MachSpeed", Kind.SPEED),
        Item("Status/CurMachSpeed", Kind.SPEED),
        Item("Admin/ProdProcessedCount", Kind.COUNTER),
        Item("Admin/ProdDefectiveCount", Kind.COUNTER),
        Item("Admin/ProdConsumedCount", Kind.COUNTER),
        Item("Admin/StopReason", Kind.ALARM),
        Item("Admin/Alarm", Kind.ALARM),
        Item("OEE/Availability", Kind.OEE),
        Item("OEE/Performance", Kind.OEE),
        Item("OEE/Quality", Kind.OEE),
        Item("OEE/OEE", Kind.OEE),
        Item("OEE/ProcessedCount", Kind.OEE),
        Item("OEE/GoodCount", Kind.OEE),
    ),
    notifiers=_PACKML_MACHINES,
)
