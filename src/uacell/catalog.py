"""The companions this build of uacell serves: one line each, named here and nowhere else.

Each entry is the ``Companion`` value's import path; the shared code (configuration, roles, cell,
server) asks ``companions()`` and reads everything companion-specific from the values
(``uacell.companion``). A third companion is one package with its ``companion.py`` and one line here.
Named by path, imported on first use: the companions' packages import the shared modules, never the
other way round.
"""

from __future__ import annotations

import functools
import importlib

from uacell.companion import Companion
from uacell.datasets import PartDataSet

# Foundations first: a companion follows those it builds on (DI under Robotics), which also gives
# the official models their load order (``uacell.models.official_models``).
COMPANIONS = (
    "uacell.di.companion:DI_LOCKING",
    "uacell.robotics.companion:ROBOTICS",
    "uacell.packml.companion:PACKML_COMPANION",
    "uacell.machinery.companion:MACHINERY_COMPANION",
)


@functools.cache
def companions() -> tuple[Companion, ...]:
    """Every companion of ``COMPANIONS``, in that order."""
    found = []
    for entry in COMPANIONS:
        module, _, name = entry.partition(":")
        companion = getattr(importlib.import_module(module), name)
        assert isinstance(companion, Companion), entry
        found.append(companion)
    return tuple(found)


def dataset_of(role: str) -> PartDataSet | None:
    """What history keeps and PubSub publishes of parts of ``role``: every companion's ``datasets``
    for that role joined, in the companions' order (a robot's or a unit's own, then what another
    companion adds to the same part, as Machinery adds a machine's state and mode)."""
    found = [d for c in companions() for d in c.datasets if d.role == role]
    if len(found) <= 1:
        return found[0] if found else None
    values = tuple(i for d in found for i in d.values)
    notifiers = tuple(dict.fromkeys(n for d in found for n in d.notifiers))
    device = any(d.device for d in found)
    commands = tuple(c for d in found for c in d.commands)
    return PartDataSet(role, values, notifiers, device, commands)
