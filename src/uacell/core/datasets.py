"""Which values and events of a part matter: the one declaration history, PubSub and Sparkplug read.

Each companion declares the DataSets of its parts (``Companion.datasets``, e.g. ``uacell.packml.datasets``);
``DataSets``, built by the composition root from the companions it serves, finds the one of a role.
Per part role (``uacell.binding.cell.Part.role``), the variables below the part (BrowseName paths, "/"
separated, ``*`` one child of any name) with what they are, and the notifiers below the part whose
events matter (state machines: their TransitionEvents and AuditUpdateStateEvents; a robot
controller's alarms, fired through the controller; history also keeps the Server object's events as
a whole); for Sparkplug (docs/sparkplug.md) whether the part is a device of its own and the commands
it takes. Pure: resolving a path to a node is the reader's (``resolve`` takes a child lookup).
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from typing import TypeVar

N = TypeVar("N")


@dataclass(frozen=True)
class Kind:
    """What a value is. Open: the kinds every companion may use are below; a companion declares its
    own beside its DataSets (robots: ``uacell.robotics.datasets.POSITION``, PackML: ``OEE``).

    ``optional``: kept and published only when configured (``axis_positions`` of ``[history]``,
    ``[pubsub]`` and ``[sparkplug]``), by PubSub on its slower interval: values that change with every
    move."""

    name: str
    optional: bool = False


STATE = Kind("state")  # a state machine's CurrentState or a mode
COUNTER = Kind("counter")  # counts of products
SPEED = Kind("speed")  # machine speeds, overrides
ALARM = Kind("alarm")  # a stop reason, an alarm list


@dataclass(frozen=True)
class Item:
    path: str
    kind: Kind

    @property
    def optional(self) -> bool:
        """Kept only when configured (axis positions change with every move)."""
        return self.kind.optional


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


class DataSets:
    """The DataSets of the companions a server serves, by part role: the registry history, PubSub and
    Sparkplug read (handed to them by the composition root, ``uacell.server``)."""

    def __init__(self, declared: Iterable[PartDataSet]) -> None:
        self.declared = tuple(declared)

    def of(self, role: str) -> PartDataSet | None:
        """What is kept and published of parts of ``role``: every DataSet declared for that role
        joined, in the companions' order (a robot's or a unit's own, then what another companion adds
        to the same part, as Machinery adds a machine's state and mode)."""
        found = [d for d in self.declared if d.role == role]
        if len(found) <= 1:
            return found[0] if found else None
        values = tuple(i for d in found for i in d.values)
        notifiers = tuple(dict.fromkeys(n for d in found for n in d.notifiers))
        device = any(d.device for d in found)
        commands = tuple(c for d in found for c in d.commands)
        return PartDataSet(role, values, notifiers, device, commands)
