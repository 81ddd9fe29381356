"""The cell uacell serves: which standard instances exist, where, and with which optional members.

A cell is declared as data (``Part`` trees) and built by the deep instantiation of ``uacell.ua``.
The cell comes from the configuration (``uacell.core.cell_file``); the default is the shipped demo cell,
``demo_cell()``. Where parts go (``DeviceSet``, ``PackMLObjects``) is each companion's declaration
(``uacell.core.companion.Root``).
"""

from __future__ import annotations

import hashlib
from collections.abc import Sequence
from copy import deepcopy
from dataclasses import dataclass, replace
from typing import Any

from asyncua import Server, ua
from asyncua.server.address_space import AddressSpace

from uacell.core.cell_file import STATE_MACHINE, Part
from uacell.core.companion import Root
from uacell.ua import toolkit
from uacell.ua.instantiate import Instantiator, Selection

__all__ = ["CELL_NAMESPACE", "STATE_MACHINE", "BuiltPart", "CellBuilder", "Part", "build_cell", "demo_cell"]

CELL_NAMESPACE = "urn:uacell:cell"

# Optional members no client needs and uacell does not keep current.
_NOISE = (
    "**/EffectiveDisplayName",
    "**/EffectiveTransitionTime",
    "**/CurrentState/Name",
    "**/LastTransition/Name",
    "**/ValuePrecision",
)


def demo_cell() -> list[tuple[str, Part]]:
    """The default cell (the shipped ``cells/demo.toml``): a robot in DeviceSet and a filler in PackMLObjects."""
    from uacell.config import load_cell
    from uacell.core.cell_file import builtin_cell_path

    return load_cell(builtin_cell_path("demo")).parts()


@dataclass
class BuiltPart:
    part: Part
    node: ua.NodeId
    type_node: ua.NodeId
    path: str  # NodeId path, e.g. "Robot1.Controllers.Controller1"


class CellBuilder:
    """Builds a cell's parts into a server that has the official models loaded."""

    def __init__(
        self,
        server: Server,
        namespace_index: int,
        model_indexes: dict[str, int],
        type_index: dict[tuple[int, int, str], ua.NodeId] | None = None,
    ) -> None:
        self.server = server
        self.type_index = type_index  # every model type by (NodeClass, namespace, name), if known
        self.instantiator = Instantiator(server, namespace_index)
        self.model_indexes = model_indexes
        self.built: list[BuiltPart] = []
        self._types: dict[tuple[str, str, int], ua.NodeId] = {}
        self._type_names: dict[int, dict[tuple[int, str], ua.NodeId]] = {}

    @property
    def aspace(self) -> AddressSpace:
        aspace: AddressSpace = self.server.iserver.aspace
        return aspace

    def type_node(self, model: str, type_name: str, root: int = ua.ObjectIds.BaseObjectType) -> ua.NodeId:
        """The type called ``type_name`` in model ``model``, below ``root`` (ObjectTypes by default)."""
        key = (model, type_name, root)
        if key not in self._types:
            found = self._indexed(self.model_indexes[model], type_name, root)
            if found is None:
                names = self._type_names.get(root)
                if names is None:  # one walk of the hierarchy for every type below this root
                    names = self._type_names[root] = toolkit.type_names(self.aspace, ua.NodeId(root))
                found = names.get((self.model_indexes[model], type_name))
            if found is None:
                raise KeyError(f"{model} has no type {type_name}")
            self._types[key] = found
        return self._types[key]

    def _indexed(self, namespace: int, type_name: str, root: int) -> ua.NodeId | None:
        """The type from the models' type index (``nodesets.type_index``), if it has it and it is
        below ``root``."""
        if self.type_index is None:
            return None
        root_id = ua.NodeId(root)
        node_class = self.aspace[root_id].attributes[ua.AttributeIds.NodeClass].value.Value.Value
        found = self.type_index.get((int(node_class), namespace, type_name))
        if found is None or not self.instantiator.types.is_subtype(found, root_id):
            return None
        return found

    def child(self, node: ua.NodeId, path: str) -> ua.NodeId:
        """Follow a BrowseName path (names without namespace) down from ``node``."""
        return toolkit.child(self.aspace, node, path)

    def build(
        self, parent: ua.NodeId, part: Part, id_prefix: str = "", reference_type: int = 47, create: bool = True
    ) -> BuiltPart:
        """Create ``part`` and its children below ``parent``; ``create`` False: they exist already
        (from an address-space snapshot), only record them."""
        where = self.child(parent, part.folder) if part.folder else parent
        type_node = self.type_node(part.model, part.type_name)
        segments = [id_prefix, *part.folder.split("/"), part.name]
        path = ".".join(s for s in segments if s)
        if create:
            node = self.instantiator.create(
                where,
                type_node,
                ua.QualifiedName(part.name, self.instantiator.ns),
                Selection((*part.include, *part.values), _NOISE),
                reference_type=reference_type,
                path=path,
            )
        else:
            node = self.instantiator.nodeid(path)
            if node not in self.aspace:
                raise KeyError(f"the address-space snapshot has no {path}")
        built = BuiltPart(part, node, type_node, path)
        self.built.append(built)
        for child in part.children:
            self.build(node, child, path, create=create)
        return built

    def extras(self) -> dict[str, Any]:
        """What a snapshot of the built cell keeps beside its nodes (``build_cell(restored=...)``):
        which declaration each instance member came from, the types looked up by name so far
        (finding one walks a type tree, which would load much of a snapshot), and the templates of
        what binders instantiate at every start (``Instantiator.kept_templates``)."""
        return {
            "declarations": dict(self.instantiator.declarations),
            "types": dict(self._types),
            "templates": self.instantiator.kept_templates(),
        }

    async def write_values(self) -> None:
        """Each part's ``values`` (String or LocalizedText members, e.g. DI identification)."""
        for built in self.built:
            for member, text in built.part.values.items():
                node = self.child(built.node, member)
                datatype = self.aspace[node].attributes[ua.AttributeIds.DataType].value.Value.Value
                localized = datatype == ua.NodeId(ua.ObjectIds.LocalizedText)
                variant = ua.Variant(
                    ua.LocalizedText(text) if localized else text,
                    ua.VariantType.LocalizedText if localized else ua.VariantType.String,
                )
                await self.aspace.write_attribute_value(node, ua.AttributeIds.Value, ua.DataValue(variant))

    def by_role(self, role: str) -> list[BuiltPart]:
        return [b for b in self.built if b.part.role == role]


