"""Which devices a cell has and which metrics each carries (docs/sparkplug.md, "Devices and metrics").

One device per PackML unit (its part path, ``Filler1``) and per robot controller
(``Robot1.Controllers.Controller1``); a controller's device also carries its task controls' values
(``TaskControls/TaskControl1/…``) and its robot's motion devices' (``MotionDevices/Arm1/…``).
A metric is named by its BrowseName path below the device's part (or its robot), the values being what
the part's companion declares (``uacell.datasets``, as for history and PubSub) plus ``extra_values``.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field

from asyncua import ua

from uacell.catalog import dataset_of
from uacell.datasets import Item, Kind


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
    commands: bool  # its declared commands are the device's (the first task control's only)


@dataclass
class DevicePlan:
    device_id: str
    role: str
    sources: list[Source] = field(default_factory=list)


def plan_devices(
    parts: Sequence[PartRef], extra: Iterable[str] = (), axis_positions: bool = True, only: Sequence[str] = ()
) -> list[DevicePlan]:
    """The devices of ``parts`` in the cell's order (only those named in ``only``, when given)."""
    added: dict[str, list[Item]] = {}
    for entry in extra:
        role, _, path = entry.partition(":")
        added.setdefault(role, []).append(Item(path, Kind.STATE))

    def items(role: str) -> tuple[Item, ...]:
        dataset = dataset_of(role)
        declared = [*(dataset.values if dataset else ()), *added.get(role, [])]
        return tuple(i for i in declared if axis_positions or i.kind is not Kind.POSITION)

    plans = []
    for part in parts:
        if part.role == "packml_unit":
            plans.append(DevicePlan(part.path, part.role, [Source(part, "", items(part.role), True)]))
        elif part.role == "controller":
            plan = DevicePlan(part.path, part.role, [Source(part, "", items(part.role), True)])
            robot = part.path.split(".Controllers.", 1)[0]
            first_task = True
            for other in parts:
                if other.role == "task_control" and other.path.startswith(part.path + "."):
                    prefix = other.path[len(part.path) + 1 :].replace(".", "/") + "/"
                    plan.sources.append(Source(other, prefix, items(other.role), first_task))
                    first_task = False
                elif other.role == "motion_device" and other.path.startswith(robot + ".MotionDevices."):
                    prefix = other.path[len(robot) + 1 :].replace(".", "/") + "/"
                    plan.sources.append(Source(other, prefix, items(other.role), False))
            plans.append(plan)
    return [p for p in plans if not only or p.device_id in only]
