"""The companions this build of uacell serves: one line each, named here and nowhere else.

Each entry is the ``Companion`` value's import path. Only the composition root asks ``companions()``
(``uacell.server.UacellServer`` unless given others, the CLI, which also hands them to the HMI's
``uacell.web.hosting.start_web``, and ``uacell.config`` for the sections): it hands the companions,
or what the parts need of them (the role table, the official models), to the parts that read their
declarations (docs/companions.md; tests/test_layers.py checks that nothing else imports this module).
A third companion is one package with its ``companion.py`` and one line here.
Named by path, imported on first use: the companions' packages import the shared modules, never the
other way round.
"""

from __future__ import annotations

import functools
import importlib
from typing import Any

from uacell.core.companion import Companion

# Foundations first: a companion follows those it builds on (DI under Robotics), which also gives
# the official models their load order (``uacell.models.official_models``).
COMPANIONS = (
    "uacell.di.companion:DI_LOCKING",
    "uacell.robotics.companion:ROBOTICS",
    "uacell.packml.companion:PACKML_COMPANION",
    "uacell.machinery.companion:MACHINERY_COMPANION",
)


@functools.cache
def companions() -> tuple[Companion[Any], ...]:
    """Every companion of ``COMPANIONS``, in that order.

    Loaded by name, so typed by what they are at run time: each is declared a
    ``Companion[uacell.host.ServerView]`` where it is defined (mypy checks its binder and metrics
    factory there), and the server takes them as such. This module cannot name ``uacell.host``:
    ``uacell.config`` asks it for the sections, and ``uacell.host`` imports the configuration.
    """
    found = []
    for entry in COMPANIONS:
        module, _, name = entry.partition(":")
        companion = getattr(importlib.import_module(module), name)
        assert isinstance(companion, Companion), entry
        found.append(companion)
    return tuple(found)