async def build_cell(
    server: Server,
    model_indexes: dict[str, int],
    parts: list[tuple[str, Part]] | None = None,
    restored: dict[str, Any] | None = None,
    type_index: dict[tuple[int, int, str], ua.NodeId] | None = None,
    *,
    roots: Sequence[Root],
) -> CellBuilder:
    """Create the cell's instances; ``parts`` (root name, part) defaults to the demo cell, each placed
    in the companions' ``roots`` (``Companion.roots``) its root name names.

    ``restored``: the instances came with the address-space snapshot (which was written with
    ``CellBuilder.extras()`` of the same cell): only the builder's records are made.
    ``type_index``: the models' types by (NodeClass, namespace index, name), from their snapshot.
    """
    ns = await server.register_namespace(CELL_NAMESPACE)
    builder = CellBuilder(server, ns, model_indexes, type_index)
    if restored is not None:
        builder.instantiator.declarations.update(restored["declarations"])
        builder.instantiator.templates.update(restored.get("templates", {}))
        builder._types.update(restored["types"])
    by_name = {root.name: root for root in roots}
    for name, part in parts or demo_cell():
        root = by_name[name]
        where = ua.NodeId(root.node, model_indexes[root.model])
        builder.build(where, part, reference_type=root.reference, create=restored is None)
    if restored is None:
        await builder.write_values()
    builder.instantiator.keep_templates()  # what binders make, they make at every start
    return builder


def _shape(part: Part) -> tuple[Any, ...]:
    return (
        part.name,
        part.model,
        part.type_name,
        part.folder,
        part.include,
        part.role,
        sorted(part.values.items()),
        [_shape(c) for c in part.children],
    )


def cell_digest(parts: list[tuple[str, Part]] | None, extra: str = "", *, roots: Sequence[Root]) -> str:
    """SHA-256 of everything that shapes the cell's instances: the parts (not their equipment
    settings, which the binders apply), where the companions place them, the cell namespace, and
    ``extra`` (what else adds nodes before the snapshot: history's HA Configurations)."""
    placed = sorted(repr(root) for root in roots)
    shape = [(name, _shape(part)) for name, part in parts or demo_cell()]
    return hashlib.sha256(repr((CELL_NAMESPACE, placed, shape, extra)).encode()).hexdigest()


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
