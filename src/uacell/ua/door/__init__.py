"""The one door to asyncua (and to uvicorn, and to the stdlib module uacell speeds up): every class
attribute uacell replaces, every attribute of asyncua's objects it swaps or sets, every subclass of
theirs and every private name it reads goes through here, each listed in ``inventory.ENTRIES`` with
why and what it replaces (docs/asyncua.md). Nothing outside this package touches an asyncua private
name or assigns an asyncua attribute (tests/test_asyncua_door.py reads every module to check).

- ``attach()`` (door/processing.py) checks the installed versions against those the inventory was
  read against (``check_versions``) and wraps asyncua's request path, once per process;
- ``swap``/``swapped``/``configure`` set one server's attribute; ``subclass`` registers a subclass;
- door/connection.py reads the private state of a connection, a session, a buffer;
- ``tag``/``tagged`` keep uacell's own state on an asyncua object.
"""

from __future__ import annotations

import importlib
import logging
import sys
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import Any, TypeVar

from uacell.ua.door.inventory import ENTRIES, INVENTORY, VERIFIED, Entry, Kind

__all__ = [
    "ENTRIES",
    "INVENTORY",
    "VERIFIED",
    "DoorError",
    "Entry",
    "Kind",
    "check_versions",
    "configure",
    "installed",
    "patch",
    "subclass",
    "swap",
    "swapped",
    "tag",
    "tagged",
]

log = logging.getLogger(__name__)
C = TypeVar("C", bound=type)

_INSTALLED: set[str] = set()


class DoorError(RuntimeError):
    """An installed asyncua differs from the one the door was read against, or a change is not in
    the inventory."""


# "Class.attribute" for each entry whose last two parts name it alone (InternalServer.method_service)
_SHORT = {
    short: e.target
    for e in ENTRIES
    if sum(1 for o in ENTRIES if o.target.endswith("." + (short := ".".join(e.target.split(".")[-2:])))) == 1
}


def _entry(target: str, *kinds: Kind) -> Entry:
    entry = INVENTORY.get(target) or INVENTORY.get(_SHORT.get(target, ""))
    if entry is None:
        raise DoorError(f"{target} is not in uacell.ua.door.inventory: list it (docs/asyncua.md) before changing it")
    if entry.kind not in kinds:
        raise DoorError(f"{target} is listed as a {entry.kind.value}, not a {' or '.join(k.value for k in kinds)}")
    return entry


def installed() -> frozenset[str]:
    """The inventory entries installed (or registered) in this process so far."""
    return frozenset(_INSTALLED)


def check_versions() -> None:
    """asyncua must be the version the inventory was read against (its private entry points are
    replaced): else one line says so and the server does not start. uvicorn (one subclass, pinned to a
    range) is only warned about."""
    found = _version("asyncua")
    if found != VERIFIED["asyncua"]:
        raise DoorError(
            f"asyncua {found} is installed; uacell's door to it was checked against {VERIFIED['asyncua']} "
            "(docs/asyncua.md: how to upgrade asyncua)"
        )
    web = _version("uvicorn")
    if web is not None and web != VERIFIED["uvicorn"]:
        log.warning(
            "uvicorn %s is installed; uacell's header deadline was checked against %s", web, VERIFIED["uvicorn"]
        )


def _version(package: str) -> str | None:
    """The version of ``package`` as it says (``__version__``): asyncua's always (it is imported
    anyway), uvicorn's once something loaded it (the web HMI); reading the installed metadata instead
    would cost a start about 35 ms (``importlib.metadata``)."""
    if package == "asyncua":
        import asyncua

        return str(asyncua.__version__)
    module = sys.modules.get(package)
    version = getattr(module, "__version__", None)
    return None if version is None else str(version)


def patch(target: str, value: Any) -> Any:
    """Replace a class's (or module's) attribute process-wide; returns what it was."""
    entry = _entry(target, Kind.PATCH)
    owner, name = _resolve_owner(entry.target)
    original = getattr(owner, name, None)
    setattr(owner, name, value)
    _INSTALLED.add(entry.target)
    return original


def _resolve_owner(target: str) -> tuple[Any, str]:
    path, _, name = target.rpartition(".")
    parts = path.split(".")
    for cut in range(len(parts), 0, -1):
        try:
            owner: Any = importlib.import_module(".".join(parts[:cut]))
        except ImportError:
            continue
        for part in parts[cut:]:
            owner = getattr(owner, part)
        return owner, name
    raise DoorError(f"cannot import {path}")


def swap(obj: Any, target: str, value: Any) -> Any:
    """Replace the attribute ``target`` names (``module.Class.attr``, or ``Class.attr`` when that is
    unambiguous) on one object; returns what it was."""
    entry = _entry(target, Kind.SWAP)
    name = target.rpartition(".")[2]
    original = getattr(obj, name)
    setattr(obj, name, value)
    _INSTALLED.add(entry.target)
    return original


@contextmanager
def swapped(obj: Any, target: str, value: Any) -> Iterator[Any]:
    """``swap`` for the duration of a ``with``: then the object's attribute is back (its class's,
    when the object had none of its own)."""
    name = target.rpartition(".")[2]
    own = name in vars(obj)
    original = swap(obj, target, value)
    try:
        yield original
    finally:
        if own:
            setattr(obj, name, original)
        else:
            delattr(obj, name)


def configure(obj: Any, target: str, value: Any) -> None:
    """Set a setting asyncua reads from an attribute of ``obj``."""
    entry = _entry(target, Kind.SETTING)
    setattr(obj, target.rpartition(".")[2], value)
    _INSTALLED.add(entry.target)


def subclass(target: str) -> Callable[[C], C]:
    """Register a subclass of the asyncua (or uvicorn) class ``target``."""
    entry = _entry(target, Kind.SUBCLASS)

    def register(cls: C) -> C:
        base = _resolve_owner(entry.target)
        if not issubclass(cls, getattr(*base)):
            raise DoorError(f"{cls.__qualname__} is registered as a subclass of {target} but is not one")
        _INSTALLED.add(entry.target)
        return cls

    return register


def tag(obj: Any, name: str, value: Any) -> None:
    """Keep uacell's ``value`` on an asyncua object (as ``_uacell_<name>``)."""
    setattr(obj, "_uacell_" + name, value)


def tagged(obj: Any, name: str, default: Any = None) -> Any:
    """What ``tag`` kept on ``obj`` under ``name``, else ``default``."""
    return getattr(obj, "_uacell_" + name, default)


def record(target: str) -> None:
    """For the door's own modules: ``target`` (a listed entry) is installed."""
    _INSTALLED.add(_entry(target, *Kind).target)
