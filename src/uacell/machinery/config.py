"""The ``[machinery]`` section and the cell's ``[[machines]]`` entries: what OPC 40001-1 identification
says of each machine beyond what the part's own table says (pure; docs/configuration.md documents
every key).

A machine is a robot or a PackML unit of the same cell; its ``[[machines]]`` entry names it. The
machine's identification starts from the part's DI identification (``identification = {...}`` of a
``[[robots]]`` entry: Manufacturer, Model, SerialNumber, ... have the same BrowseNames in OPC 40001-1),
and its entry adds or overrides. An entry adds no part, so it names none at the top of the cell.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import date
from typing import Any

from uacell.core.cell_file import IDENTIFICATION, Table, unique

# [[machines]] keys that are text -> the BrowseName of MachineIdentificationType's property: the text
# properties of DI's identification that its nameplate interfaces also have (not DeviceRevision and
# DeviceManual), and Location.
TEXT_KEYS = {
    **{key: name for key, name in IDENTIFICATION.items() if key not in ("device_revision", "device_manual")},
    "location": "Location",
}
# [[machines]] keys that are integers -> (BrowseName, least, greatest).
NUMBER_KEYS = {
    "year_of_construction": ("YearOfConstruction", 1, 65535),  # UInt16
    "month_of_construction": ("MonthOfConstruction", 1, 12),  # Byte
}
INITIAL_OPERATION_DATE = "InitialOperationDate"


@dataclass
class MachineryConfig:
    """The ``[machinery]`` section: what every machine shares unless its ``[[machines]]`` entry says."""

    location: str = ""  # Location of every machine (OPC 40001-1: where it stands), e.g. "Plant 1/Hall 3"


@dataclass
class MachineSpec:
    """One ``[[machines]]`` entry: the part it describes and its identification values by BrowseName
    (text, integers, and InitialOperationDate as a date)."""

    name: str
    values: dict[str, str | int | date] = field(default_factory=dict)


@dataclass
class MachinesSection:
    """Every ``[[machines]]`` entry (a ``uacell.core.cell_file.CellSection`` that adds no parts)."""

    machines: list[MachineSpec]
    tables: list[Table]

    def parts(self) -> list[tuple[str, Any]]:
        return []

    def top_names(self) -> list[tuple[str, Table]]:
        return []

    def describe(self, settings: Mapping[str, Any]) -> list[str]:
        lines = []
        for m in self.machines:
            lines.append(f"Machines/{m.name}  (OPC 40001-1 identification)")
            lines += [f"    {k} = {v!s}" for k, v in m.values.items()]
        return lines

    def of(self, name: str) -> MachineSpec | None:
        return next((m for m in self.machines if m.name == name), None)

    def table_of(self, name: str) -> Table | None:
        return next((t for m, t in zip(self.machines, self.tables, strict=True) if m.name == name), None)


def _machine(table: Table) -> MachineSpec:
    name = table.name()
    values: dict[str, str | int | date] = {}
    # every key is asked for, given or not (the configuration reference records what is read)
    for key, member in TEXT_KEYS.items():
        text = table.string(key)
        if table.has(key):
            values[member] = text
    for key, (member, least, greatest) in NUMBER_KEYS.items():
        number = table.integer(key, 0)
        if table.has(key):
            if not least <= number <= greatest:
                raise table.error(key, f"must be within {least}..{greatest}")
            values[member] = number
    text = table.string("initial_operation_date")
    if table.has("initial_operation_date"):
        try:
            values[INITIAL_OPERATION_DATE] = date.fromisoformat(text)
        except ValueError:
            raise table.error("initial_operation_date", f'{text!r} is not a date like "2021-05-31"') from None
    table.finish()
    return MachineSpec(name, values)


def parse_machines(root: Table, key: str) -> MachinesSection:
    tables = root.entries(key)
    machines = [_machine(t) for t in tables]
    unique([(m.name, t) for m, t in zip(machines, tables, strict=True)], "machine")
    return MachinesSection(machines, tables)
