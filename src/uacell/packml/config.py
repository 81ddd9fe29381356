"""The ``[packml]`` configuration section."""

from __future__ import annotations

from dataclasses import dataclass


@dataclass
class PackMLConfig:
    acting_time: float = 1.0  # seconds each acting state of the simulated unit takes
    mach_speed: float = 60.0  # initial MachSpeed, packages/min
    equipment: str = ""  # "package.module:factory" for real equipment (docs/equipment.md)
