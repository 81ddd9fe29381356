"""The ``[robot]`` configuration section."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class RobotConfig:
    time_scale: float = 1.0  # simulated robot: >1 runs faster than real time
    equipment: str = ""  # "package.module:factory" for real equipment (docs/equipment.md)
