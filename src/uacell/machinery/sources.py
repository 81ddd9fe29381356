"""Where a machine's facts come from: the models of the companion that made the part (a PackML unit's,
a robot's controllers'), read and watched, never changed. Each source turns its model into
``uacell.machinery.model.Facts`` and calls back on every change the model announces."""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from typing import Protocol

from uacell.core.capabilities import Identified, Reachable, has
from uacell.machinery.model import Facts, packml_facts, robot_facts
from uacell.packml.model import PackMLUnit
from uacell.robotics.equipment import ModeReporting
from uacell.robotics.model import RobotCell


class Source(Protocol):
    def facts(self) -> Facts:
        """What the companion's model says now."""
        ...

    def watch(self, changed: Callable[[], None]) -> None:
        """Call ``changed`` after every change the model announces (several per change are fine)."""
        ...

    def identification(self) -> dict[str, str]:
        """What the equipment reports of itself (BrowseName -> text), where its interface has
        ``identification``: a controller or PLC that knows its serial number."""
        ...


class UnitSource:
    """A PackML unit: its TR88 state, UnitModeCurrent and whether its PLC is reachable."""

    def __init__(self, unit: PackMLUnit) -> None:
        self.unit = unit

    def facts(self) -> Facts:
        u = self.unit
        return packml_facts(u.state, u.unit_mode, u.reachable)

    def watch(self, changed: Callable[[], None]) -> None:
        u = self.unit
        u.listeners.append(lambda _values: changed())  # Status values (the unit mode), Executable
        for machine in u.machines.values():
            machine.listeners.append(lambda _change: changed())
        u.conditions.condition_listeners.append(lambda _condition: changed())  # CommunicationLost

    def identification(self) -> dict[str, str]:
        return _identification(self.unit.equipment)


def _identification(equipment: object) -> dict[str, str]:
    """What equipment reports of itself (``uacell.core.capabilities.Identified``), as text."""
    found = equipment.identification if has(equipment, Identified) else None
    if not isinstance(found, Mapping):
        return {}
    return {str(k): str(v) for k, v in found.items() if v is not None and str(v)}


class RobotSource:
    """A robot: the SystemOperation of each of its controllers, their alarms and their equipment."""

    def __init__(self, cells: Sequence[RobotCell]) -> None:
        self.cells = list(cells)

    def facts(self) -> Facts:
        modes = [c.equipment.operational_mode for c in self.cells if has(c.equipment, ModeReporting)]
        return robot_facts(
            [c.system.state for c in self.cells],
            int(modes[0]) if modes else None,
            alarm=any(cond.active and cond.enabled for c in self.cells for cond in c.system.conditions.values()),
            reachable=all(c.equipment.reachable for c in self.cells if has(c.equipment, Reachable)),
        )

    def watch(self, changed: Callable[[], None]) -> None:
        for cell in self.cells:
            cell.add_listener(changed)

    def identification(self) -> dict[str, str]:
        return _identification(self.cells[0].equipment) if self.cells else {}
