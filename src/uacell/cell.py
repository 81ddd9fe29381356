"""The cell uacell serves: which standard instances exist, where, and with which optional members.

A cell is declared as data (``Part`` trees) and built by the deep instantiation of ``uacell.ua``.
The demo cell of design.md is ``demo_cell()``.
"""

from __future__ import annotations

from copy import deepcopy
from dataclasses import dataclass, field, replace

from asyncua import Server, ua

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
# What every state machine publishes (decision 1).
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

    @property
    def aspace(self):
        return self.server.iserver.aspace

    def type_node(self, model: str, type_name: str) -> ua.NodeId:
        ns = self.model_indexes[model]
        for ref in self._subtype_closure():
            if ref.NamespaceIndex == ns:
                name = self.instantiator.types.attr(ref, ua.AttributeIds.BrowseName)
                if name is not None and name.Name == type_name:
                    return ref
        raise KeyError(f"{model} has no type {type_name}")

    def _subtype_closure(self) -> set[ua.NodeId]:
        cached = getattr(self, "_types", None)
        if cached is None:
            cached = self._types = self.instantiator.types._subtypes(ua.NodeId(ua.ObjectIds.BaseObjectType))
        return cached

    def child(self, node: ua.NodeId, path: str) -> ua.NodeId:
        """Follow a BrowseName path (names without namespace) down from ``node``."""
        for name in [p for p in path.split("/") if p]:
            for ref in self.aspace[node].references:
                if ref.IsForward and ref.BrowseName.Name == name and ref.ReferenceTypeId != ua.NodeId(40):
                    node = ref.NodeId
                    break
            else:
                raise KeyError(f"{node} has no child {name!r}")
        return node

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


async def build_cell(server: Server, model_indexes: dict[str, int], parts=None) -> CellBuilder:
    """Create the cell's instances; ``parts`` defaults to the demo cell."""
    ns = await server.register_namespace(CELL_NAMESPACE)
    builder = CellBuilder(server, ns, model_indexes)
    roots = {
        "DeviceSet": ua.NodeId(5001, model_indexes["DI"]),
        "PackMLObjects": ua.NodeId(72, model_indexes["PackML"]),
    }
    for root, part in parts or demo_cell():
        # Devices are components of DeviceSet (DI); PackML units are organized by PackMLObjects.
        ref = ua.ObjectIds.HasComponent if root == "DeviceSet" else ua.ObjectIds.Organizes
        builder.build(roots[root], part, reference_type=ref)
    return builder


def sized_cell(units: int, robots: int, task_controls: int = 1) -> list[tuple[str, Part]]:
    """The demo cell scaled up: ``robots`` robots (``Robot<i>`` with ``Controller<i>`` and
    ``task_controls`` task controls each) and ``units`` PackML units ``Filler<i>``; the first robot
    and unit are the demo cell's, with the same NodeIds (benchmarks, tests of cell-size independence)."""
    (robot_root, robot), (unit_root, filler) = demo_cell()
    parts: list[tuple[str, Part]] = []
    for i in range(1, robots + 1):
        copy = deepcopy(robot)
        copy.name = f"Robot{i}"
        controller = next(p for p in copy.children if p.role == "controller")
        controller.name = f"Controller{i}"
        task = next(p for p in controller.children if p.role == "task_control")
        others = [p for p in controller.children if p.role != "task_control"]
        tasks = []
        for t in range(1, task_controls + 1):
            tc = deepcopy(task)
            tc.name = f"TaskControl{t}"
            tasks.append(tc)
        controller.children = tasks + others
        parts.append((robot_root, copy))
    for i in range(1, units + 1):
        parts.append((unit_root, replace(filler, name=f"Filler{i}")))
    return parts
