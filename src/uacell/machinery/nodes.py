"""A machine's OPC 40001-1 nodes below its part, in the cell's namespace, as OPC 40001-1 section 7
lays them out and OPC 40010-1 Annex C shows for a MotionDeviceSystem:

    Objects/Machines (ns=Machinery;i=1001) --Organizes--> <part>
    <part> --HasAddIn--> 2:Identification            MachineIdentificationType (DI's BrowseName)
    <part> --HasComponent--> 3:MachineryBuildingBlocks   FolderType
        --HasAddIn--> 2:Identification                the same node
        --HasAddIn--> 3:MachineryItemState            MachineryItemState_StateMachineType
        --HasAddIn--> 3:MachineryOperationMode        MachineryOperationModeStateMachineType

and on a robot the Components building block (OPC 40001-1 section 11) over its controllers and motion
devices, which get a component Identification of their own:

    <robot> --HasAddIn--> 3:Components                MachineComponentsType (also from MachineryBuildingBlocks)
        --HasComponent--> <controller>, <motion device>   the robot's own parts
    <controller> --HasAddIn--> 2:Identification       MachineryComponentIdentificationType

Each is made unless it exists. ``members`` are the Optional properties of Identification that get a value.
The building blocks and the Organizes reference depend on nothing but the part being a machine: the
companion's shape (``shape_machines``) makes them with the cell, so that a restart finds them in the
address-space snapshot; Identification, whose members come from the equipment too, is made by the
binder on every start.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

from asyncua import ua

from uacell.binding.cell import BuiltPart, CellBuilder
from uacell.binding.space import Space
from uacell.machinery.config import INITIAL_OPERATION_DATE, NUMBER_KEYS, TEXT_KEYS
from uacell.machinery.model import ITEM_STATE, ITEM_STATE_TYPE, MACHINERY, OPERATION_MODE, OPERATION_MODE_TYPE
from uacell.packml.companion import UNIT_PART
from uacell.robotics.companion import CONTROLLER
from uacell.ua.instantiate import Selection

MACHINES_FOLDER = 1001  # ns=Machinery;i=1001
BLOCKS = "MachineryBuildingBlocks"
COMPONENTS = "Components"
IDENTIFICATION = "Identification"
HAS_ADD_IN = ua.ObjectIds.HasAddIn
ORGANIZES = ua.ObjectIds.Organizes
# The parts that are machines, (model, type), and a robot's parts that are its components (OPC 40001-1
# Components): controllers and motion devices.
ROBOT, UNIT = ("Robotics", "MotionDeviceSystemType"), ("PackML", "PackMLBaseObjectType")
MACHINE_TYPES = (ROBOT, UNIT)
COMPONENT_TYPES = (("Robotics", "ControllerType"), ("Robotics", "MotionDeviceType"))
# The properties of MachineIdentificationType a machine may have a value for.
MACHINE_MEMBERS = frozenset({*TEXT_KEYS.values(), *(m for m, _, _ in NUMBER_KEYS.values()), INITIAL_OPERATION_DATE})
# What a state machine gets of its optional members: the last transition, its number and time, the
# states and transitions it has; not what uacell does not keep current (names, effective display name).
STATE_MACHINE = Selection(
    ("CurrentState/Number", "LastTransition", "LastTransition/Number", "LastTransition/TransitionTime",
     "AvailableStates", "AvailableTransitions"),
)  # fmt: skip


def _create(
    cell: CellBuilder, parent: ua.NodeId, type_name: str, name: ua.QualifiedName, selection: Selection, ref: int
) -> ua.NodeId:
    """An instance of the Machinery type ``type_name`` called ``name`` below ``parent`` (NodeId: the
    parent's path and the name), unless it exists."""
    make = cell.instantiator
    nodeid = make.nodeid(f"{parent.Identifier}.{name.Name}")
    if nodeid in cell.aspace:
        return nodeid
    type_node = cell.type_node(MACHINERY, type_name)
    return make.create(parent, type_node, name, selection, reference_type=ref, path=str(nodeid.Identifier))


async def add_components(
    space: Space,
    cell: CellBuilder,
    machine: MachineNodes,
    parts: Iterable[tuple[BuiltPart, Iterable[str]]],
    ns_m: int,
    ns_di: int,
) -> ua.NodeId:
    """The Components add-in of ``machine`` over ``parts`` (each with the members its component
    Identification gets), each part given that Identification, unless they exist; the Components node."""
    components = _create(
        cell, machine.machine, "MachineComponentsType", ua.QualifiedName(COMPONENTS, ns_m), Selection(), HAS_ADD_IN
    )
    await _reference(space, machine.blocks, components, HAS_ADD_IN)
    for part, members in parts:
        wanted = Selection(tuple(sorted(set(members) & MACHINE_MEMBERS - {"Location"})))
        name = ua.QualifiedName(IDENTIFICATION, ns_di)
        _create(cell, part.node, "MachineryComponentIdentificationType", name, wanted, HAS_ADD_IN)
        await _reference(space, components, part.node, ua.ObjectIds.HasComponent)
    return components


@dataclass(frozen=True)
class MachineNodes:
    machine: ua.NodeId
    identification: ua.NodeId
    blocks: ua.NodeId
    item_state: ua.NodeId
    operation_mode: ua.NodeId


async def _reference(space: Space, source: ua.NodeId, target: ua.NodeId, reference: int) -> None:
    """``source --reference--> target`` (and its inverse) unless it is there."""
    refs = space.references(source)
    if any(r.IsForward and r.NodeId == target and r.ReferenceTypeId == ua.NodeId(reference) for r in refs):
        return
    await space.add_reference(source, target, reference)


def machine_parts(cell: CellBuilder) -> list[BuiltPart]:
    """The parts of the cell that are machines: every PackML unit its companion binds, and every robot
    with a controller (a robot without one has no model to follow)."""
    controllers = [b.path for b in cell.by_role(CONTROLLER)]
    found = []
    for built in cell.built:
        kind = (built.part.model, built.part.type_name)
        if kind == UNIT and built.part.role == UNIT_PART:
            found.append(built)
        elif kind == ROBOT and any(c.startswith(f"{built.path}.") for c in controllers):
            found.append(built)
    return found


async def add_blocks(
    space: Space, cell: CellBuilder, built: BuiltPart, ns_m: int
) -> tuple[ua.NodeId, ua.NodeId, ua.NodeId]:
    """MachineryBuildingBlocks with the two state machines below ``built``, and the Organizes reference
    from ``Objects/Machines``, each unless it exists: (blocks, item state, operation mode)."""
    blocks = cell.instantiator.nodeid(f"{built.path}.{BLOCKS}")
    if blocks not in space:
        await space.add_folder(built.node, blocks, ua.QualifiedName(BLOCKS, ns_m))
    item = _create(cell, blocks, ITEM_STATE_TYPE, ua.QualifiedName(ITEM_STATE, ns_m), STATE_MACHINE, HAS_ADD_IN)
    mode = _create(cell, blocks, OPERATION_MODE_TYPE, ua.QualifiedName(OPERATION_MODE, ns_m), STATE_MACHINE, HAS_ADD_IN)
    await _reference(space, ua.NodeId(MACHINES_FOLDER, ns_m), built.node, ORGANIZES)
    return blocks, item, mode


async def shape_machines(space: Space, cell: CellBuilder) -> None:
    """The building blocks of every machine of the cell (``Companion.shape``)."""
    ns_m = cell.model_indexes[MACHINERY]
    for built in machine_parts(cell):
        await add_blocks(space, cell, built, ns_m)


async def add_machine(
    space: Space, cell: CellBuilder, built: BuiltPart, indexes: dict[str, int], members: Iterable[str]
) -> MachineNodes:
    """The machine's nodes below ``built`` (see the module docstring), each unless it exists."""
    ns_m, ns_di = indexes[MACHINERY], indexes["DI"]
    blocks, item, mode = await add_blocks(space, cell, built, ns_m)
    wanted = Selection(tuple(sorted(set(members) & MACHINE_MEMBERS)))
    name = ua.QualifiedName(IDENTIFICATION, ns_di)
    ident = _create(cell, built.node, "MachineIdentificationType", name, wanted, HAS_ADD_IN)
    await _reference(space, blocks, ident, HAS_ADD_IN)
    return MachineNodes(built.node, ident, blocks, item, mode)
