"""DI LockingServices on the parts the companions name, and the lock guard (docs/decisions.md 20).

Each companion says which parts carry a Lock (``Companion.locks``: a part role, the role of the
part above it, non-lockable members guarded with it) and which method families a lock guards
(``Companion.lock_guarded``). Those parts form the tree of ``uacell.di.locking``, keyed by their object
NodeIds (``BuiltPart.node``). A binder passes ``element=<part NodeId>`` to ``dispatcher.bind``; the
guard refuses guarded methods there with Bad_ResourceUnavailable while another session holds a lock
on the element or a part above it. For Robotics: Controllers, the TaskControls below them, and each
Controller's SystemOperation as a member. The write guard refuses, with DI's Bad_Locked, every write
to a node below a locked element (found by walking the hierarchy up from the written node) by another
session.
"""

from __future__ import annotations

import asyncio
import contextlib
import functools
import logging
from collections.abc import Awaitable, Callable, Hashable
from typing import TYPE_CHECKING

from asyncua import ua

from uacell.binding.dispatch import BoundMethod
from uacell.core.background import Background
from uacell.core.errors import CallError
from uacell.core.registry import RegistryKey
from uacell.core.roles import Family
from uacell.di.companion import LOCKING
from uacell.di.locking import LockManager, LockOwner
from uacell.ua.context import Caller, caller_of

if TYPE_CHECKING:
    from asyncua.server.internal_session import InternalSession

    from uacell.host import BinderHost

log = logging.getLogger(__name__)

DI = "http://opcfoundation.org/UA/DI/"
_MAX_INACTIVE_LOCK_TIME = 6387  # DI: ServerCapabilities/MaxInactiveLockTime
TICK = 0.5  # seconds between expiry checks and RemainingLockTime updates
_LOCK_VARIABLES = (
    ("Locked", ua.VariantType.Boolean),
    ("LockingClient", ua.VariantType.String),
    ("LockingUser", ua.VariantType.String),
    ("RemainingLockTime", ua.VariantType.Double),
)
# The one LockBinding of a server, under "" (it is not a part).
LOCK_SERVICE: RegistryKey[LockBinding] = RegistryKey("lock service")
# Every Lock object, keyed by the browse path of the part that carries it.
LOCKS: RegistryKey[ua.NodeId] = RegistryKey("lock")
# Child references followed upwards from a written node to the lockable element above it.
_CHILD_REFS = {
    ua.NodeId(i)
    for i in (
        ua.ObjectIds.HasComponent,
        ua.ObjectIds.HasProperty,
        ua.ObjectIds.HasOrderedComponent,
        ua.ObjectIds.Organizes,
    )
}
_MAX_DEPTH = 32


