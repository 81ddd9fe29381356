"""DI LockingServices (OPC 10000-100, LockingServicesType) as pure behaviour.

Lockable elements form a tree (``Controller1`` above ``TaskControl1`` and its ``SystemOperation``). A
lock is held by one session. While another session holds a lock on an element or on an ancestor of
it, ``check`` refuses Robotics operation methods there with Bad_ResourceUnavailable (decision 20) and
writes to the element's variables with Bad_Locked (DI LockingServices). A
lock ends on ExitLock, BreakLock, the owner's session closing, or MaxInactiveLockTime without
activity from the owner. Expiry is computed lazily from an injected clock; the server may also call
``expire()`` periodically so the published ``Locked`` variables follow promptly.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Hashable, Iterator
from dataclasses import dataclass

from uacell.core.errors import CallError

_log = logging.getLogger(__name__)

# Status values of the DI methods' Int32 output arguments (OPC 10000-100, 7.5-7.8).
OK = 0
E_ALREADY_LOCKED = -1  # InitLock: the element (or one above or below it) is already locked
E_INVALID = -2  # InitLock: the element cannot be locked
E_NOT_LOCKED = -1  # RenewLock, ExitLock, BreakLock: the element is not locked

DEFAULT_MAX_INACTIVE = 60.0  # seconds; published as MaxInactiveLockTime in milliseconds


@dataclass(frozen=True)
class LockOwner:
    """Who holds a lock: the session, plus the client's ApplicationUri and user name for display."""

    session: Hashable
    client: str = ""
    user: str = ""


@dataclass(frozen=True)
class LockStatus:
    """What the LockingServices variables of one element show."""

    locked: bool
    locking_client: str
    locking_user: str
    remaining_ms: float


_UNLOCKED = LockStatus(False, "", "", 0.0)


@dataclass
class _Lock:
    owner: LockOwner
    context: str
    deadline: float


