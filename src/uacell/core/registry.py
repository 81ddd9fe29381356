"""Typed registries of the parts a server binds, keyed by the part's browse path.

A browse path is the dotted path of the part's instance below its root, as the cell namespace's
NodeIds spell it: ``Robot1.Controllers.Controller1``, ``Filler1``. Pure: no OPC UA stack here.
"""

from __future__ import annotations

from collections.abc import Iterator
from typing import Any, Generic, TypeVar

T = TypeVar("T")
__all__ = ["Registries", "Registry", "RegistryKey", "T"]


class Registry(Generic[T]):
    """Parts of one kind (``kind`` names it in errors), each registered once under its browse path."""

    def __init__(self, kind: str) -> None:
        self.kind = kind
        self._items: dict[str, T] = {}

    def add(self, path: str, item: T) -> T:
        if path in self._items:
            raise ValueError(f"{self.kind} {path!r} is registered twice")
        self._items[path] = item
        return item

    def __getitem__(self, path: str) -> T:
        try:
            return self._items[path]
        except KeyError:
            known = ", ".join(self._items) or "none"
            raise KeyError(f"no {self.kind} {path!r} (registered: {known})") from None

    def get(self, path: str) -> T | None:
        return self._items.get(path)

    def named(self, name: str) -> T:
        """The one part whose browse path ends in ``name`` (``"Controller1"``, ``"Filler1"``)."""
        found = [item for path, item in self._items.items() if path.rsplit(".", 1)[-1] == name]
        if len(found) != 1:
            raise KeyError(f"{len(found)} {self.kind}s are called {name!r}")
        return found[0]

    def __contains__(self, path: object) -> bool:
        return path in self._items

    def __iter__(self) -> Iterator[str]:
        return iter(self._items)

    def __len__(self) -> int:
        return len(self._items)

    def items(self) -> list[tuple[str, T]]:
        return list(self._items.items())

    def values(self) -> list[T]:
        return list(self._items.values())


class RegistryKey(Generic[T]):
    """Names one registry of an application and the type of its parts.

    Declared next to the part's code (``CONTROLLERS: RegistryKey[RoboticsBinding] =
    RegistryKey("controller")``); ``Registries.of(CONTROLLERS)`` is then a ``Registry[RoboticsBinding]``.
    """

    def __init__(self, kind: str) -> None:
        self.kind = kind

    def __repr__(self) -> str:
        return f"RegistryKey({self.kind!r})"


class Registries:
    """Every registry of one application, created on first use."""

    def __init__(self) -> None:
        self._registries: dict[RegistryKey[Any], Registry[Any]] = {}

    def of(self, key: RegistryKey[T]) -> Registry[T]:
        registry = self._registries.get(key)
        if registry is None:
            registry = self._registries[key] = Registry(key.kind)
        return registry
