"""Optional capabilities any equipment (a robot controller's, a PackML unit's) may have: it declares
one by implementing the Protocol, and the shared code checks it with ``isinstance``, never by looking
an attribute up by name. The companions' own are beside their equipment Protocols
(``uacell.robotics.equipment``, ``uacell.packml.equipment``)."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Protocol, runtime_checkable


@runtime_checkable
class Reachable(Protocol):
    """Equipment that knows whether it can reach what it drives (a gateway driver and its PLC or
    controller): False while it cannot. Equipment without it is always reachable."""

    @property
    def reachable(self) -> bool: ...


@runtime_checkable
class Identified(Protocol):
    """Equipment that reports what it is: BrowseName of an Identification member (``SerialNumber``,
    ``Manufacturer``, ...) -> its value (uacell.machinery)."""

    @property
    def identification(self) -> Mapping[str, object]: ...
