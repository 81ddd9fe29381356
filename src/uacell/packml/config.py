"""The ``[packml]`` section and the ``[[packml_units]]`` of a cell: one PackMLBaseObjectType per entry.

Pure: reads and checks the tables (``uacell.core.cell_file.Table``) and turns them into ``Part`` trees
(``uacell.binding.cell``). docs/configuration.md documents every key.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from uacell.core.cell_file import Part, Table
from uacell.core.drivers import PACKML_UNIT, drivers_of
from uacell.packml.types import ProductionMaintenanceModeEnum

# ProductionMaintenanceModeEnum's names, as the NodeSet spells them.
UNIT_MODES = {m.name.capitalize(): int(m) for m in ProductionMaintenanceModeEnum if m.value != 0}
# The TR88 acting states (the simulator spends ``acting_time`` in each unless ``acting_times`` says).
ACTING_STATES = (
    "Clearing",
    "Stopping",
    "Aborting",
    "Resetting",
    "Starting",
    "Completing",
    "Holding",
    "Unholding",
    "Suspending",
    "Unsuspending",
)


# The drivers shipped for PackML units (docs/equipment.md, "Gateway"): equipment = { driver = ... }.
DRIVERS = drivers_of(PACKML_UNIT)  # name -> factory (uacell.core.drivers, the one registry)


@dataclass
class PackMLConfig:
    """The ``[packml]`` section: defaults for every unit that does not set its own."""

    acting_time: float = 1.0  # seconds each acting state of the simulated unit takes
    mach_speed: float = 60.0  # initial MachSpeed, packages/min
    equipment: str = ""  # "package.module:factory" for real equipment (docs/equipment.md)
    oee_window_hours: float = 8.0  # OEE over the last this many hours (docs/packml.md, "OEE")
    oee_shifts: str = ""  # "06:00,14:00,22:00": OEE since the current shift's start (UTC) instead


@dataclass
class UnitSpec:
    name: str
    equipment: str = ""  # "package.module:factory"; "" = [packml] equipment, else the simulator
    settings: dict[str, Any] = field(default_factory=dict)
    acting_time: float | None = None  # simulator; None = [packml] acting_time
    acting_times: dict[str, float] = field(default_factory=dict)  # simulator, per acting state
    mach_speed: float | None = None  # initial MachSpeed; None = [packml] mach_speed
    mach_speed_range: tuple[float, float] = (0.0, 600.0)
    design_speed: float = 120.0
    unit_mode: int = int(ProductionMaintenanceModeEnum.PRODUCE)


def _unit(table: Table) -> UnitSpec:
    name = table.name()
    speed_range = table.raw("mach_speed_range")
    if speed_range is None:
        low, high = 0.0, 600.0
    else:
        if (
            not isinstance(speed_range, list)
            or len(speed_range) != 2
            or not all(isinstance(v, int | float) and not isinstance(v, bool) for v in speed_range)
        ):
            raise table.error("mach_speed_range", "must be [minimum, maximum] in packages/min")
        low, high = float(speed_range[0]), float(speed_range[1])
        if not 0 <= low < high:
            raise table.error("mach_speed_range", "must satisfy 0 <= minimum < maximum")
    mach_speed = table.optional_number("mach_speed")
    if mach_speed is not None and not low <= mach_speed <= high:
        raise table.error("mach_speed", f"{mach_speed:g} is outside mach_speed_range {low:g}..{high:g}")
    design = table.number("design_speed", 120.0, positive=True)
    times = table.table("acting_times")
    acting_times = {s: times.number(s, 0.0) for s in ACTING_STATES if times.has(s)}
    times.finish()
    equipment, settings = table.equipment(DRIVERS)
    spec = UnitSpec(
        name,
        equipment=equipment,
        settings=settings,
        acting_time=table.optional_number("acting_time"),
        acting_times=acting_times,
        mach_speed=mach_speed,
        mach_speed_range=(low, high),
        design_speed=design,
        unit_mode=table.choice("unit_mode", UNIT_MODES, "Produce"),
    )
    table.finish()
    return spec


@dataclass
class UnitsSection:
    """Every ``[[packml_units]]`` entry (a ``uacell.core.cell_file.CellSection``)."""

    units: list[UnitSpec]
    tables: list[Table]

    def parts(self) -> list[tuple[str, Any]]:
        return [("PackMLObjects", unit_part(u)) for u in self.units]

    def top_names(self) -> list[tuple[str, Table]]:
        return [(u.name, t) for u, t in zip(self.units, self.tables, strict=True)]

    def describe(self, settings: Mapping[str, Any]) -> list[str]:
        defaults = settings.get("packml", PackMLConfig())
        modes = {v: k for k, v in UNIT_MODES.items()}
        lines = []
        for u in self.units:
            lines.append(f"PackMLObjects/{u.name}  PackMLBaseObjectType  equipment: {describe_equipment(u, defaults)}")
            speed = f"{defaults.mach_speed:g} (from [packml])" if u.mach_speed is None else f"{u.mach_speed:g}"
            low, high = u.mach_speed_range
            lines.append(
                f"    MachSpeed {speed} in {low:g}..{high:g}, design {u.design_speed:g} packages/min;"
                f" unit mode {modes[u.unit_mode]}"
            )
        return lines


def describe_equipment(u: UnitSpec, defaults: PackMLConfig) -> str:
    """What the unit runs on, with the values in effect (``defaults``: the ``[packml]`` section)."""
    extra = f" settings {u.settings}" if u.settings else ""
    if u.equipment:
        return u.equipment + extra
    if defaults.equipment:
        return f"{defaults.equipment} (from [packml] equipment){extra}"
    acting = f"{defaults.acting_time:g} s from [packml]" if u.acting_time is None else f"{u.acting_time:g} s"
    per_state = "".join(f", {k} {v:g} s" for k, v in u.acting_times.items())
    return f"simulator (acting states {acting}{per_state}){extra}"


def parse_units(root: Table, key: str) -> UnitsSection:
    tables = root.entries(key)
    units = [_unit(t) for t in tables]
    return UnitsSection(units, tables)


def unit_part(u: UnitSpec) -> Part:
    """The unit as a ``Part`` (every optional member of PackMLBaseObjectType)."""
    return Part(u.name, "PackML", "PackMLBaseObjectType", include=("**",), role="packml_unit", spec=u)
