"""What history keeps, PubSub and Sparkplug publish of a PackML unit, and the commands it takes
(``Companion.datasets``, uacell.core.datasets)."""

from __future__ import annotations

from uacell.core.datasets import ALARM, COUNTER, SPEED, STATE, Item, Kind, PartDataSet

OEE = Kind("oee")  # OEE figures (uacell's namespace, docs/packml.md): a PackML unit's own kind

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
        *(Item(f"{m}/CurrentState", STATE) for m in _PACKML_MACHINES),
        Item("Status/UnitModeCurrent", STATE),
        Item("Status/EquipmentBlocked", STATE),
        Item("Status/EquipmentStarved", STATE),
        Item("Status/MachSpeed", SPEED),
        Item("Status/CurMachSpeed", SPEED),
        Item("Admin/ProdProcessedCount", COUNTER),
        Item("Admin/ProdDefectiveCount", COUNTER),
        Item("Admin/ProdConsumedCount", COUNTER),
        Item("Admin/StopReason", ALARM),
        Item("Admin/Alarm", ALARM),
        Item("OEE/Availability", OEE),
        Item("OEE/Performance", OEE),
        Item("OEE/Quality", OEE),
        Item("OEE/OEE", OEE),
        Item("OEE/ProcessedCount", OEE),
        Item("OEE/GoodCount", OEE),
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
