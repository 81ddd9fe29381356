"""What a PackML unit publishes, and when (decisions 28 and 47), free of OPC UA.

``PackMLUnit`` groups its changes in operations; each change is counted and says what it touched
(``Publishing.change``). When the outermost operation ends, the unit publishes once, and only if
something changed since the last publish: an operation that named what it changed (keys of
``TOUCHABLE``) publishes those and the derived values; ``TIMES`` adds the Admin times and OEE
figures (a whole second passed), ``DURABLE`` the stored values (a save became durable); any other
operation rebuilds and compares every value. Listeners get only the values that differ from what
they were last told.

The stored Admin values are published only once durable (decision 28, ``StoredValues``): a changed
count is handed to the store before it is published, and clients see the stored values.
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable, Iterable
from typing import Any, Protocol

from uacell.packml.accounting import DURABLE_KEYS, DURABLE_TIMES, AdminAccounting
from uacell.packml.admin_store import AdminStore
from uacell.packml.data import Status

log = logging.getLogger(__name__)

TIMES = "times"  # the touched mark of the Admin times and OEE figures (AdminAccounting.account)
DURABLE = "durable"  # the touched mark of the stored values (a save became durable)
_DURABLE_NOT_TIMES = tuple(k for k in DURABLE_KEYS if k not in DURABLE_TIMES)
# A change of the stored times alone (a whole second passed) is stored, and then published, at most this
# often (seconds): the three times pass their whole seconds at different instants.
TIMES_SAVE_PERIOD = 1.0
_MISSING = object()

Listener = Callable[[dict[str, Any]], None]

# The values an operation may name as all it changed (decision 47), each read on its own.
TOUCHABLE: dict[str, Callable[[Status], Any]] = {
    "Status/MachSpeed": lambda s: s.mach_speed,
    "Status/Parameter": lambda s: list(s.parameter),
    "Status/RemoteParameter": lambda s: list(s.remote_parameter),
    "Status/Product": lambda s: list(s.product),
}


def derived(s: Status) -> dict[str, Any]:
    """The Status values the unit derives from the states and the speed (decision 29)."""
    return {
        "Status/StateRequested": s.state_requested,
        "Status/StateChangeInProcess": s.state_change_in_process,
        "Status/CurMachSpeed": s.cur_mach_speed,
    }


class Published(Protocol):
    """What ``Publishing`` reads the values from (a ``PackMLUnit``)."""

    status: Status
    accounting: AdminAccounting

    def values(self) -> dict[str, Any]: ...

    def oee_values(self) -> dict[str, float | int]: ...


class Publishing:
    """The publish bookkeeping of one unit: changes counted, what they touched, what listeners were
    last told. ``everything`` publishes as before decision 47: every value rebuilt and compared."""

    def __init__(self, name: str) -> None:
        self.name = name
        self.listeners: list[Listener] = []
        self.everything = False
        self._changes = 0
        self._published = -1  # the count of changes at the last publish
        self._touched: set[str] | None = None  # what changed since the last publish (None: anything)
        self._last: dict[str, Any] = {}

    def start(self, values: dict[str, Any]) -> None:
        """What listeners are taken to know to begin with (what they read)."""
        self._last = values

    def change(self, touched: Iterable[str] | None = None) -> None:
        """A change that may alter published values: ``touched`` names them, None means any."""
        self._changes += 1
        if touched is None or self.everything:  # ``touch``, inline: every operation passes here
            self._touched = None
        elif self._touched is not None:
            self._touched.update(touched)

    @property
    def due(self) -> bool:
        """Did anything change since the last publish?"""
        return self._changes != self._published

    def select(self, unit: Published, final: bool) -> dict[str, Any]:
        """The values to compare now; a ``final`` publish (outside any operation) takes the marks,
        one inside an operation (SetUnitMode's request) leaves them for the final one."""
        touched = self._touched
        if final:
            self._touched = set()
        if touched is None:
            return unit.values()
        values = derived(unit.status)
        for key in touched:
            if key in TOUCHABLE:
                values[key] = TOUCHABLE[key](unit.status)
        if TIMES in touched:
            durable = unit.accounting.durable()
            values.update({k: durable[k] for k in DURABLE_TIMES})
            values.update(unit.accounting.times())
            values.update(unit.oee_values())
        if DURABLE in touched:
            values.update(unit.accounting.durable())
        return values

    def emit(self, values: dict[str, Any], final: bool) -> None:
        """Tell the listeners the ``values`` that differ from what they were last told."""
        if final:
            self._published = self._changes
        last = self._last
        changed = {k: v for k, v in values.items() if last.get(k, _MISSING) != v}
        last.update(values)
        if not changed:
            return
        for listener in list(self.listeners):
            try:
                listener(changed)
            except Exception:
                log.exception("%s: change listener failed", self.name)


class StoredValues:
    """Decision 28 for one unit: the durable Admin values are handed to the ``store`` (if any) before
    they are published, and clients see them as stored. The store tells once the data is durable (at
    once, or later from a writer thread). Failures are logged once, and retried at the next change."""

    def __init__(
        self, name: str, store: AdminStore | None, clock: Callable[[], float], *, since: float | None = None
    ) -> None:
        self.name = name
        self.store = store
        self._clock = clock
        self.last_save = clock() if since is None else since
        self.saved: dict[str, Any] = {}  # the durable values as last stored: what clients may see
        self.submitted: dict[str, Any] | None = None  # the durable values last handed to the store
        self.times_due = False  # stored times changed, to be saved at a tick (TIMES_SAVE_PERIOD)
        self.publishing = False  # a save made by a publish (its own publish follows)
        self._failing = False

    def start(self, durable: dict[str, Any]) -> None:
        """What was loaded from the store: what clients will first see."""
        self.saved = self.submitted = durable

    def submit(
        self,
        durable: dict[str, Any],
        data: Callable[[], dict[str, Any]],
        done: Callable[[dict[str, Any], OSError | None], None],
    ) -> None:
        """Hand ``data()`` (what the store keeps) to the store; ``done(durable, error)`` once durable."""
        self.last_save = self._clock()
        self.times_due = False
        if self.store is None:
            return
        self.submitted = durable
        self.store.submit(data(), functools.partial(done, durable))

    def stored(self, durable: dict[str, Any], error: OSError | None) -> bool:
        """The store's answer for ``durable``; True if clients may now see other values."""
        if error is not None:
            # Retried at the next change of a stored value: log the failure once, not at every try. A
            # failing disk does not freeze the values clients see.
            if not self._failing:
                log.error("%s: cannot save PackML admin data to %s", self.name, self.path, exc_info=error)
            self._failing = True
        elif self._failing:
            log.warning("%s: PackML admin data saved to %s again", self.name, self.path)
            self._failing = False
        if durable == self.saved:
            return False
        self.saved = durable
        return True

    def settle(self, values: dict[str, Any], save: Callable[[], None]) -> None:
        """Before ``values`` are published: ``save`` if a stored value among them moved (the times
        alone at most every TIMES_SAVE_PERIOD; later at a tick), then show the stored ones."""
        if self.store is None:
            return
        submitted = self.submitted
        moved = [k for k in DURABLE_KEYS if k in values and (submitted is None or values[k] != submitted[k])]
        if moved and DURABLE_TIMES.issuperset(moved) and self._clock() - self.last_save < TIMES_SAVE_PERIOD:
            self.times_due = True  # only time passed: stored at a tick, once a second at most
        elif moved:
            self.publishing = True
            try:
                save()
            finally:
                self.publishing = False
        # clients see the stored values, the newer ones once stored
        values.update({k: v for k, v in self.saved.items() if k in values})

    def next_save(self, save_interval: float) -> float:
        """When (on the unit's clock) ``save_due`` turns True, nothing else changing."""
        return self.last_save + (min(save_interval, TIMES_SAVE_PERIOD) if self.times_due else save_interval)

    def save_due(self, save_interval: float) -> bool:
        """Is a save due at a tick (every ``save_interval``, or stored times waiting)?"""
        since = self._clock() - self.last_save
        return since >= save_interval or (self.times_due and since >= TIMES_SAVE_PERIOD)

    @property
    def storing(self) -> bool:
        """A stored value other than a time (a count, StopReason, AlarmHistory) changed and is not yet
        durable, hence not yet published."""
        submitted = self.submitted
        if self.store is None or submitted is None:
            return False
        saved = self.saved
        return any(submitted[k] != saved[k] for k in _DURABLE_NOT_TIMES)

    @property
    def path(self) -> str:
        return str(self.store.path) if self.store is not None else "(no store)"
