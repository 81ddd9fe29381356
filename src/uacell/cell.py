"""The cell uacell serves: which standard instances exist, where, and with which optional members.

A cell is declared as data (``Part`` trees) and built by the deep instantiation of ``uacell.ua``.
The default cell is ``demo_cell()``: one robot and one filler. Where parts go (``DeviceSet``,
``PackMLObjects``) is each companion's declaration (``uacell.companion.Root``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

from asyncua import Server, ua
from asyncua.server.address_space import AddressSpace

from uacell.companion import companions
from uacell.ua import toolkit
from uacell.ua.instantiate import Instantiator, Selection

CELL_NAMESPACE = "urn:uacell:cell"

# Optional members no client needs and uacell does not keep current.
_NOISE = (
    "**/EffectiveDisplayName",
    "**/EffectiveTransitionTime",
    "**/CurrentState/Name",
    "**/LastTransition/Name",
    "**/ValuePrecision",
)
# What every state machine publishes (docs/decisions.md 1).
_STATE_MACHINE = ("**/CurrentState/Number", "**/LastTransition/Number", "**/LastTransition/TransitionTime")


@dataclass
class Part:
    """An instance of ``type_name`` (in model ``model``) called ``name``, placed in ``folder``.

    ``folder`` is a BrowseName path below the parent part ("" = the parent itself); ``include`` lists
    the Optional members to create (see ``Selection``); ``children`` are parts placed below this one
    (typically in place of a placeholder).
    """

    name: str
    model: str
    type_name: str
    folder: str = ""
    include: tuple[str, ...] = ()
    children: list[Part] = field(default_factory=list)
    role: str = ""  # what the server binds to it: "controller", "task_control", "motion_device", "packml_unit"


def demo_cell() -> list[tuple[str, Part]]:
    """The default cell: a robot in DeviceSet and a filler in PackMLObjects."""
    axes = [
        Part(
            f"Axis{i}",
            "Robotics",
            "AxisType",
            "Axes",
            include=("ParameterSet/ActualSpeed", "ParameterSet/ActualAcceleration"),
        )
        for i in range(1, 7)
    ]
    power_trains = [
        Part(
            f"PowerTrain{i}",
            "Robotics",
            "PowerTrainType",
            "PowerTrains",
            children=[Part(f"Motor{i}", "Robotics", "MotorType")],
        )
        for i in range(1, 7)
    ]
    arm = Part(
        "Arm1",
        "Robotics",
        "MotionDeviceType",
        "MotionDevices",
        include=("ParameterSet/InControl", "ParameterSet/OnPath", "FlangeLoad"),
        children=axes + power_trains,
        role="motion_device",
    )
    task_control = Part(
        "TaskControl1",
        "Robotics",
        "TaskControlType",
        "TaskControls",
        include=(
            "Lock",
            "ParameterSet/ExecutionMode",
            "TaskModules",
            "TaskControlOperation",
            "TaskControlOperation/**",
            *_STATE_MACHINE,
        ),
        role="task_control",
    )
    controller = Part(
        "Controller1",
        "Robotics",
        "ControllerType",
        "Controllers",
        include=(
            "Lock",
            "Programs",
            "SystemOperation",
            "SystemOperation/**",
            *_STATE_MACHINE,
        ),
        children=[task_control, Part("Software1", "DI", "SoftwareType", "Software")],
        role="controller",
    )
    robot = Part(
        "Robot1",
        "Robotics",
        "MotionDeviceSystemType",
        include=(),
        children=[controller, arm, Part("SafetyState1", "Robotics", "SafetyStateType", "SafetyStates")],
    )
    filler = Part(
        "Filler1",
        "PackML",
        "PackMLBaseObjectType",
        include=("**",),
        role="packml_unit",
    )
    return [("DeviceSet", robot), ("PackMLObjects", filler)]


@dataclass
class BuiltPart:
    part: Part
    node: ua.NodeId
    type_node: ua.NodeId
    path: str  # NodeId path, e.g. "Robot1.Controllers.Controller1"


class CellBuilder:
    """Builds a cell's parts into a server that has the official models loaded."""

    def __init__(self, server: Server, namespace_index: int, model_indexes: dict[str, int]) -> None:
        self.server = server
        self.instantiator = Instantiator(server, namespace_index)
        self.model_indexes = model_indexes
        self.built: list[BuiltPart] = []
        self._types: dict[tuple[str, str, int], ua.NodeId] = {}

    @property
    def aspace(self) -> AddressSpace:
        aspace: AddressSpace = self.server.iserver.aspace
        return aspace

    def type_node(self, model: str, type_name: str, root: int = ua.ObjectIds.BaseObjectType) -> ua.NodeId:
        """The type called ``type_name`` in model ``model``, below ``root`` (ObjectTypes by default)."""
        key = (model, type_name, root)
        if key not in self._types:
            found = toolkit.type_named(self.aspace, ua.NodeId(root), self.model_indexes[model], type_name)
            if found is None:
                raise KeyError(f"{model} has no type {type_name}")
            self._types[key] = found
        return self._types[key]

    def child(self, node: ua.NodeId, path: str) -> ua.NodeId:
        """Follow a BrowseName path (names without namespace) down from ``node``."""
        return toolkit.child(self.aspace, node, path)

    def build(self, parent: ua.NodeId, part: Part, id_prefix: str = "", reference_type: int = 47) -> BuiltPart:
        where = self.child(parent, part.folder) if part.folder else parent
        type_node = self.type_node(part.model, part.type_name)
        segments = [id_prefix, *part.folder.split("/"), part.name]
        path = ".".join(s for s in segments if s)
        node = self.instantiator.create(
            where,
            type_node,
            ua.QualifiedName(part.name, self.instantiator.ns),
            Selection(part.include, _NOISE),
            reference_type=reference_type,
            path=path,
        )
        built = BuiltPart(part, node, type_node, path)
        self.built.append(built)
        for child in part.children:
            self.build(node, child, path)
        return built

    def by_role(self, role: str) -> list[BuiltPart]:
        return [b for b in self.built if b.part.role == role]


async def build_cell(
    server: Server, model_indexes: dict[str, int], parts: list[tuple[str, Part]] | None = None
) -> CellBuilder:
    """Create the cell's instances; ``parts`` (root name, part) defaults to the demo cell."""
    ns = await server.register_namespace(CELL_NAMESPACE)
    builder = CellBuilder(server, ns, model_indexes)
    roots = {root.name: root for c in companions() for root in c.roots}
    for name, part in parts or demo_cell():
        root = roots[name]
        builder.build(ua.NodeId(root.node, model_indexes[root.model]), part, reference_type=root.reference)
    return builder
