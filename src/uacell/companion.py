"""What a companion specification brings to uacell, declared in one place in its own package.

A companion (OPC 40010-1 Robotics, OPC 30050 PackML, DI LockingServices, ...) is a ``Companion``
value in its package's ``companion.py``; ``uacell.catalog`` lists the ones this build serves, one
line each. The shared code reads everything companion-specific from there:

- ``uacell.roles``: the method families (``type_hints``) and the rows of the role table (``roles``);
- ``uacell.config``: the configuration section (``section`` with its dataclass ``settings``) and
  the parts it adds to the cell (``cell_section``, read by ``cell_parser``);
- ``uacell.cell``: where instances live (``roots``);
- ``uacell.history`` and ``uacell.pubsub``: what is kept and published of its parts (``datasets``);
- ``uacell.web.discovery``: what the web HMI shows of its parts (``web_view``);
- ``uacell.metrics``: its figures in ``/metrics`` (``metrics``);
- ``uacell.models``: the official NodeSet files to fetch, verify and load (``models``);
- ``uacell.server``: the binder that ties the companion's models to their nodes (``binder``);
- ``uacell.di.locks``: which parts carry a DI Lock and which families it guards (``locks``).
"""

from __future__ import annotations

import importlib
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from typing import Any

from uacell.cell_file import SectionParser
from uacell.datasets import PartDataSet
from uacell.models.model_file import ModelFile
from uacell.roles import Family, Role

Closer = Callable[[], Awaitable[None]]
# Called once the cell exists, before the server listens, with the server (``uacell.server.UacellServer``,
# typed at each binder's definition: naming it here would tie every companion to the server's
# imports); returns what to run at shutdown (or None).
Binder = Callable[[Any], Awaitable[Closer | None]]


def lazy_binder(module: str, name: str) -> Binder:
    """The binder ``module.name``, imported when the server binds (configuration loading stays light)."""

    async def bind(app: Any) -> Closer | None:
        binder: Binder = getattr(importlib.import_module(module), name)
        return await binder(app)

    return bind


def lazy_metrics(module: str, name: str) -> Callable[[Any], Any]:
    """The metrics factory ``module.name``, imported when metrics start (prometheus-client stays unloaded
    otherwise)."""

    def make(app: Any) -> Any:
        return getattr(importlib.import_module(module), name)(app)

    return make


@dataclass(frozen=True)
class Root:
    """A standard object instances are placed in (``"DeviceSet"``: DI's ns=DI;i=5001, HasComponent)."""

    name: str
    model: str  # model key of the node's namespace
    node: int  # numeric id in that namespace
    reference: int  # ns0 id of the reference type from the root to a part (HasComponent, Organizes)


@dataclass(frozen=True)
class LockRule:
    """Parts of ``role`` carry a DI Lock; below the part of ``parent_role`` that contains them (if any).

    ``members`` are children (BrowseName paths) that are not lockable themselves but are guarded by
    the part's lock (a Controller's SystemOperation).
    """

    role: str
    parent_role: str | None = None
    members: tuple[str, ...] = ()


@dataclass(frozen=True)
class WebView:
    """What the web HMI shows of a companion's parts: the instances of type ``type_id`` (numeric, in the
    companion's ``namespace``) in the folder ``root`` of Objects, each described for the page by
    ``describe`` (``"module:function"``, an async function of the discoverer, the instance and the
    namespace index), listed under ``layout_key`` in the page's layout."""

    layout_key: str
    namespace: str
    root: str
    type_id: int
    describe: str

    def describer(self) -> Callable[..., Awaitable[dict[str, Any]]]:
        module, _, name = self.describe.partition(":")
        found: Callable[..., Awaitable[dict[str, Any]]] = getattr(importlib.import_module(module), name)
        return found


@dataclass(frozen=True)
class Companion:
    name: str
    models: tuple[ModelFile, ...] = ()  # the official NodeSet files it needs (uacell models fetch)
    # Its figures for /metrics: called with the server (uacell.host.Host) when metrics start, returns
    # a prometheus-client collector (an object with ``collect()``).
    metrics: Callable[[Any], Any] | None = None
    web_view: WebView | None = None  # what the web HMI shows of its parts (uacell.web.discovery)
    datasets: tuple[PartDataSet, ...] = ()  # what history keeps and PubSub publishes of its parts
    binder: Binder | None = None
    section: str | None = None  # configuration section, e.g. "robot"
    settings: type[Any] | None = None  # its dataclass: every field optional, typed by its default
    cell_section: str | None = None  # its parts in the cell configuration, e.g. "robots" ([[robots]])
    cell_parser: SectionParser | None = None  # reads and checks them (uacell.cell_file.CellSection)
    roots: tuple[Root, ...] = ()
    roles: Mapping[tuple[Family, str], Role] = field(default_factory=dict)  # (family, method) -> least role
    type_hints: Mapping[str, Family] = field(default_factory=dict)  # ObjectType/instance name -> family
    locks: tuple[LockRule, ...] = ()
    lock_guarded: frozenset[Family] = frozenset()  # families a foreign lock refuses (docs/decisions.md 20)