class LockManager:
    """The locks of one server over a tree of elements (any hashable keys, e.g. node paths)."""

    def __init__(
        self,
        max_inactive: float = DEFAULT_MAX_INACTIVE,
        *,
        clock: Callable[[], float] = time.monotonic,
        on_change: Callable[[Hashable], None] | None = None,
    ) -> None:
        self.max_inactive = max_inactive
        self._clock = clock
        self._on_change = on_change
        self._parent: dict[Hashable, Hashable | None] = {}
        self._lockable: dict[Hashable, bool] = {}
        self._locks: dict[Hashable, _Lock] = {}

    @property
    def max_inactive_ms(self) -> float:
        """MaxInactiveLockTime as published (Duration, milliseconds)."""
        return self.max_inactive * 1000.0

    # tree ---------------------------------------------------------------------------------------

    def add(self, element: Hashable, parent: Hashable | None = None, *, lockable: bool = True) -> None:
        """Register ``element`` below ``parent``; a non-lockable one is covered by its ancestors' locks."""
        if parent is not None and parent not in self._parent:
            raise KeyError(f"unknown parent element {parent!r}")
        self._parent[element] = parent
        self._lockable[element] = lockable

    def __contains__(self, element: object) -> bool:
        return element in self._parent

    def _lineage(self, element: Hashable) -> Iterator[Hashable]:
        """The element itself, then its ancestors up to the root."""
        if element not in self._parent:
            raise KeyError(f"unknown element {element!r}")
        node: Hashable | None = element
        while node is not None:
            yield node
            node = self._parent[node]

    def _descendants(self, element: Hashable) -> list[Hashable]:
        return [e for e in self._parent if e != element and element in self._lineage(e)]

    # locks --------------------------------------------------------------------------------------

    def _live(self, element: Hashable) -> _Lock | None:
        lock = self._locks.get(element)
        if lock is not None and self._clock() >= lock.deadline:
            _log.info(
                "lock on %s held by %s expired after %.1f s of inactivity",
                element,
                _describe(lock.owner),
                self.max_inactive,
            )
            self._drop(element)
            return None
        return lock

    def _drop(self, element: Hashable) -> None:
        del self._locks[element]
        self._changed(element)

    def _changed(self, element: Hashable) -> None:
        if self._on_change is not None:
            self._on_change(element)

    def holder(self, element: Hashable) -> LockOwner | None:
        """Who holds the lock on ``element`` itself, if anyone."""
        lock = self._live(element)
        return lock.owner if lock else None

    def status(self, element: Hashable) -> LockStatus:
        """The values of Locked, LockingClient, LockingUser and RemainingLockTime for ``element``."""
        lock = self._live(element)
        if lock is None:
            return _UNLOCKED
        remaining = max(0.0, lock.deadline - self._clock()) * 1000.0
        return LockStatus(True, lock.owner.client, lock.owner.user, remaining)

    def init_lock(self, element: Hashable, owner: LockOwner, context: str = "") -> int:
        """InitLock: OK, E_ALREADY_LOCKED (here, above or below, by anyone), or E_INVALID."""
        lineage = list(self._lineage(element))
        if not self._lockable[element]:
            return E_INVALID
        if self._live(element) is not None:
            return E_ALREADY_LOCKED
        for other in lineage[1:] + self._descendants(element):
            lock = self._live(other)
            if lock is not None and lock.owner.session != owner.session:
                return E_ALREADY_LOCKED
        self._locks[element] = _Lock(owner, context, self._clock() + self.max_inactive)
        _log.info("%s locked %s (context %r)", _describe(owner), element, context)
        self._changed(element)
        return OK

    def renew_lock(self, element: Hashable, session: Hashable) -> int:
        """RenewLock: restart the inactivity timer. Another session's lock is refused."""
        lock = self._owned(element, session, "RenewLock")
        if lock is None:
            return E_NOT_LOCKED
        lock.deadline = self._clock() + self.max_inactive
        self._changed(element)
        return OK

    def exit_lock(self, element: Hashable, session: Hashable) -> int:
        """ExitLock: release the caller's own lock. Another session's lock is refused."""
        if self._owned(element, session, "ExitLock") is None:
            return E_NOT_LOCKED
        _log.info("lock on %s released by its owner", element)
        self._drop(element)
        return OK

    def break_lock(self, element: Hashable, by: str = "") -> int:
        """BreakLock: remove whoever's lock is on ``element`` (the role check is the dispatcher's)."""
        lock = self._live(element)
        if lock is None:
            return E_NOT_LOCKED
        _log.warning("lock on %s held by %s broken by %s", element, _describe(lock.owner), by or "a client")
        self._drop(element)
        return OK

    def _owned(self, element: Hashable, session: Hashable, method: str) -> _Lock | None:
        self._lineage(element)  # KeyError for unknown elements
        lock = self._live(element)
        if lock is not None and lock.owner.session != session:
            # DI lets only the lock's initiator call this; E_NotLocked would be untrue here.
            raise CallError("BadUserAccessDenied", f"{method}: the lock on {element} is held by another session")
        return lock

    def session_closed(self, session: Hashable) -> list[Hashable]:
        """Release every lock the closed (or timed-out) session held; returns the elements freed."""
        freed = [e for e, lock in self._locks.items() if lock.owner.session == session]
        for element in freed:
            _log.info("lock on %s released: its session closed", element)
            self._drop(element)
        return freed

    def expire(self) -> list[Hashable]:
        """Drop locks past MaxInactiveLockTime; returns the elements freed (call periodically)."""
        now = self._clock()
        stale = [e for e, lock in self._locks.items() if now >= lock.deadline]
        for element in stale:
            self._live(element)
        return stale

    def locked_elements(self) -> list[Hashable]:
        """Elements that currently carry a lock (for refreshing RemainingLockTime)."""
        return [e for e in list(self._locks) if self._live(e) is not None]

    # enforcement --------------------------------------------------------------------------------

    def blocked_for(self, element: Hashable, session: Hashable) -> bool:
        """True when another session holds a lock on ``element`` or on an ancestor of it."""
        for node in self._lineage(element):
            lock = self._live(node)
            if lock is not None and lock.owner.session != session:
                return True
        return False

    def check(self, element: Hashable, session: Hashable, status: str = "BadResourceUnavailable") -> None:
        """Refuse with ``status`` (Robotics methods: Bad_ResourceUnavailable; writes: DI's Bad_Locked)
        when blocked; a request by the owner renews its locks."""
        for node in self._lineage(element):
            lock = self._live(node)
            if lock is None:
                continue
            if lock.owner.session != session:
                raise CallError(status, f"{element} is locked by {_describe(lock.owner)} (lock on {node})")
            # DI: a request by the initiator for the locked element restarts the lock timer.
            lock.deadline = self._clock() + self.max_inactive


def _describe(owner: LockOwner) -> str:
    who = owner.user or "anonymous"
    return f"{who} ({owner.client})" if owner.client else who
