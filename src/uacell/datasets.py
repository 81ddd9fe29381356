"""Which values and events of a part matter: the one declaration history, PubSub and Sparkplug read.

Each companion declares the DataSets of its parts (``Companion.datasets``, e.g. ``uacell.packml.datasets``);
``uacell.catalog.dataset_of(role)`` finds one.
Per part role (``uacell.cell.Part.role``), the variables below the part (BrowseName paths, "/"
separated, ``*`` one child of any name) with what they are, and the notifiers below the part whose
events matter (state machines: their TransitionEvents and AuditUpdateStateEvents; a robot
controller's alarms, fired through the controller; history also keeps the Server object's events as
a whole); for Sparkplug (docs/sparkplug.md) whether the part is a device of its own and the commands
it takes. Pure: resolving a path to a node is the reader's (``resolve`` takes a child lookup).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from enum import Enum
from typing import TypeVar

N = TypeVar("N")


class Kind(Enum):
    STATE = "state"  # a state machine's CurrentState or a mode
    COUNTER = "counter"  # counts of products
    SPEED = "speed"  # machine speeds, overrides
    POSITION = "position"  # axis positions: many changes; only with [history] axis_positions
    PROGRAM = "program"  # which program runs, where it is
    OEE = "oee"  # OEE figures (uacell's namespace, docs/packml.md)
    ALARM = "alarm"  # a unit's stop reason and alarm list


@dataclass(frozen=True)
class Item:
    path: str
    kind: Kind

    @property
    def optional(self) -> bool:
        """Kept only when configured (axis positions change with every move)."""
        return self.kind is Kind.POSITION


# A command a part takes from outside OPC UA (Sparkplug's DCMD, docs/sparkplug.md): its name and the
# method(s) it calls, as (object path below the part, method BrowseName); of several, the first
# whose Executable is true.
Command = tuple[str, tuple[tuple[str, str], ...]]


@dataclass(frozen=True)
class PartDataSet:
    role: str  # the part role it applies to
    values: tuple[Item, ...]
    notifiers: tuple[str, ...]  # state machines below the part whose events matter
    device: bool = False  # a Sparkplug device of its own; other parts join the device nearest in the cell
    commands: tuple[Command, ...] = ()


def resolve(path: str, children: Callable[[N], list[tuple[str, N]]], root: N) -> Iterator[tuple[str, N]]:
    """Every node ``path`` names below ``root``: (the path with ``*`` filled in, the node's key).

    ``children(node)`` lists a node's children as (BrowseName, node); a missing name yields nothing;
    ``""`` is ``root`` itself.
    """
    if not path:
        yield "", root
        return

    def walk(node: N, names: list[str], done: list[str]) -> Iterator[tuple[str, N]]:
        if not names:
            yield "/".join(done), node
            return
        head, rest = names[0], names[1:]
        for name, child in children(node):
            if head == "*" or name == head:
                yield from walk(child, rest, [*done, name])

    yield from walk(root, path.split("/"), [])
