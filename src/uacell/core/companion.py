"""What a companion specification brings to uacell, declared in one place in its own package.

A companion (OPC 40010-1 Robotics, OPC 30050 PackML, DI LockingServices, ...) is a ``Companion``
value in its package's ``companion.py``; ``uacell.catalog`` lists the ones this build serves, one
line each. The shared code reads everything companion-specific from there:

- ``uacell.core.rights``: the method families (``type_hints``) and the rows of the role table (``roles``);
- ``uacell.config``: the configuration section (``section`` with its dataclass ``settings``) and
  the parts it adds to the cell (``cell_section``, read by ``cell_parser``);
- ``uacell.binding.cell``: where instances live (``roots``);
- ``uacell.history`` and ``uacell.pubsub``: what is kept and published of its parts (``datasets``);
- ``uacell.web.discovery``: what the web HMI shows of its parts (``web_view``);
- ``uacell.services.metrics``: its figures in ``/metrics`` (``metrics``);
- ``uacell.models``: the official NodeSet files to fetch, verify and load (``models``);
- ``uacell.server``: the binder that ties the companion's models to their nodes (``binder``), and the
  nodes of uacell's own its parts get with the cell, kept in the address-space snapshot (``shape``);
- ``uacell.di.locks``: which parts carry a DI Lock and which families it guards (``locks``).
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.resources
import importlib.util
from collections.abc import Awaitable, Callable, Iterable, Mapping
from dataclasses import Field, dataclass, field
from importlib.resources.abc import Traversable
from pathlib import Path
from typing import Any, ClassVar, Generic, Protocol, TypeVar

from uacell.core.cell_file import SectionParser
from uacell.core.datasets import DataSets, PartDataSet
from uacell.core.roles import Family, Role
from uacell.models.model_file import ModelFile

Closer = Callable[[], Awaitable[None]]

# The server as a companion's functions receive it: ``uacell.host.ServerView`` for this build's
# companions (``Companion[ServerView]``), named by them, not here: the kernel stays below the server's
# imports. Contravariant: a companion whose functions need less of the server serves one that has more.
S = TypeVar("S", contravariant=True)
H = TypeVar("H")

# Called once the cell exists, before the server listens, with the server; returns what to run at
# shutdown (or None).
Binder = Callable[[S], Awaitable[Closer | None]]


class Collector(Protocol):
    """A prometheus-client collector: what a companion's metrics factory returns."""

    def collect(self) -> Iterable[Any]: ...


# Called with the server when metrics start; returns the companion's collector.
MetricsFactory = Callable[[S], Collector]


class SectionSettings(Protocol):
    """A companion's configuration section: a dataclass (every field optional, typed by its default)."""

    __dataclass_fields__: ClassVar[dict[str, Field[Any]]]


def lazy_binder(module: str, name: str) -> Binder[H]:
    """The binder ``module.name``, imported when the server binds (configuration loading stays light)."""

    async def bind(app: H) -> Closer | None:
        binder: Binder[H] = getattr(importlib.import_module(module), name)
        return await binder(app)

    return bind


# Called once the cell is built, before the address-space snapshot is taken, with the address space
# (``uacell.binding.space.Space``) and the built cell (``uacell.binding.cell.CellBuilder``): makes the nodes of
# uacell's own that the companion's parts get whatever their equipment and configuration, so that a
# restart finds them in the snapshot. It leaves a node that exists alone; the binder makes any that
# are missing (a server without the snapshot) the same way.
Shape = Callable[[Any, Any], Awaitable[None]]


def _function(spec: str) -> Any:
    """The function ``"module:function"``, importing its module."""
    module, _, name = spec.partition(":")
    return getattr(importlib.import_module(module), name)


def shape_function(spec: str) -> Shape:
    """The shape function ``"module:function"`` (imported when the cell is built)."""
    found: Shape = _function(spec)
    return found


def shapes_digest(specs: Iterable[str]) -> str:
    """SHA-256 of the source of the modules of the shape functions ``specs``: what they make is in
    the snapshot, so their code is part of its key (read without importing them)."""
    digest = hashlib.sha256()
    for spec in sorted(specs):
        module = spec.partition(":")[0]
        found = importlib.util.find_spec(module)
        origin = found.origin if found is not None else None
        digest.update(spec.encode())
        digest.update(Path(origin).read_bytes() if origin else b"")
    return digest.hexdigest()


