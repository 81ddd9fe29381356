"""DI LockingServices on the cell's Controllers and TaskControls, and the lock guard of decision 20.

Every Controller part and the TaskControl parts below it form the tree of ``uacell.locking``, keyed
by their object NodeIds (``BuiltPart.node``); a Controller's SystemOperation object is a non-lockable
element below it. The Robotics binder passes ``element=<TaskControl or Controller NodeId>`` (the
SystemOperation NodeId works too) to ``dispatcher.bind``; the guard refuses TaskControl and
SystemOperation methods there with Bad_ResourceUnavailable while another session holds a lock on
the element or its Controller. The write guard refuses, with DI's Bad_Locked, every write to a node
below a locked element (found by walking the hierarchy up from the written node) by another session.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
from collections.abc import Awaitable, Callable, Hashable
from typing import TYPE_CHECKING

from asyncua import ua

from uacell.errors import CallError
from uacell.locking import LockManager, LockOwner
from uacell.roles import Family
from uacell.ua.context import Caller, caller_of
from uacell.ua.dispatch import BoundMethod

if TYPE_CHECKING:
    from asyncua.server.internal_session import InternalSession

    from uacell.server import UacellServer

log = logging.getLogger(__name__)

DI = "http://opcfoundation.org/UA/DI/"
_MAX_INACTIVE_LOCK_TIME = 6387  # DI: ServerCapabilities/MaxInactiveLockTime
TICK = 0.5  # seconds between expiry checks and RemainingLockTime updates
_GUARDED = (Family.TASK_CONTROL, Family.SYSTEM_OPERATION)
# Child references followed upwards from a written node to the lockable element above it.
_CHILD_REFS = {
    ua.NodeId(i)
    for i in (ua.ObjectIds.HasComponent, ua.ObjectIds.HasProperty, ua.ObjectIds.HasOrderedComponent,
              ua.ObjectIds.Organizes)
}
_MAX_DEPTH = 32


class LockBinding:
    """The LockManager of one server and the Lock objects that show it."""

    def __init__(self, app: UacellServer, manager: LockManager | None = None) -> None:
        self.app = app
        self.manager = manager or LockManager(on_change=self._changed)
        if manager is not None:
            manager._on_change = self._changed
        self.lock_nodes: dict[Hashable, ua.NodeId] = {}  # element -> its Lock object
        self._task: asyncio.Task[None] | None = None

    # tree -------------------------------------------------------------------------------------------

    def _lock_child(self, node: ua.NodeId) -> ua.NodeId | None:
        try:
            return self.app.cell.child(node, "Lock")
        except KeyError:
            return None

    def build_tree(self) -> None:
        cell = self.app.cell
        task_controls = cell.by_role("task_control")
        for ctrl in cell.by_role("controller"):
            self._add(ctrl.node, None)
            with contextlib.suppress(KeyError):
                self.manager.add(cell.child(ctrl.node, "SystemOperation"), ctrl.node, lockable=False)
            for tc in task_controls:
                if tc.path.startswith(ctrl.path + "."):
                    self._add(tc.node, ctrl.node)

    def _add(self, node: ua.NodeId, parent: ua.NodeId | None) -> None:
        lock = self._lock_child(node)
        self.manager.add(node, parent, lockable=lock is not None)
        if lock is not None:
            self.lock_nodes[node] = lock

    # methods ----------------------------------------------------------------------------------------

    def bind_methods(self) -> None:
        d = self.app.dispatcher
        for element, lock in self.lock_nodes.items():
            handlers = self._handlers(element)
            for name, handler in handlers.items():
                d.bind(lock, d.method_of(lock, name), Family.LOCKING, handler, element=element)

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
        """Decision 20: Robotics operation methods are refused while another session holds a lock."""
        if bound.family in _GUARDED and bound.element is not None and bound.element in self.manager:
            self.manager.check(bound.element, caller.session_id)

    def element_of(self, node: ua.NodeId) -> Hashable | None:
        """The nearest lockable-tree element at or above ``node`` (through child references), if any."""
        aspace = self.app.server.iserver.aspace
        level, seen = [node], {node}
        for _ in range(_MAX_DEPTH):
            if not level:
                return None
            for current in level:
                if current in self.manager:
                    return current
            parents = []
            for current in level:
                data = aspace.get(current)
                for ref in data.references if data is not None else ():
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
        values = (
            ("Locked", status.locked, ua.VariantType.Boolean),
            ("LockingClient", status.locking_client, ua.VariantType.String),
            ("LockingUser", status.locking_user, ua.VariantType.String),
            ("RemainingLockTime", status.remaining_ms, ua.VariantType.Double),
        )
        for name, value, vtype in values:
            node = ua.NodeId(f"{lock.Identifier}.{name}", lock.NamespaceIndex)
            await self.app.server.write_attribute_value(node, ua.DataValue(ua.Variant(value, vtype)))

    async def publish_all(self) -> None:
        for element in self.lock_nodes:
            await self.publish(element)
        try:
            di = await self.app.server.get_namespace_index(DI)
        except ValueError:
            return
        node = ua.NodeId(_MAX_INACTIVE_LOCK_TIME, di)
        if node in self.app.server.iserver.aspace:
            dv = ua.DataValue(ua.Variant(self.manager.max_inactive_ms, ua.VariantType.Double))
            await self.app.server.write_attribute_value(node, dv)

    async def _tick(self) -> None:
        # Expiry is lazy in LockManager; this loop makes Locked and RemainingLockTime follow promptly.
        while True:
            await asyncio.sleep(TICK)
            try:
                self.manager.expire()
                for element in self.manager.locked_elements():
                    if element in self.lock_nodes:
                        self.app.publisher.submit(lambda e=element: self.publish(e))
            except Exception:
                log.exception("lock expiry check failed")

    def start(self) -> None:
        self._task = asyncio.get_running_loop().create_task(self._tick())

    async def close(self) -> None:
        if self._task is not None:
            self._task.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._task


async def bind_locks(app: UacellServer) -> Callable[[], Awaitable[None]]:
    """Binder: LockingServices on every Controller and TaskControl of the cell."""
    binding = LockBinding(app)
    binding.build_tree()
    binding.bind_methods()
    app.dispatcher.guards.append(binding.guard)
    app.writes.guards.append(binding.write_guard)
    app.security.on_session_closed.append(binding.session_closed)
    await binding.publish_all()
    binding.start()
    app.locks = binding  # type: ignore[attr-defined]
    return binding.close
