"""A pure finite state machine over a table read from the NodeSet.

It knows states, transitions and sub-state machines (a sub-machine is active only while its parent
is in the hosting state), and tells listeners about every change. It knows nothing of OPC UA: the
binding in ``uacell.binding.machine_binding`` listens and publishes. Domain rules (which command is allowed
when) live in ``robotics.model`` and ``packml.model``, which drive these machines.
"""

from __future__ import annotations

from collections.abc import Callable, Collection
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import IntEnum

from uacell.models.tables import FsmTable, TransitionInfo


class Reason(IntEnum):
    """Robotics LastTransitionReason values (docs/decisions.md, 21); PackML machines ignore them."""

    UNKNOWN = 0
    EXTERNAL = 1
    DIRECT = 2
    SYSTEM = 3
    ERROR = 4
    APPLICATION = 5


@dataclass(frozen=True)
class Change:
    """One change of a machine: a transition taken, or a state entered without one."""

    machine: StateMachine
    transition: TransitionInfo | None
    from_state: str | None
    to_state: str
    reason: Reason
    time: datetime


Listener = Callable[[Change], None]


class StateMachine:
    def __init__(
        self,
        name: str,
        table: FsmTable,
        initial: str,
        *,
        parent: StateMachine | None = None,
        parent_state: str | None = None,
    ) -> None:
        if initial not in table.states:
            raise ValueError(f"{table.type_name} has no state {initial!r}")
        self.name = name
        self.table = table
        self.current = initial
        self.last_transition: TransitionInfo | None = None
        self.last_transition_time: datetime | None = None
        self.last_reason = Reason.UNKNOWN
        self.parent = parent
        self.parent_state = parent_state
        self.children: list[StateMachine] = []
        self.listeners: list[Listener] = []
        # the current state is the last one known, not live (equipment behind a PLC that cannot be reached)
        self.stale = False
        if parent is not None:
            if parent_state not in parent.table.states:
                raise ValueError(f"{parent.table.type_name} has no state {parent_state!r}")
            parent.children.append(self)

    def __repr__(self) -> str:
        return f"<StateMachine {self.name} {self.current}{'' if self.active else ' (inactive)'}>"

    @property
    def active(self) -> bool:
        """A sub-state machine is active only while its parent is active and in the hosting state."""
        p = self.parent
        return p is None or (p.active and p.current == self.parent_state)

    def hosted(self) -> StateMachine | None:
        """The sub-machine the current state hosts (the first, if several): of an active machine, the
        active sub-machine; ``active`` without asking every parent again."""
        for child in self.children:
            if child.parent_state == self.current:
                return child
        return None

    def is_in(self, *states: str) -> bool:
        return self.active and self.current in states

    def allows(self, method: str, stays: Collection[tuple[str, str]] = ()) -> bool:
        """The one guard every model starts from: the machine is active, and ``method`` causes a
        transition from the current state (the NodeSet's HasCause) or is declared in ``stays`` as
        acting there without one (``(method, state)`` pairs)."""
        if not self.active:
            return False
        return self.table.caused_by(method, self.current) is not None or (method, self.current) in stays

    def take(self, transition: str, reason: Reason = Reason.EXTERNAL) -> Change:
        """Take ``transition`` (a name from the table); it must start at the current state."""
        t = self.table.transitions[transition]
        if t.from_state != self.current:
            raise RuntimeError(f"{self.name}: {transition} does not start at {self.current}")
        self.last_transition = t
        self.last_transition_time = datetime.now(UTC)
        self.last_reason = reason
        self.current = t.to_state
        return self._notify(Change(self, t, t.from_state, t.to_state, reason, self.last_transition_time))

    def move(self, to_state: str, reason: Reason = Reason.EXTERNAL) -> Change:
        """Take the (unique) transition from the current state to ``to_state``."""
        return self.take(self.table.between(self.current, to_state).name, reason)

    def enter(self, state: str, reason: Reason = Reason.SYSTEM) -> Change:
        """Set the state without a transition: a sub-machine's state on entering its parent state."""
        if state not in self.table.states:
            raise ValueError(f"{self.table.type_name} has no state {state!r}")
        previous, self.current = self.current, state
        return self._notify(Change(self, None, previous, state, reason, datetime.now(UTC)))

    def set_stale(self, stale: bool) -> None:
        """Mark the current state as the last known one (``stale``) or live again; listeners are told
        (a change without a transition, to the same state) so the state is shown with its quality."""
        if stale != self.stale:
            self.stale = stale
            self._notify(Change(self, None, self.current, self.current, self.last_reason, datetime.now(UTC)))

    def _notify(self, change: Change) -> Change:
        for listener in list(self.listeners):
            listener(change)
        return change

    def walk(self) -> list[StateMachine]:
        """This machine and all its sub-machines, parents first."""
        out = [self]
        for child in self.children:
            out.extend(child.walk())
        return out