def lazy_metrics(module: str, name: str) -> MetricsFactory[H]:
    """The metrics factory ``module.name``, imported when metrics start (prometheus-client stays unloaded
    otherwise)."""

    def make(app: H) -> Collector:
        factory: MetricsFactory[H] = getattr(importlib.import_module(module), name)
        return factory(app)

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
    """What the web HMI shows of a companion's parts, all of it in the companion's package.

    The server side: the instances of type ``type_id`` (numeric, in the companion's ``namespace``) in
    the folder ``root`` of Objects, each described for the page by ``describe`` (an async function of
    the discoverer, the instance and the namespace index), listed under ``layout_key`` in the page's
    layout; ``history`` (optional) reads a part's history view (an async function of the client, the
    discovered cell, the part's name and the window, ``uacell.web.history``). Both functions are
    named ``"module:function"``: they are imported when the HMI browses (with asyncua's client), so
    that loading the configuration does not import them.

    The browser side: ``script``, a JavaScript module in the package (e.g. ``static/view.js``) the
    page loads (served at ``/views/<layout_key>.js``), which registers how the parts of ``layout_key``
    are drawn (docs/companions.md); ``style``, its stylesheet (``/views/<layout_key>.css``).
    """

    layout_key: str
    namespace: str
    root: str
    type_id: int
    describe: str
    script: Traversable | None = None
    style: Traversable | None = None
    history: str | None = None

    def describer(self) -> Callable[..., Awaitable[dict[str, Any]]]:
        found: Callable[..., Awaitable[dict[str, Any]]] = _function(self.describe)
        return found

    def history_reader(self) -> Callable[..., Awaitable[dict[str, Any]]] | None:
        if self.history is None:
            return None
        found: Callable[..., Awaitable[dict[str, Any]]] = _function(self.history)
        return found


def package_file(package: str, name: str) -> Traversable:
    """The file ``name`` (``"static/view.js"``) shipped in ``package`` (``"uacell.machinery"``)."""
    return importlib.resources.files(package).joinpath(*name.split("/"))


@dataclass(frozen=True)
class Companion(Generic[S]):
    """A companion's declarations; ``S`` is what its binder and metrics factory receive of the server
    (``Companion[uacell.host.ServerView]``)."""

    name: str
    models: tuple[ModelFile, ...] = ()  # the official NodeSet files it needs (uacell models fetch)
    # Its figures for /metrics: called with the server when metrics start, returns a prometheus-client
    # collector (an object with ``collect()``).
    metrics: MetricsFactory[S] | None = None
    web_view: WebView | None = None  # what the web HMI shows of its parts (uacell.web.discovery)
    datasets: tuple[PartDataSet, ...] = ()  # what history keeps and PubSub publishes of its parts
    binder: Binder[S] | None = None
    shape: str | None = None  # "module:function", a ``Shape``: nodes of its parts kept in the snapshot
    section: str | None = None  # configuration section, e.g. "robot"
    settings: type[SectionSettings] | None = None  # its dataclass: every field optional, typed by its default
    cell_section: str | None = None  # its parts in the cell configuration, e.g. "robots" ([[robots]])
    cell_parser: SectionParser | None = None  # reads and checks them (uacell.core.cell_file.CellSection)
    roots: tuple[Root, ...] = ()
    roles: Mapping[tuple[Family, str], Role] = field(default_factory=dict)  # (family, method) -> least role
    type_hints: Mapping[str, Family] = field(default_factory=dict)  # ObjectType/instance name -> family
    locks: tuple[LockRule, ...] = ()
    lock_guarded: frozenset[Family] = frozenset()  # families a foreign lock refuses (docs/decisions.md 20)


def datasets_of(companions: Iterable[Companion[H]]) -> DataSets:
    """The DataSets ``companions`` declare, joined by part role (``uacell.core.datasets.DataSets``)."""
    return DataSets(d for c in companions for d in c.datasets)


def models_of(companions: Iterable[Companion[H]]) -> tuple[ModelFile, ...]:
    """The NodeSet files ``companions`` declare, in their order (``uacell.models.source.official_models``
    orders them for loading)."""
    return tuple(m for c in companions for m in c.models)


def web_views(companions: Iterable[Companion[H]]) -> list[WebView]:
    """What the web HMI shows of ``companions``' parts: their web views, in their order."""
    return [c.web_view for c in companions if c.web_view is not None]
