"""What history keeps and PubSub publishes of a machine (``Companion.datasets``, uacell.core.datasets): its
MachineryItemState and MachineryOperationMode, values and TransitionEvents, on every robot and unit."""

from __future__ import annotations

from uacell.core.datasets import STATE, Item, PartDataSet

BLOCKS = "MachineryBuildingBlocks"
_MACHINES = (f"{BLOCKS}/MachineryItemState", f"{BLOCKS}/MachineryOperationMode")

# The part roles that are machines: a robot (its MotionDeviceSystem) and a PackML unit.
MACHINE_ROLES = ("robot", "packml_unit")

DATASETS = tuple(
    PartDataSet(
        role=role,
        values=tuple(Item(f"{m}/CurrentState", STATE) for m in _MACHINES),
        notifiers=_MACHINES,
    )
    for role in MACHINE_ROLES
)
