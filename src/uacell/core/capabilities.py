"""Optional capabilities any equipment (a robot controller's, a PackML unit's) may have: it declares
one by implementing the Protocol, and the shared code checks it with ``isinstance``, never by looking
an attribute up by name (``reachable`` alone answers what that check would, in one lookup: its
docstring says why). The companions' own are beside their equipment Protocols
(``uacell.robotics.equipment``, ``uacell.packml.equipment``)."""

from __future__ import annotations

import typing
from collections.abc import Callable, Mapping
from typing import Protocol, TypeGuard, TypeVar, runtime_checkable

T = TypeVar("T")


@runtime_checkable
class Reachable(Protocol):
    """Equipment that knows whether it can reach what it drives (a gateway driver and its PLC or
    controller): False while it cannot. Equipment without it is always reachable."""

    @property
    def reachable(self) -> bool: ...


def reachable(equipment: object) -> bool:
    """Can ``equipment`` reach what it drives: its ``reachable`` when it is ``Reachable``, else True.

    Asked several times in every call and for every method whose Executable is refreshed, so answered
    in one lookup: the Protocol's one member is a property, so what ``has(equipment, Reachable)`` finds
    (``hasattr``: the attribute is there and reading it raises no AttributeError) is what ``getattr``
    with a default finds (tests/test_capabilities.py holds the two to the same answers)."""
    return bool(getattr(equipment, "reachable", True))


@runtime_checkable
class Identified(Protocol):
    """Equipment that reports what it is: BrowseName of an Identification member (``SerialNumber``,
    ``Manufacturer``, ...) -> its value (uacell.machinery)."""

    @property
    def identification(self) -> Mapping[str, object]: ...


_MEMBERS: dict[object, tuple[tuple[str, bool], ...]] = {}


def _members(capability: object) -> tuple[tuple[str, bool], ...]:
    """The names a capability Protocol declares, each with whether it is a method (found once)."""
    members = _MEMBERS.get(capability)
    if members is None:
        names = typing._get_protocol_attrs(capability)  # type: ignore[attr-defined]  # what isinstance walks
        members = _MEMBERS[capability] = tuple(
            (name, callable(getattr(capability, name, None))) for name in sorted(names)
        )
    return members


def has(equipment: object, capability: Callable[..., T]) -> TypeGuard[T]:
    """``isinstance(equipment, capability)`` for a capability Protocol, answered as isinstance does
    (every member present; a method member not None) but with the Protocol's members found once:
    Python 3.11's isinstance walks the Protocol's classes on every check (about 20 us), and calls ask
    on every call (is the unit reachable? may the controller confirm a start?). An equipment's own
    attributes count, as for isinstance (a factory may add ``identification`` to an instance).
    """
    for name, method in _members(capability):
        if not hasattr(equipment, name) or (method and getattr(equipment, name) is None):
            return False
    return True
