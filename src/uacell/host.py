"""What the server's cross-cutting parts receive: a narrow, read-only view of the server.

Security, diagnostics, metrics and the audit observers are wired by ``uacell.server`` and see it
only as a ``Host``: the asyncua server, the configuration, the cell, the method dispatcher and write
router, users, the audit trail, the listening policy and the diagnostics hooks. A companion's binder
sees a ``BinderHost``: not the asyncua server but the address-space operations of
``uacell.binding.space.Space``, plus registries, the publisher and the state tables. Neither imports
``uacell.server`` (which imports them), so the server's assembly stays at the top of the imports.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol, TypeVar

from asyncua import Server, ua

from uacell.binding.cell import CellBuilder
from uacell.binding.dispatch import MethodDispatcher
from uacell.binding.machine_binding import NodeRefs
from uacell.binding.publisher import Publisher
from uacell.binding.space import Space
from uacell.binding.writes import WriteRouter
from uacell.config import Config
from uacell.core.companion import Companion
from uacell.core.file_store import HandlePool
from uacell.core.registry import Registry, RegistryKey
from uacell.core.roles import ListeningPolicy
from uacell.models.tables import StateTables
from uacell.security.audit import AuditTrail
from uacell.security.users import UserStore

T = TypeVar("T")


class SessionHooks(Protocol):
    """What session handling tells the server's diagnostics (``uacell.services.diagnostics.Diagnostics``)."""

    def session_created(self, session: Any, params: ua.CreateSessionParameters, processor: Any) -> None: ...

    def session_closed(self, session: Any) -> None: ...


class _Shared(Protocol):
    """What the server's parts and the binders both see."""

    @property
    def config(self) -> Config: ...

    @property
    def data_dir(self) -> Path: ...

    @property
    def cell(self) -> CellBuilder: ...

    @property
    def dispatcher(self) -> MethodDispatcher: ...

    @property
    def writes(self) -> WriteRouter: ...

    @property
    def audit(self) -> AuditTrail: ...


class Host(_Shared, Protocol):
    """The server as its parts see it (``uacell.server.UacellServer`` is one)."""

    @property
    def server(self) -> Server: ...

    @property
    def users(self) -> UserStore: ...

    @property
    def policy(self) -> ListeningPolicy: ...

    @property
    def diagnostics(self) -> SessionHooks | None: ...


class SessionEvents(Protocol):
    """Who is told when a client session ends (``security.Security``)."""

    @property
    def on_session_closed(self) -> list[Callable[[Any], None]]: ...


class ChannelGuard(SessionEvents, Protocol):
    """Session ends, and the secure channels checked again when the trust list changed
    (``security.Security``), who is then told of it (``on_trust_changed``, also after changes made
    out of band: decision 100)."""

    def recheck_channels(self) -> list[str]: ...

    @property
    def on_trust_changed(self) -> list[Callable[[], None]]: ...


class ConfigurationHost(Host, Protocol):
    """What the server's own configuration objects (``uacell.security.push``) need besides ``Host``:
    the ordered publisher for values that change between calls, session ends and the channel guard."""

    @property
    def publisher(self) -> Publisher: ...

    @property
    def security(self) -> ChannelGuard: ...


class BinderHost(_Shared, Protocol):
    """All a companion's binder receives (``Companion.binder``): the address-space operations it needs
    (``space``; never the asyncua server itself), the configuration and the built cell, the method
    dispatcher and write router, the audit trail, the registries its parts go in, the ordered
    publisher, the state tables and namespaces, file handles and session ends."""

    @property
    def space(self) -> Space: ...

    @property
    def publisher(self) -> Publisher: ...

    @property
    def refs(self) -> NodeRefs: ...

    @property
    def tables(self) -> StateTables: ...

    @property
    def model_indexes(self) -> dict[str, int]: ...

    @property
    def file_handles(self) -> HandlePool: ...

    @property
    def security(self) -> SessionEvents: ...

    @property
    def companions(self) -> tuple[Companion[ServerView], ...]:
        """The companions this server serves (their lock rules, DataSets, ...)."""
        ...

    def registry(self, key: RegistryKey[T]) -> Registry[T]: ...

    async def settle(self) -> None: ...


class ServerView(Host, BinderHost, Protocol):
    """The server as a companion's functions receive it (``Companion[ServerView]``): its binder (which
    should use the ``BinderHost`` part only) and its metrics factory (the ``Host`` part)."""
