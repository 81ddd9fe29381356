"""Making each part's equipment: the factory the configuration names, called with the part's settings.

A factory is ``"package.module:name"``, a callable that takes one ``EquipmentSpec`` (a robot
controller's: ``uacell.robotics.equipment.ControllerEquipmentSpec``, with its axes) and returns the
equipment (``RobotEquipment`` for a controller, ``PackMLEquipment`` for a PackML unit), or a coroutine
that does (a driver that connects at start-up). Whatever goes wrong (the import, the call, a result
that lacks a member of the Protocol) stops start-up with one ``ConfigError`` line naming the part.
At shutdown ``close_equipment`` calls the equipment's ``close()`` (plain or coroutine) if it has one.
"""

from __future__ import annotations

import inspect
import logging
from collections.abc import Mapping
from typing import Any

from uacell.config import load_factory
from uacell.core.equipment_spec import EquipmentSpec
from uacell.core.errors import ConfigError

log = logging.getLogger(__name__)

__all__ = ["EquipmentSpec", "choose_equipment", "close_equipment", "make_equipment"]


def choose_equipment(
    factory: str,
    settings: Mapping[str, Any],
    *,
    default: str,
    simulator: str,
    simulator_settings: Mapping[str, Any],
    simulator_defaults: Mapping[str, Any],
) -> tuple[str, dict[str, Any]]:
    """A part's factory and settings: its own factory, else its section's ``default``, else the
    ``simulator``; for the simulator, the part's own simulator keys (``simulator_settings``, those
    not None) win over its settings table, which wins over the section's ``simulator_defaults``."""
    chosen = factory or default or simulator
    merged = dict(settings)
    if chosen == simulator:
        merged.update({k: v for k, v in simulator_settings.items() if v is not None})
        for key, value in simulator_defaults.items():
            merged.setdefault(key, value)
    return chosen, merged


def protocol_members(protocol: type) -> list[str]:
    """The members a ``typing.Protocol`` declares (its own and its bases'), in declaration order."""
    names: list[str] = []
    for cls in reversed(protocol.__mro__):
        if cls is object or not getattr(cls, "_is_protocol", False) or cls.__module__ == "typing":
            continue
        names += [n for n in vars(cls) if not n.startswith("_") and n not in names]
    return names


def missing_members(obj: object, protocol: type) -> list[str]:
    return [n for n in protocol_members(protocol) if not hasattr(obj, n)]


async def make_equipment(factory: str, spec: EquipmentSpec, protocol: type) -> Any:
    """Import and call ``factory`` for ``spec.part``; check the result against ``protocol``."""
    where = spec.part
    make = load_factory(factory, where)
    try:
        result = make(spec)
        if inspect.isawaitable(result):
            result = await result
    except ConfigError:
        raise
    except Exception as exc:
        raise ConfigError(f"{where}: equipment {factory!r} failed: {type(exc).__name__}: {exc}") from exc
    missing = missing_members(result, protocol)
    if missing:
        raise ConfigError(
            f"{where}: equipment {factory!r} returned {type(result).__name__}, not a {protocol.__name__}"
            f" (missing {', '.join(missing)})"
        )
    log.info("%s: equipment %s.%s (from %s)", where, type(result).__module__, type(result).__qualname__, factory)
    return result


async def close_equipment(equipment: object, where: str) -> None:
    """Call ``equipment.close()`` if it has one (awaiting it if it is a coroutine); log failures."""
    close = getattr(equipment, "close", None)
    if close is None:
        return
    try:
        result = close()
        if inspect.isawaitable(result):
            await result
    except Exception:
        log.exception("%s: closing the equipment failed", where)
