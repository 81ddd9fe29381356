"""The equipment drivers and simulators shipped with uacell: the one registry of the names a cell file
gives a part's driver (``equipment = { driver = "ur-dashboard", ... }``, docs/equipment.md, "Gateway")
and of the factories they stand for.

A factory is named by ``"package.module:function"`` because configuration names it too (``[robot]
equipment``, a part's ``equipment``: a driver of one's own); it is imported only when the part's
equipment is made (``uacell.core.equipment_factory``), so that loading a configuration imports no driver
library. Companions, the cell parsers and ``uacell config check --connect`` take the names from here.
"""

from __future__ import annotations

from dataclasses import dataclass

ROBOT_CONTROLLER = "robot controller"
PACKML_UNIT = "PackML unit"


@dataclass(frozen=True)
class Driver:
    name: str  # what a cell file's ``driver`` says
    factory: str  # "package.module:function"
    part: str  # what it drives: ROBOT_CONTROLLER or PACKML_UNIT


DRIVERS = (
    Driver("modbus-signals", "uacell.gateway.robot:modbus_signals", ROBOT_CONTROLLER),
    Driver("ur-dashboard", "uacell.gateway.ur_robot:ur_dashboard", ROBOT_CONTROLLER),
    Driver("opcua-signals", "uacell.gateway.opcua_robot:opcua_signals", ROBOT_CONTROLLER),
    Driver("opcua-packtags", "uacell.gateway.packml_opcua:opcua_packtags", PACKML_UNIT),
    Driver("modbus-packtags", "uacell.gateway.packml_modbus:modbus_packtags", PACKML_UNIT),
    Driver("s7-packtags", "uacell.gateway.packml_s7:s7_packtags", PACKML_UNIT),
    Driver("logix-packtags", "uacell.gateway.packml_logix:logix_packtags", PACKML_UNIT),
)

# The equipment of a part that names none (and whose section names none): the built-in simulators.
SIMULATORS = {
    ROBOT_CONTROLLER: "uacell.robotics.sim:simulator",
    PACKML_UNIT: "uacell.packml.sim:simulator",
}


def drivers_of(part: str) -> dict[str, str]:
    """The drivers of ``part`` (ROBOT_CONTROLLER, PACKML_UNIT): name -> factory."""
    return {d.name: d.factory for d in DRIVERS if d.part == part}


def factory_of(name: str) -> str:
    """The factory of the driver ``name`` (KeyError for an unknown name)."""
    return {d.name: d.factory for d in DRIVERS}[name]
