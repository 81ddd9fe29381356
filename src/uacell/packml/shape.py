"""What every PackML unit gets of uacell's own with the cell (``Companion.shape``): its ``OEE``
folder with the figures of ``uacell.packml.oee``, read-only variables in uacell's namespace, made
with the figures of a unit that has not run (the binder writes the unit's own at start); its
read-only ``Status/StartParameters``; and its ``InjectFault`` method node (the binder binds it).

They depend on nothing but the unit being there, so they are made before the address-space snapshot
is taken and a restart finds them in it (with their HA Configurations) instead of making a hundred
variables again for a hundred units. The binder writes their values; it makes them itself where they
are missing (a server without the snapshot) through the same functions.
"""

from __future__ import annotations

from asyncua import ua

from uacell.binding.cell import CellBuilder
from uacell.binding.space import Space
from uacell.packml.companion import PACKML_MODEL, UNIT_PART
from uacell.packml.oee import Figures

DESCRIPTOR_TYPE = 16  # PackMLDescriptorDataType's DataType id (OPC 30050 NodeSet)
INJECT_FAULT = "InjectFault"
INJECT_FAULT_INPUTS = (
    ("Id", ua.VariantType.Int32, "alarm ID"),
    ("Message", ua.VariantType.String, "alarm message"),
)

# The figures of a unit that has not run (the values the variables are made with).
_NOTHING_YET = Figures(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0, 0).values()


async def add_oee(space: Space, unit: ua.NodeId, path: str, ns: int) -> None:
    """``<path>.OEE`` below ``unit`` with a variable per figure (Double or UInt32), each unless it exists."""
    folder_id = ua.NodeId(f"{path}.OEE", ns)
    if folder_id not in space:
        await space.add_object(unit, folder_id, ua.QualifiedName("OEE", ns))
    for key, value in _NOTHING_YET.items():
        name = key.split("/")[1]
        variable_id = ua.NodeId(f"{path}.OEE.{name}", ns)
        if variable_id in space:
            continue
        vtype = ua.VariantType.Double if isinstance(value, float) else ua.VariantType.UInt32
        await space.add_variable(folder_id, variable_id, ua.QualifiedName(name, ns), ua.Variant(value, vtype))


async def add_start_parameters(space: Space, status: ua.NodeId, path: str, ns: int, packml_ns: int) -> None:
    """The server-defined read-only ``<path>.Status.StartParameters`` (PackMLDescriptorDataType[])
    below the unit's ``status``, unless it exists."""
    nodeid = ua.NodeId(f"{path}.Status.StartParameters", ns)
    if nodeid in space:
        return
    var = await space.add_variable(
        status,
        nodeid,
        ua.QualifiedName("StartParameters", ns),
        ua.Variant([], ua.VariantType.ExtensionObject, is_array=True),
        datatype=ua.NodeId(DESCRIPTOR_TYPE, packml_ns),
    )
    a = ua.AttributeIds
    await space.write(var, a.ValueRank, ua.Variant(1, ua.VariantType.Int32))
    await space.write(var, a.ArrayDimensions, ua.Variant([0], ua.VariantType.UInt32, is_array=True))
    text = ua.LocalizedText("uacell: the parameters of the last accepted Start")
    await space.write(var, a.Description, ua.Variant(text, ua.VariantType.LocalizedText))


async def add_inject_fault(space: Space, unit: ua.NodeId, path: str, ns: int) -> None:
    """The ``InjectFault(Int32 Id, String Message)`` method node below ``unit``, unless it exists."""
    nodeid = ua.NodeId(f"{path}.{INJECT_FAULT}", ns)
    if nodeid not in space:
        await space.add_method(unit, nodeid, ua.QualifiedName(INJECT_FAULT, ns), INJECT_FAULT_INPUTS)


async def shape_units(space: Space, cell: CellBuilder) -> None:
    """The OEE folder, StartParameters and InjectFault of every unit of the cell."""
    ns = cell.instantiator.ns
    packml_ns = cell.model_indexes[PACKML_MODEL.key]
    for built in cell.by_role(UNIT_PART):
        await add_oee(space, built.node, built.path, ns)
        await add_start_parameters(space, cell.child(built.node, "Status"), built.path, ns, packml_ns)
        await add_inject_fault(space, built.node, built.path, ns)
