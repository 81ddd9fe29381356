"""What an equipment factory is called with (a leaf: each companion's Protocol module extends it)."""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class EquipmentSpec:
    """Which part the equipment drives and that part's ``settings`` table. A companion passes a
    subclass with what its parts add (a robot controller: ``uacell.robotics.equipment.ControllerEquipmentSpec``)."""

    part: str  # the part's browse path, e.g. "Robot1.Controllers.Controller1" or "Filler1"
    settings: Mapping[str, Any] = field(default_factory=dict)
