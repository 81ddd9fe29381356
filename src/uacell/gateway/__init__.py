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


class DriverSettings:
    """The one reader of a driver's settings (a part's ``equipment = { driver = ..., ... }``): a key the
    driver does not know is refused at once; each value is read with what it must be, and a ValueError
    names the part (or the driver) and the key."""

    def __init__(self, driver: str, part: str, settings: Mapping[str, Any], known: Sequence[str]) -> None:
        unknown = sorted(set(settings) - set(known))
        if unknown:
            raise ValueError(f"the {driver} driver has no setting {unknown[0]!r} (it knows {', '.join(known)})")
        self.driver, self.part, self.raw = driver, part, dict(settings)

    def __contains__(self, key: str) -> bool:
        return key in self.raw

    def get(self, key: str, default: Any = None) -> Any:
        """The value as given (the transport's own checks read it)."""
        return self.raw.get(key, default)

    def text(self, key: str, default: str = "") -> str:
        return str(self.raw.get(key, default))

    def real(self, key: str, default: float) -> float:
        """A number of seconds or a factor, taken as given."""
        return float(self.raw.get(key, default))

    def reals(self, defaults: object, *keys: str) -> dict[str, float]:
        """``keys`` as numbers, each defaulting to the attribute of that name of ``defaults`` (a Timing)."""
        return {key: self.real(key, getattr(defaults, key)) for key in keys}

    def host(self, of: str) -> str:
        """The required ``host``: ValueError naming the part unless a non-empty string."""
        value = self.raw.get("host")
        if not isinstance(value, str) or not value:
            raise ValueError(f'{self.part}: host: needs "<address of {of}>"')
        return value

    def whole(self, key: str, default: int, low: int, high: int) -> int:
        """A whole number in range (``default`` when absent)."""
        value = self.raw.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int) or not low <= value <= high:
            raise ValueError(f"{self.part}: {key}: a whole number from {low} to {high}, not {value!r}")
        return value

    def number(self, key: str, default: float, low: float, high: float) -> float:
        """A number in range (``default`` when absent)."""
        value = self.raw.get(key, default)
        if isinstance(value, bool) or not isinstance(value, int | float) or not low <= value <= high:
            raise ValueError(f"{self.part}: {key}: a number from {low:g} to {high:g}, not {value!r}")
        return float(value)

    def table(self, key: str, shape: str) -> Mapping[str, Any]:
        """A table (``{}`` when absent); ValueError saying its ``shape`` otherwise."""
        value = self.raw.get(key, {})
        if not isinstance(value, Mapping):
            raise ValueError(f"{self.part}: {key}: {shape}, not {value!r}")
        return value

    def polling(self) -> tuple[float, float]:
        """``interval`` and ``timeout`` of a polled PLC connection (seconds)."""
        return self.number("interval", 0.05, 0.005, 60), self.number("timeout", 1.0, 0.05, 60)
