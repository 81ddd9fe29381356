"""The one pool of shared connections every gateway transport uses: Modbus/TCP connections (robots, UR,
PackTags units), the polled links of S7 and Logix PLCs, the OPC UA links to PLCs.

A connection is made on its key's first use and shared by every part that asks for the same key (fifty
units on one PLC use one connection); the parts must agree on the settings the connection has (a
ValueError names both parts, the key and the values); the last part that lets it go closes it.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable, Hashable, Iterator
from dataclasses import dataclass, field
from typing import Any, Generic, Protocol, TypeVar


class Pooled(Protocol):
    users: int  # the parts that hold it (the pool counts them)


K = TypeVar("K", bound=Hashable)
C = TypeVar("C", bound=Pooled)
# (endpoint, setting, (first part, its value), (part, its value)) -> the one-line refusal
Conflict = Callable[[str, str, tuple[str, object], tuple[str, object]], str]


def shared_conflict(endpoint: str, key: str, first: tuple[str, object], second: tuple[str, object]) -> str:
    """The one-line refusal of two parts that share the connection to ``endpoint`` with different ``key``."""
    (a, x), (b, y) = first, second

    def said(v: object) -> str:
        return f"{v:g}" if isinstance(v, float) else repr(v)

    return (
        f"{b or 'a part'}: {key} = {said(y)}, but {a} shares its connection to {endpoint} with {key} = {said(x)}: "
        f"parts on one PLC endpoint use one connection, so give them the same {key}"
    )


def unit_conflict(endpoint: str, key: str, first: tuple[str, object], second: tuple[str, object]) -> str:
    """The refusal of a PackTags unit whose setting differs from the units' before it on one PLC."""
    return (
        f"{second[0]}: {key}: another unit on {endpoint} set {first[1]}; "
        "units on one PLC share its connection and its settings"
    )


@dataclass
class _Entry(Generic[C]):
    item: C
    owner: str  # the part that made it (for messages)
    settings: dict[str, object] = field(default_factory=dict)


class SharedPool(Generic[K, C]):
    """Connections by key, shared. ``close`` ends one (it may be a coroutine function); ``name`` is
    how messages call its endpoint; ``conflict`` words a refusal."""

    def __init__(
        self,
        close: Callable[[C], Any],
        name: Callable[[C], str],
        conflict: Conflict = shared_conflict,
    ) -> None:
        self._close, self._name, self._conflict = close, name, conflict
        self._entries: dict[K, _Entry[C]] = {}

    def get(self, key: K, make: Callable[[], C], part: str = "", **settings: object) -> C:
        """The connection of ``key`` (``make`` makes it on first use), one more user counted; a
        ValueError, nothing counted, when one of ``settings`` differs from the connection's."""
        entry = self._entries.get(key)
        if entry is None:
            entry = self._entries[key] = _Entry(make(), part, dict(settings))
        else:
            self.check(key, part, **settings)
        entry.item.users += 1
        return entry.item

    def check(self, key: K, part: str = "", **settings: object) -> None:
        """A ValueError naming both parts when the connection of ``key`` is open with other ``settings``."""
        entry = self._entries.get(key)
        if entry is None:
            return
        for setting, value in settings.items():
            had = entry.settings.get(setting, value)
            if had != value:
                first = (entry.owner or "another part", had)
                raise ValueError(self._conflict(self._name(entry.item), setting, first, (part, value)))

    async def release(self, item: C) -> None:
        """One user less; the last one closes it (and the next ``get`` makes a new one)."""
        item.users -= 1
        if item.users <= 0:
            self._entries = {k: e for k, e in self._entries.items() if e.item is not item}
            closing = self._close(item)
            if inspect.isawaitable(closing):
                await closing

    def __len__(self) -> int:
        return len(self._entries)

    def get_open(self, key: K) -> C | None:
        """The connection of ``key`` if it is open (nothing counted)."""
        entry = self._entries.get(key)
        return entry.item if entry is not None else None

    def values(self) -> Iterator[C]:
        return (e.item for e in self._entries.values())
