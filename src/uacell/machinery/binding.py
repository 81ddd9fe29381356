"""The Machinery binder: every robot and PackML unit of the cell as an OPC 40001-1 machine.

For each machine (a part of a type in ``MACHINE_TYPES``) it makes, in the cell's namespace below the
part (``uacell.machinery.nodes``): ``Identification`` (MachineIdentificationType, HasAddIn) with the
values of the part's DI identification, what its equipment reports, ``[machinery]`` and its
``[[machines]]`` entry; ``MachineryBuildingBlocks`` with ``MachineryItemState`` and
``MachineryOperationMode``; on a robot, ``Components`` over its controllers and motion devices; and
the Organizes reference from ``Objects/Machines``. The two state machines are a pure
``uacell.machinery.model.Machine`` bound with the one state-machine binding; they follow the facts the
part's own companion model gives (``uacell.machinery.sources``), re-read in a publisher job after each
change that model announces (so a change seen half-way, a parent machine moved before its sub-machine,
is never published).
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from dataclasses import dataclass
from datetime import UTC, date, datetime
from typing import Any

from asyncua import ua

from uacell.binding.cell import BuiltPart
from uacell.binding.publisher import Publisher
from uacell.core.companion import Closer
from uacell.core.errors import ConfigError
from uacell.core.registry import RegistryKey
from uacell.host import BinderHost
from uacell.machinery.config import INITIAL_OPERATION_DATE, NUMBER_KEYS, MachineryConfig, MachinesSection
from uacell.machinery.model import Machine, MachineryTables
from uacell.machinery.nodes import (
    COMPONENT_TYPES,
    MACHINE_MEMBERS,
    MACHINE_TYPES,
    UNIT,
    MachineNodes,
    add_components,
    add_machine,
    machine_parts,
)
from uacell.machinery.sources import RobotSource, Source, UnitSource
from uacell.packml.binding import UNITS
from uacell.robotics.binding import CONTROLLERS

log = logging.getLogger(__name__)
# Members that are not text: equipment reports text only, the cell file gives these.
NUMBERED = frozenset({*(m for m, _, _ in NUMBER_KEYS.values()), INITIAL_OPERATION_DATE})


@dataclass
class MachineBinding:
    """One machine: its model, its nodes and where its facts come from."""

    machine: Machine
    nodes: MachineNodes
    source: Source


MACHINES: RegistryKey[MachineBinding] = RegistryKey("machine")


class Follower:
    """Re-reads a machine's facts once per publisher drain after its source announced a change."""

    def __init__(self, publisher: Publisher, machine: Machine, source: Source) -> None:
        self.publisher = publisher
        self.machine = machine
        self.source = source
        self._queued = False

    def changed(self) -> None:
        if not self._queued:
            self._queued = True
            self.publisher.submit(self.follow)

    async def follow(self) -> None:
        self._queued = False
        self.machine.observe(self.source.facts())


def _source(app: BinderHost, built: BuiltPart) -> Source | None:
    kind = (built.part.model, built.part.type_name)
    if kind == UNIT:
        unit = app.registry(UNITS).get(built.path)
        return UnitSource(unit.unit) if unit is not None else None
    controllers = [b.cell for path, b in app.registry(CONTROLLERS).items() if path.startswith(f"{built.path}.")]
    return RobotSource(controllers) if controllers else None


def identification(
    built: BuiltPart,
    settings: MachineryConfig,
    section: MachinesSection | None,
    application_uri: str,
    reported: Mapping[str, str] | None = None,
) -> dict[str, str | int | date]:
    """The machine's identification by BrowseName: the part's DI identification, what its equipment
    reports of itself (``reported``), ``[machinery]``, then its ``[[machines]]`` entry (the later
    wins); ProductInstanceUri, when none of them gives it, from the server's ApplicationUri and the
    machine's name (unique in this server)."""
    values: dict[str, str | int | date] = {k: v for k, v in built.part.values.items() if k in MACHINE_MEMBERS}
    values.update({k: v for k, v in (reported or {}).items() if k in MACHINE_MEMBERS - NUMBERED})
    if settings.location:
        values["Location"] = settings.location
    entry = section.of(built.part.name) if section is not None else None
    if entry is not None:
        values.update(entry.values)
    values.setdefault("ProductInstanceUri", f"{application_uri}:machine:{built.part.name}")
    return values


