"""What history keeps, PubSub and Sparkplug publish of a PackML unit, and the commands it takes
(``Companion.datasets``, uacell.datasets)."""

from __future__ import annotations

from uacell.datasets import Item, Kind, PartDataSet

_SM = "BaseStateMachine"
_MACHINE = f"{_SM}/MachineState"
_EXECUTE = f"{_MACHINE}/ExecuteState"
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
    device=True,
    # Reset: MachineState's from Stopped, ExecuteState's from Complete (whichever is executable)
    commands=(
        ("Reset", ((_MACHINE, "Reset"), (_EXECUTE, "Reset"))),
        ("Start", ((_EXECUTE, "Start"),)),
        ("Stop", ((_MACHINE, "Stop"),)),
        ("Hold", ((_EXECUTE, "Hold"),)),
        ("Unhold", ((_EXECUTE, "Unhold"),)),
        ("Suspend", ((_EXECUTE, "Suspend"),)),
        ("Unsuspend", ((_EXECUTE, "Unsuspend"),)),
        ("Complete", ((_EXECUTE, "ToComplete"),)),
        ("Abort", ((_SM, "Abort"),)),
        ("Clear", ((_SM, "Clear"),)),
        ("SetMachSpeed", (("", "SetMachSpeed"),)),
        ("SetUnitMode", (("", "SetUnitMode"),)),
    ),
)
