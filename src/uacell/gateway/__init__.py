"""Gateway to real equipment behind a PLC: drivers a cell file names with
``equipment = { driver = "...", ... }`` (docs/equipment.md, "Gateway").

- ``robot`` (``modbus-signals``): a robot controller's remote-operation signals over Modbus/TCP
  (``modbus``, ``modbus_robot``, ``signals``; ``codec`` for register values);
- ``opcua_robot`` (``opcua-signals``): the same signals as a PLC's OPC UA variables (``opcua_link``);
- ``ur_robot`` (``ur-dashboard``): Universal Robots through the Dashboard Server and UR's Modbus
  registers (``ur_link``);
- ``packml_opcua`` (``opcua-packtags``): a PackML unit whose state machine runs in a PLC, over its
  PackTags on OPC UA (``opcua_link``, ``packtags``, ``handshake``);
- ``packml_modbus`` (``modbus-packtags``), ``packml_s7`` (``s7-packtags``, ``s7`` for S7
  addresses and write jobs) and ``packml_logix`` (``logix-packtags``): the same unit over Modbus/TCP
  registers, a Siemens S7 data block or Rockwell Logix tags (``link.PolledLink``).

``examples/robot_controller.py`` is a Modbus robot controller to try the first with,
``examples/robot_plc.py`` an OPC UA PLC holding robot signals for ``opcua-signals``;
``interop/plc_packtags.js`` a PackTags PLC for the second.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any


def driver_settings(driver: str, settings: Mapping[str, Any], known: Sequence[str]) -> dict[str, Any]:
    """``settings`` as a dict; ValueError naming the first key ``driver`` does not know."""
    unknown = sorted(set(settings) - set(known))
    if unknown:
        raise ValueError(f"the {driver} driver has no setting {unknown[0]!r} (it knows {', '.join(known)})")
    return dict(settings)


def whole_number(part: str, settings: Mapping[str, Any], key: str, default: int, low: int, high: int) -> int:
    """The setting ``key`` (``default`` when absent); ValueError naming the part unless a whole number in range."""
    value = settings.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
        raise ValueError(f"{part}: {key}: a whole number from {low} to {high}, not {value!r}")
    return value


def number(part: str, settings: Mapping[str, Any], key: str, default: float, low: float, high: float) -> float:
    """The setting ``key`` (``default`` when absent); ValueError naming the part unless a number in range."""
    value = settings.get(key, default)
    if isinstance(value, bool) or not isinstance(value, int | float) or not low <= value <= high:
        raise ValueError(f"{part}: {key}: a number from {low:g} to {high:g}, not {value!r}")
    return float(value)
