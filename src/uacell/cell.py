"""The cell uacell serves: which standard instances exist, where, and with which optional members.

A cell is declared as data (``Part`` trees) and built by the deep instantiation of ``uacell.ua``.
The cell comes from the configuration (``uacell.cellconfig``); the default is the shipped demo cell,
``demo_cell()``. Where parts go (``DeviceSet``, ``PackMLObjects``) is each companion's declaration
(``uacell.companion.Root``).
"""

from __future__ import annotations

from dataclasses import dataclass

from asyncua import Server, ua
from asyncua.server.address_space import AddressSpace

from uacell.cellconfig import STATE_MACHINE, Part
from uacell.companion import companions
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
    from uacell.cellconfig import builtin_cell_path
    from uacell.config import load_cell

    return load_cell(builtin_cell_path("demo")).parts()


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
            Selection((*part.include, *part.values), _NOISE),
            reference_type=reference_type,
            path=path,
        )
        built = BuiltPart(part, node, type_node, path)
        self.built.append(built)
        for child in part.children:
            self.build(node, child, path)
        return built

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
    server: Server, model_indexes: dict[str, int], parts: list[tuple[str, Part]] | None = None
) -> CellBuilder:
    """Create the cell's instances; ``parts`` (root name, part) defaults to the demo cell."""
    ns = await server.register_namespace(CELL_NAMESPACE)
    builder = CellBuilder(server, ns, model_indexes)
    roots = {root.name: root for c in companions() for root in c.roots}
    for name, part in parts or demo_cell():
        root = roots[name]
        builder.build(ua.NodeId(root.node, model_indexes[root.model]), part, reference_type=root.reference)
    await builder.write_values()
    return builder
