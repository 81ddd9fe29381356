"""What every PackML unit gets of uacell's own with the cell (``Companion.shape``): its ``OEE``
folder with the figures of ``uacell.packml.oee``, read-only variables in uacell's namespace, made
with the figures of a unit that has not run (the binder writes the unit's own at start).

They depend on nothing but the unit being there, so they are made before the address-space snapshot
is taken and a restart finds them in it (with their HA Configurations) instead of making a hundred
variables again for a hundred units. The binder writes their values; it makes them itself where they
are missing (a server without the snapshot) through the same function.
"""

from __future__ import annotations

from asyncua import ua

from uacell.cell import CellBuilder
from uacell.packml.companion import UNIT_PART
from uacell.packml.oee import Figures
from uacell.ua.space import Space

# The figures of a unit that has not run (the values the variables are made with).
_NOTHING_YET = Figures(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0).values()


async def add_oee(space: Space, unit: ua.NodeId, path: str, ns: int) -> None:
    """``<path>.OEE`` below ``unit`` with a variable per figure (Double or UInt32), each unless it exists."""
    aspace = space.aspace
    folder_id = ua.NodeId(f"{path}.OEE", ns)
    if folder_id not in aspace:
        await space.node(unit).add_object(folder_id, ua.QualifiedName("OEE", ns))
    folder = space.node(folder_id)
    for key, value in _NOTHING_YET.items():
        name = key.split("/")[1]
        variable_id = ua.NodeId(f"{path}.OEE.{name}", ns)
        if variable_id in aspace:
            continue
        vtype = ua.VariantType.Double if isinstance(value, float) else ua.VariantType.UInt32
        await folder.add_variable(variable_id, ua.QualifiedName(name, ns), ua.Variant(value, vtype))


async def shape_units(space: Space, cell: CellBuilder) -> None:
    """The OEE folder of every unit of the cell."""
    ns = cell.instantiator.ns
    for built in cell.by_role(UNIT_PART):
        await add_oee(space, built.node, built.path, ns)