class LockBinding:
    """The LockManager of one server and the Lock objects that show it."""

    def __init__(self, app: BinderHost, manager: LockManager | None = None) -> None:
        self.app = app
        self.manager = manager or LockManager(on_change=self._changed)
        if manager is not None:
            manager._on_change = self._changed
        self.lock_nodes: dict[Hashable, ua.NodeId] = {}  # element -> its Lock object
        self.guarded: frozenset[Family] = frozenset().union(*(c.lock_guarded for c in app.companions))
        self.values = app.space.value_writer(app.dispatcher.types.builtin_of)
        self._background = Background()

    # tree -------------------------------------------------------------------------------------------

    def build_tree(self) -> None:
        """The companions' lock rules, in order: a rule's parents come from an earlier rule."""
        cell = self.app.cell
        for rule in (r for c in self.app.companions for r in c.locks):
            parents = cell.by_role(rule.parent_role) if rule.parent_role else []
            for part in cell.by_role(rule.role):
                above = [p for p in parents if part.path.startswith(p.path + ".")]
                if rule.parent_role and not above:
                    continue
                self._add(part.node, part.path, above[0].node if above else None)
                for member in rule.members:
                    with contextlib.suppress(KeyError):
                        self.manager.add(cell.child(part.node, member), part.node, lockable=False)

    def _add(self, node: ua.NodeId, path: str, parent: ua.NodeId | None) -> None:
        lock = self.app.space.find_child(node, "Lock")
        self.manager.add(node, parent, lockable=lock is not None)
        if lock is not None:
            self.lock_nodes[node] = lock
            self.app.registry(LOCKS).add(path, lock)

    # methods ----------------------------------------------------------------------------------------

    def bind_methods(self) -> None:
        d = self.app.dispatcher
        for element, lock in self.lock_nodes.items():
            handlers = self._handlers(element)
            for name, handler in handlers.items():
                d.bind(lock, d.method_of(lock, name), LOCKING, handler, element=element)

    def _handlers(self, element: Hashable) -> dict[str, Callable[..., Awaitable[list[int]]]]:
        m = self.manager

        async def init_lock(caller: Caller, context: str) -> list[int]:
            owner = LockOwner(caller.session_id, caller.client, caller.user or "")
            return [m.init_lock(element, owner, context or "")]

        async def renew_lock(caller: Caller) -> list[int]:
            return [m.renew_lock(element, caller.session_id)]

        async def exit_lock(caller: Caller) -> list[int]:
            return [m.exit_lock(element, caller.session_id)]

        async def break_lock(caller: Caller) -> list[int]:
            return [m.break_lock(element, by=caller.display_user)]

        return {"InitLock": init_lock, "RenewLock": renew_lock, "ExitLock": exit_lock, "BreakLock": break_lock}

    def guard(self, caller: Caller, bound: BoundMethod) -> None:
        """Decision 20: guarded methods are refused while another session holds a lock."""
        if bound.family in self.guarded and bound.element is not None and bound.element in self.manager:
            self.manager.check(bound.element, caller.session_id)

    def element_of(self, node: ua.NodeId) -> Hashable | None:
        """The nearest lockable-tree element at or above ``node`` (through child references), if any."""
        space = self.app.space
        level: list[ua.NodeId] = [node]
        seen = {node}
        for _ in range(_MAX_DEPTH):
            if not level:
                return None
            for current in level:
                if current in self.manager:
                    found: Hashable = current
                    return found
            parents: list[ua.NodeId] = []
            for current in level:
                for ref in space.references(current):
                    if not ref.IsForward and ref.ReferenceTypeId in _CHILD_REFS and ref.NodeId not in seen:
                        seen.add(ref.NodeId)
                        parents.append(ref.NodeId)
            level = parents
        return None

    def write_guard(self, caller: Caller, item: ua.WriteValue) -> ua.StatusCode | None:
        """DI LockingServices: writes below an element another session has locked answer Bad_Locked."""
        element = self.element_of(item.NodeId)
        if element is None:
            return None
        try:
            self.manager.check(element, caller.session_id, status="BadLocked")
        except CallError as refused:
            log.info("write of %s refused for %s: %s", item.NodeId.to_string(), caller.display_user, refused.message)
            return ua.StatusCode(getattr(ua.StatusCodes, refused.status))
        return None

    def session_closed(self, session: InternalSession) -> None:
        self.manager.session_closed(caller_of(session).session_id)

    # variables --------------------------------------------------------------------------------------

    def _changed(self, element: Hashable) -> None:
        if element in self.lock_nodes:
            self.app.publisher.submit(lambda: self.publish(element))

    async def publish(self, element: Hashable) -> None:
        lock = self.lock_nodes[element]
        status = self.manager.status(element)
        values = (status.locked, status.locking_client, status.locking_user, status.remaining_ms)
        for (name, vtype), value in zip(_LOCK_VARIABLES, values, strict=True):
            node = ua.NodeId(f"{lock.Identifier}.{name}", lock.NamespaceIndex)
            await self.values.write(node, value, vtype, force=True)

    async def publish_all(self) -> None:
        for element in self.lock_nodes:
            await self.publish(element)
        try:
            di = await self.app.space.namespace_index(DI)
        except ValueError:
            return
        node = ua.NodeId(_MAX_INACTIVE_LOCK_TIME, di)
        if node in self.app.space:
            await self.values.write(node, self.manager.max_inactive_ms, ua.VariantType.Double, force=True)

    async def _tick(self) -> None:
        # Expiry is lazy in LockManager; this loop makes Locked and RemainingLockTime follow promptly.
        while True:
            await asyncio.sleep(TICK)
            try:
                self.manager.expire()
                for element in self.manager.locked_elements():
                    if element in self.lock_nodes:
                        self.app.publisher.submit(functools.partial(self.publish, element))
            except Exception:
                log.exception("lock expiry check failed")

    def start(self) -> None:
        self._background.spawn(self._tick(), name="lock-expiry")

    async def close(self) -> None:
        await self._background.close()


async def bind_locks(app: BinderHost) -> Callable[[], Awaitable[None]]:
    """Binder: LockingServices on every part a companion's lock rules name."""
    binding = LockBinding(app)
    app.registry(LOCK_SERVICE).add("", binding)
    binding.build_tree()
    binding.bind_methods()
    app.dispatcher.guards.append(binding.guard)
    app.writes.guards.append(binding.write_guard)
    app.security.on_session_closed.append(binding.session_closed)
    await binding.publish_all()
    binding.start()
    return binding.close