def _check_entries(section: MachinesSection | None, names: set[str]) -> None:
    for machine in section.machines if section is not None else ():
        if machine.name not in names:
            table = section.table_of(machine.name) if section is not None else None
            message = f"{machine.name!r} is no robot or PackML unit of this cell"
            raise table.error("name", message) if table is not None else ConfigError(message)


def _variant(app: BinderHost, node: ua.NodeId, value: str | int | date) -> ua.Variant:
    datatype = app.space.attribute(node, ua.AttributeIds.DataType)
    vtype = app.dispatcher.types.builtin_of(datatype) or ua.VariantType.String
    converted: Any = value
    if vtype == ua.VariantType.LocalizedText:
        converted = ua.LocalizedText(str(value))
    elif vtype == ua.VariantType.DateTime and isinstance(value, date):
        converted = datetime(value.year, value.month, value.day, tzinfo=UTC)
    return ua.Variant(converted, vtype)


async def _write(app: BinderHost, identification: ua.NodeId, values: Mapping[str, str | int | date]) -> None:
    """Each value into the property of that BrowseName below ``identification``."""
    for member, value in values.items():
        node = app.cell.child(identification, member)
        variant = _variant(app, node, value)
        await app.space.write(node, ua.AttributeIds.Value, variant)


async def bind_machine(
    app: BinderHost, built: BuiltPart, source: Source, tables: MachineryTables, values: dict[str, str | int | date]
) -> MachineBinding:
    machine = Machine(built.part.name, tables, source.facts())
    nodes = await add_machine(app.space, app.cell, built, app.model_indexes, tuple(values))
    await _write(app, nodes.identification, values)
    components = [
        b
        for b in app.cell.built
        if b.path.startswith(f"{built.path}.") and (b.part.model, b.part.type_name) in COMPONENT_TYPES
    ]
    if components:
        ns_m, ns_di = app.model_indexes["Machinery"], app.model_indexes["DI"]
        await add_components(app.space, app.cell, nodes, [(c, c.part.values) for c in components], ns_m, ns_di)
        for component in components:
            own = {k: v for k, v in component.part.values.items() if k in MACHINE_MEMBERS}
            await _write(app, app.cell.child(component.node, "Identification"), own)
    await app.space.bind_machine(nodes.item_state, machine.item_state, app.publisher, app.refs)
    await app.space.bind_machine(nodes.operation_mode, machine.operation_mode, app.publisher, app.refs)
    follower = Follower(app.publisher, machine, source)
    source.watch(follower.changed)
    follower.changed()  # what changed between the source's binding and now
    return app.registry(MACHINES).add(built.path, MachineBinding(machine, nodes, source))


async def bind_machinery(app: BinderHost) -> Closer | None:
    """Every robot and PackML unit the other binders bound, as a machine in ``Objects/Machines``."""
    tables = MachineryTables.load(app.tables)
    settings = app.config.section("machinery", MachineryConfig)
    section = app.config.cell.sections.get("machines")
    section = section if isinstance(section, MachinesSection) else None
    kinds = [b for b in app.cell.built if (b.part.model, b.part.type_name) in MACHINE_TYPES]
    _check_entries(section, {b.part.name for b in kinds})
    machines = {id(b) for b in machine_parts(app.cell)}
    for part in kinds:
        source = _source(app, part) if id(part) in machines else None
        if source is None:  # its companion bound nothing there (a robot without controllers)
            log.info("%s: no model to follow; not a machine", part.path)
            continue
        values = identification(part, settings, section, app.config.server.application_uri, source.identification())
        await bind_machine(app, part, source, tables, values)
    return None


__all__ = ["MACHINES", "MachineBinding", "bind_machinery"]
