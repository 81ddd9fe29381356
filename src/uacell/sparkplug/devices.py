"""Which devices a cell has and which metrics each carries (docs/sparkplug.md, "Devices and metrics").

A part whose DataSet (``uacell.core.datasets``, its companion's) says ``device`` is a device of its own,
named by its path (``Filler1``, ``Robot1.Controllers.Controller1``); every other part with a DataSet
joins the device whose path shares the most leading levels with its own (a controller's task
controls, its robot's motion devices; the first such device in the cell's order on a tie), its
metric names below the levels they do not share (``TaskControls/TaskControl1/…``,
``MotionDevices/Arm1/…``). A metric is named by its BrowseName path below that, the values being
what the DataSet declares plus ``extra_values``; the commands are the DataSets' too, a device's own
first, then its parts' in the cell's order (of two with one name, the first).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from asyncua import ua

from uacell.core.datasets import STATE, Command, DataSets, Item


@dataclass(frozen=True)
class PartRef:
    role: str
    node: ua.NodeId
    path: str  # the part's NodeId path, e.g. "Robot1.Controllers.Controller1"


@dataclass(frozen=True)
class Source:
    """One part whose values (and commands) a device carries, its metric names below ``prefix``."""

    part: PartRef
    prefix: str  # "" for the device's own part, "TaskControls/TaskControl1/" for one of its task controls
    items: tuple[Item, ...]
    commands: tuple[Command, ...]


@dataclass
class DevicePlan:
    device_id: str
    sources: list[Source] = field(default_factory=list)


def _shared(a: str, b: str) -> int:
    """How many leading path levels ``a`` and ``b`` share."""
    n = 0
    for x, y in zip(a.split("."), b.split("."), strict=False):
        if x != y:
            break
        n += 1
    return n


def plan_devices(
    datasets: DataSets,
    parts: Sequence[PartRef],
    extra: Iterable[str] = (),
    axis_positions: bool = True,
    only: Sequence[str] = (),
) -> list[DevicePlan]:
    """The devices of ``parts`` in the cell's order (only those named in ``only``, when given)."""
    added: dict[str, list[Item]] = {}
    for entry in extra:
        role, _, path = entry.partition(":")
        added.setdefault(role, []).append(Item(path, STATE))
    plans: dict[str, DevicePlan] = {}
    joining: list[tuple[PartRef, tuple[Item, ...], tuple[Command, ...]]] = []
    for part in parts:
        dataset = datasets.of(part.role)
        if dataset is None:
            continue
        declared = [*dataset.values, *added.get(part.role, [])]
        items = tuple(i for i in declared if axis_positions or not i.optional)
        if dataset.device:
            plans[part.path] = DevicePlan(part.path, [Source(part, "", items, dataset.commands)])
        else:
            joining.append((part, items, dataset.commands))
    for part, items, commands in joining:
        best = max(plans, key=lambda d: _shared(d, part.path), default=None)
        shared = _shared(best, part.path) if best is not None else 0
        if best is None or shared == 0:
            continue  # no device of its own nor one nearby: not published
        prefix = "/".join(part.path.split(".")[shared:]) + "/"
        plans[best].sources.append(Source(part, prefix, items, commands))
    return [p for p in plans.values() if not only or p.device_id in only]
