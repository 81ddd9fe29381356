"""The pure ISA-TR88 / OPC 30050 PackML unit: three nested state machines, unit modes, Status, Admin.

The transitions are the NodeSet's (``PackMLTables``, handed in by the caller); this module adds only
what the tables cannot say: which sub-state a machine is entered at (decision 23), when the unit mode
disables a command (decision 26), the rules of the unit methods, and the Status/Admin bookkeeping (decisions 28, 29).
Every public operation either succeeds or raises ``CallError`` having changed nothing (decision 22).

The unit is split along its responsibilities: the rules and tables (``packml.rules``, re-exported
here, with the one table of ISA-TR88 command numbers, ``TR88_COMMANDS``), its values as data
(``packml.data``), what it shows (``packml.unit_view``), what its equipment reports
(``packml.equipment_side``), its own methods (``packml.unit_methods``), the Admin accounting
(``packml.accounting``) and what it publishes when (``packml.publishing``).
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import logging
import time
from collections.abc import Callable, Iterable, Iterator, Sequence
from datetime import UTC, datetime
from datetime import time as dt_time
from typing import Any

from uacell.core.capabilities import has
from uacell.core.conditions import ConditionSet
from uacell.core.errors import CallError
from uacell.core.fsm import Reason, StateMachine
from uacell.models.tables import TransitionInfo
from uacell.packml.accounting import DURABLE_KEYS, DURABLE_TIMES, AdminAccounting
from uacell.packml.admin_store import AdminStore
from uacell.packml.data import INT32_WRAP, PACKAGES, STATE_COLUMNS, Admin, Status
from uacell.packml.equipment import EquipmentBase, NamedConditions, PackMLEquipment, PollHint
from uacell.packml.equipment_side import EquipmentSide
from uacell.packml.oee import OEE
from uacell.packml.publishing import (
    DURABLE,
    TIMES,
    TIMES_SAVE_PERIOD,
    TOUCHABLE,
    Listener,
    Publishing,
    StoredValues,
)
from uacell.packml.rules import (
    BASE,
    COMPLETE,
    ENTRY_STATE,
    EXECUTE,
    JOB_STATES,
    MACHINE,
    MODE_DISABLED,
    SET_UNIT_MODE_STATES,
    STOP_COMMAND_IDS,
    TR88_COMMANDS,
    UNIT,
    UNIT_METHODS,
    Mode,
    PackMLTables,
    hosting,
    path,
)
from uacell.packml.types import (
    PackMLAlarmDataType,
    PackMLCountDataType,
    PackMLDescriptorDataType,
    validate_descriptors,
)
from uacell.packml.unit_methods import UnitMethods
from uacell.packml.unit_view import UnitView

__all__ = [  # what other modules import from here, wherever it is defined
    "BASE", "COMPLETE", "DURABLE", "DURABLE_KEYS", "DURABLE_TIMES", "ENTRY_STATE", "EXECUTE", "INT32_WRAP",
    "JOB_STATES", "MACHINE", "MODE_DISABLED", "PACKAGES", "SET_UNIT_MODE_STATES", "STATE_COLUMNS",
    "STOP_COMMAND_IDS", "TIMES", "TIMES_SAVE_PERIOD", "TOUCHABLE", "TR88_COMMANDS", "UNIT", "UNIT_METHODS",
    "Admin", "Listener", "Mode", "PackMLTables", "PackMLUnit", "Status", "path", "run_units",
]  # fmt: skip

log = logging.getLogger(__name__)

TICK_GROUP = 10  # run_units lets the event loop run other work after every this many units
# The unit's own methods (PackMLBaseObjectType), by the model method that answers each.
_UNIT_METHODS = {
    "SetUnitMode": "set_unit_mode",
    "SetMachSpeed": "set_mach_speed",
    "SetProduct": "set_product",
    "SetParameter": "set_parameter",
    "RemoteCommand": "remote_command",
    "SetInterlock": "set_interlock",
}


class PackMLUnit(UnitView, EquipmentSide, UnitMethods):
    """One PackML unit (an instance of PackMLBaseObjectType), free of OPC UA: its state rules. What it
    shows is ``UnitView``, what its equipment reports ``EquipmentSide``, its own methods
    ``UnitMethods``; the Admin accounting is ``accounting``, what is published when ``publishing``
    and ``saving`` (decisions 28, 47)."""

    def __init__(
        self,
        equipment: PackMLEquipment | None = None,
        *,
        tables: PackMLTables,
        name: str = "Filler1",
        store: AdminStore | None = None,
        mach_speed: float = 100.0,
        mach_speed_range: tuple[float, float] = (0.0, 600.0),
        mach_design_speed: float = 120.0,
        supported_modes: Iterable[int] = (Mode.PRODUCE, Mode.MAINTENANCE, Mode.MANUAL),
        initial_mode: int = Mode.PRODUCE,
        interlocks: int = 4,
        processed_counts: Sequence[PackMLCountDataType] | None = None,
        consumed_counts: Sequence[PackMLCountDataType] | None = None,
        alarm_extent: int = 10,
        alarm_history_extent: int = 50,
        warning_extent: int = 10,
        save_interval: float = 10.0,
        clock: Callable[[], float] = time.monotonic,
        wall_clock: Callable[[], datetime] = lambda: datetime.now(UTC),
        oee_window_hours: float = 8.0,
        oee_shifts: tuple[dt_time, ...] = (),
    ) -> None:
        self.name = name
        self.store = store
        self.save_interval = save_interval
        self._clock = clock
        self._wall = wall_clock
        self.supported_modes = frozenset(int(m) for m in supported_modes) - {Mode.INVALID}
        if initial_mode not in self.supported_modes:
            raise ValueError(f"initial mode {initial_mode} is not a supported mode")

        base_t, machine_t, execute_t = tables.base, tables.machine, tables.execute
        self._steps = tables.steps()
        self.base = StateMachine(BASE, base_t, "Cleared")
        self.machine = StateMachine(
            MACHINE, machine_t, "Stopped", parent=self.base, parent_state=hosting(base_t.states.values(), MACHINE)
        )
        self.execute = StateMachine(
            EXECUTE, execute_t, "Idle", parent=self.machine, parent_state=hosting(machine_t.states.values(), EXECUTE)
        )
        self.machines: dict[str, StateMachine] = {m.name: m for m in self.base.walk()}
        self._methods = {name: m.table.methods for name, m in self.machines.items()}
        # Executable of every method, for the inputs of _refusal it was computed from (see _executable_now)
        self._executable_key: tuple[Any, ...] | None = None
        self._executable_memo: dict[tuple[str | None, str], bool] = {}
        # The "state complete" transitions: those no method causes. Their from-states are the acting states.
        self._sc: dict[tuple[str, str], TransitionInfo] = {
            (m.name, t.from_state): t
            for m in self.machines.values()
            for t in m.table.transitions.values()
            if not t.causes
        }

        self.status = Status(
            unit_mode_current=int(initial_mode),
            mach_speed_range=(float(mach_speed_range[0]), float(mach_speed_range[1])),
            material_interlock=[True] * interlocks,
        )
        self.status.mach_speed = float(mach_speed)
        self._reported_cur_mach_speed: float | None = None  # the equipment's own (equipment_speeds)
        product = PackMLCountDataType(1, "Product", PACKAGES)
        self.admin = Admin(
            alarm_extent=alarm_extent,
            alarm_history_extent=alarm_history_extent,
            warning_extent=warning_extent,
            prod_processed_count=list(processed_counts or [product]),
            prod_defective_count=list(processed_counts or [product]),
            prod_consumed_count=list(consumed_counts or [PackMLCountDataType(100, "Material", PACKAGES)]),
            mach_design_speed=float(mach_design_speed),
        )

        # OEE over its window, from every span the accounting hands it and every production report (oee.py)
        self.oee = OEE(self.admin.mach_design_speed, oee_window_hours, oee_shifts)
        self.accounting = AdminAccounting(self.admin, max(self.supported_modes) + 1, self.oee, clock)
        self.publishing = Publishing(name)
        self.listeners: list[Listener] = self.publishing.listeners
        self.saving = StoredValues(name, store, clock, since=self.accounting.last)
        # OPC 10000-9 alarm conditions the equipment declares (a gateway's CommunicationLost), in
        # <unit>/Conditions (decision 45); PackML's own alarms stay Admin.Alarm and Admin.Warning
        self.conditions = ConditionSet(equipment.condition_names if has(equipment, NamedConditions) else ())
        self._depth = 0
        self.quiet_until = 0.0  # unit-clock time before which a tick would change nothing (run_units skips it)
        self._pending: list[str | None] = []
        # The acting state a command entered and that command's context: the state's completion runs
        # in it, so its AuditUpdateStateEvent names the caller (decision 38).
        self._cause: tuple[str, contextvars.Context] | None = None
        self._stop_armed = True  # the next stop event becomes StopReason (first out)
        if store is not None:
            self._load(store)
            self.saving.start(self.accounting.durable())  # what clients will first see is what was stored
        self._refresh()
        self.publishing.start(self.values())
        self.equipment: PackMLEquipment = equipment if equipment is not None else EquipmentBase()
        self.equipment.attach(self)

    # --- state-machine commands (decisions 22-25) ---------------------------------------------

    def command(self, machine_name: str | None, method: str, *args: Any) -> None:
        """Call ``method`` of ``machine_name`` (None: a unit method) with the method's input arguments."""
        self.check_reachable()
        if machine_name is UNIT:
            attribute = _UNIT_METHODS.get(method)
            if attribute is None:
                raise CallError("BadMethodInvalid", f"the unit has no method {method}")
            getattr(self, attribute)(*args)
        elif method == "Start" and machine_name == EXECUTE:
            self.start(*args)
        else:
            if args:
                raise CallError("BadTooManyArguments", f"{method} takes no arguments")
            self._machine_command(machine_name, method)

    def abort(self) -> None:
        self._machine_command(BASE, "Abort")

    def clear(self) -> None:
        self._machine_command(BASE, "Clear")

    def stop(self) -> None:
        self._machine_command(MACHINE, "Stop")

    def reset_machine(self) -> None:
        """MachineState.Reset: Stopped -> Running (Execute entered at Resetting)."""
        self._machine_command(MACHINE, "Reset")

    def start(self, parameters: Sequence[PackMLDescriptorDataType] = ()) -> None:
        """ExecuteState.Start(Parameter): Idle -> Starting; the parameters go to the equipment."""
        if parameters is None:
            raise CallError("BadArgumentsMissing", "Start needs the Parameter argument (may be empty)")
        params = validate_descriptors(list(parameters), argument=0, where="Parameter")
        self._machine_command(EXECUTE, "Start", parameters=params)

    def hold(self) -> None:
        self._machine_command(EXECUTE, "Hold")

    def unhold(self) -> None:
        self._machine_command(EXECUTE, "Unhold")

    def suspend(self) -> None:
        self._machine_command(EXECUTE, "Suspend")

    def _refusal(self, machine_name: str | None, method: str) -> str | None:
        """Why ``method`` cannot succeed now, or None if it can."""
        state = self.state
        if machine_name is UNIT:
            if method == "SetUnitMode":
                return None if state in SET_UNIT_MODE_STATES else f"SetUnitMode is not allowed in {state}"
            if method in ("SetProduct", "SetParameter"):
                return f"{method} is not allowed while a job runs ({state})" if state in JOB_STATES else None
            if method == "SetInterlock":
                return None if self.status.material_interlock else "the unit has no material interlocks"
            return None if method in UNIT_METHODS else f"the unit has no method {method}"
        sm = self.machines.get(machine_name)
        if sm is None or method not in self._methods[sm.name]:
            return f"{machine_name} has no method {method}"
        if not sm.active:
            return f"{method}: {machine_name} is not active (unit is {state})"
        if not sm.allows(method):
            return f"{method} is not allowed in {state}"
        if method in MODE_DISABLED.get(self.status.unit_mode_current, ()):
            return f"{method} is disabled in unit mode {self._mode_name()}"
        if method == "Start" and self.status.material_interlocked:
            return "Start is refused while MaterialInterlocked is true"
        return None

    def _machine_command(
        self,
        machine_name: str | None,
        method: str,
        *,
        parameters: tuple[PackMLDescriptorDataType, ...] = (),
        reason: Reason = Reason.EXTERNAL,
        stop_reason: PackMLAlarmDataType | None = None,
    ) -> None:
        why = self._refusal(machine_name, method)
        if why is not None:
            if machine_name not in self.machines or method not in self.machines[machine_name].table.methods:
                raise CallError("BadMethodInvalid", why)
            raise CallError("BadInvalidState", why)
        sm = self.machines[machine_name]  # type: ignore[index]
        t = sm.table.caused_by(method, sm.current)
        assert t is not None
        if method == "Start":
            # The equipment may refuse the parameters (e.g. an unknown ID) before anything changes.
            self.equipment.validate_start(parameters)
        with self._operation():
            if method == "Start":
                self.status.start_parameters = parameters
            if method in STOP_COMMAND_IDS:
                self._record_stop(
                    stop_reason
                    or PackMLAlarmDataType(
                        STOP_COMMAND_IDS[method], 0, f"{method} commanded", 0, self._wall(), None, False
                    )
                )
            if method == "Clear":
                self.accounting.acknowledge_alarms(self._wall())
            self._take(sm, t, reason)
            acting = self.acting_state
            self._cause = (acting, contextvars.copy_context()) if acting is not None else None

    # --- admin data ----------------------------------------------------------------------------

    def reset_counters(self) -> None:
        """Reset times and Count fields (AccCount is kept); there is no OPC UA method for this."""
        with self._operation():
            self._account()
            self.accounting.reset()
            self._account()
            self.save()

    def save(self) -> None:
        """Hand the durable Admin data to the store (if the unit has one). The store tells the unit once
        the data is durable (at once, or later from a writer thread); only then do clients see the stored
        values (decision 28). Failures are logged."""
        self.saving.submit(self.accounting.durable(), self._admin_json, self._stored)

    def _admin_json(self) -> dict[str, Any]:
        return self.accounting.to_json(self.name, self._wall().isoformat())

    def _stored(self, durable: dict[str, Any], error: OSError | None) -> None:
        self.quiet_until = 0.0  # what is stored moved: a save or a publication may be due
        if self.saving.stored(durable, error):
            self.publishing.change((DURABLE,))
        if self._depth == 0 and not self.saving.publishing and self.publishing.due:
            self._publish()  # stored later, outside any change: publish now

    async def run(self, period: float = 0.1) -> None:
        """Call ``tick`` every ``period`` seconds until cancelled (a server ticks its units with one
        ``run_units``)."""
        await run_units([self], period)

    @property
    def storing(self) -> bool:
        """A stored value other than a time (a count, StopReason, AlarmHistory) changed and is not yet
        durable, hence not yet published: a call that made such a change answers once it is."""
        return self.saving.storing

    @property
    def store_path(self) -> str:
        return self.saving.path

    def tick(self) -> None:
        """Advance time: Admin times, the equipment's ``poll``, a throttled save; publish changes."""
        with self._operation(changes=False):  # accounts the time when it ends (and before any transition)
            self.equipment.poll(self._clock())
            if self.saving.save_due(self.save_interval):
                self._account()
                self.save()
        self.quiet_until = next_tick(self)

    def close(self) -> None:
        """Shut down: account time, save, tell the equipment."""
        self._account()
        self.save()
        # A driver's close() may be a coroutine: the caller awaits it (uacell.packml.binding).
        self.equipment_closed: object = self.equipment.close()

    # --- internals -----------------------------------------------------------------------------

    def _check(self, machine_name: str | None, method: str) -> None:
        why = self._refusal(machine_name, method)
        if why is not None:
            raise CallError("BadInvalidState", why)

    @contextlib.contextmanager
    def _operation(self, changes: bool = True, touched: tuple[str, ...] | None = None) -> Iterator[None]:
        """Group changes: completions requested meanwhile run afterwards, then one publish. An operation
        that ``changes`` nothing itself (a tick) publishes only what its nested operations, the time
        (a whole second) or a save changed; one that names what it ``touched`` (keys of TOUCHABLE)
        publishes only those and the derived values (decision 47)."""
        self._depth += 1
        if changes:
            self.publishing.change(touched)
        try:
            yield
        finally:
            self._depth -= 1
            if self._depth == 0:
                self.quiet_until = 0.0  # something may be due at once: the next round ticks (tick sets it after)
                while self._pending:
                    state = self._pending.pop(0)
                    self._depth += 1
                    self.publishing.change()
                    try:
                        self._complete_now(state)
                    finally:
                        self._depth -= 1
                self._account()
                if self.publishing.due:
                    self._publish()

    def _complete_now(self, state: str | None) -> bool:
        sm = self.innermost()
        t = self._sc.get((sm.name, sm.current))
        if t is None or (state is not None and state != sm.current):
            return False
        cause, self._cause = self._cause, None
        if cause is not None and cause[0] == sm.current:
            cause[1].run(self._take, sm, t, Reason.SYSTEM)  # the command that entered it completes here
        else:
            self._take(sm, t, Reason.SYSTEM)
        return True

    def _take(self, sm: StateMachine, t: TransitionInfo, reason: Reason) -> None:
        self._account()  # time up to now belongs to the state being left
        sm.take(t.name, reason)
        for child in sm.children:
            if child.parent_state == t.to_state:
                child.enter(ENTRY_STATE[child.name], Reason.SYSTEM)
        self.accounting.new_state()
        state = self.state
        if state == "Execute":
            self._stop_armed = True
        self._refresh()
        self.save()
        self._call_hooks(state)

    def _call_hooks(self, state: str) -> None:
        eq = self.equipment
        hooks: dict[str, Callable[[], None]] = {
            "Clearing": eq.on_clearing,
            "Stopping": eq.on_stopping,
            "Aborting": eq.on_aborting,
            "Resetting": eq.on_resetting,
            "Starting": lambda: eq.on_starting(self.status.start_parameters),
            "Completing": eq.on_completing,
            "Holding": eq.on_holding,
            "Unholding": eq.on_unholding,
            "Suspending": eq.on_suspending,
            "Unsuspending": eq.on_unsuspending,
            "Execute": eq.on_execute,
        }
        try:
            eq.on_state(state)
            hook = hooks.get(state)
            if hook is not None:
                hook()
        except Exception as exc:
            log.exception("%s: equipment failed in %s", self.name, state)
            self.fault(0, f"equipment error in {state}: {exc}", category=0)

    def _refresh(self) -> None:
        """Derived Status values (decision 29)."""
        s = self.status
        sm = self.innermost()
        sc = self._sc.get((sm.name, sm.current))
        s.state_change_in_process = sc is not None
        s.state_requested = sm.table.states[sc.to_state if sc else sm.current].number
        reported = self._reported_cur_mach_speed
        s.cur_mach_speed = reported if reported is not None else s.mach_speed if self.execute.is_in("Execute") else 0.0

    def _record_stop(self, reason: PackMLAlarmDataType) -> None:
        if self._stop_armed:
            self.admin.stop_reason = reason
            self._stop_armed = False

    def _mode_name(self) -> str:
        try:
            return Mode(self.status.unit_mode_current).name.title()
        except ValueError:
            return str(self.status.unit_mode_current)

    def _account(self) -> None:
        """Add the time since the last call to the current mode/state (``accounting``)."""
        sm = self.innermost()
        if self.accounting.account(self.status.unit_mode_current, sm.table.states[sm.current].number, sm.current):
            self.publishing.change((TIMES,))

    def _publish(self) -> None:
        self._refresh()
        final = self._depth == 0  # a publish inside an operation (SetUnitMode's request) leaves the rest due
        values = self.publishing.select(self, final)
        if self.store is not None:
            # Decision 28: store before publishing, so that a crash never loses a value a client has read.
            self.saving.settle(values, self.save)
        self.publishing.emit(values, final)

    def _load(self, store: AdminStore) -> None:
        data = store.load()
        if data is None:
            return
        try:
            self.accounting.load(data)
        except (KeyError, TypeError, ValueError) as exc:
            log.warning("%s: stored PackML admin data is inconsistent (%s); using defaults", self.name, exc)
            return
        self._account()


def next_tick(unit: PackMLUnit) -> float:
    """Until when (on the unit's clock) a tick would change nothing, so ``run_units`` may skip the
    unit: the poll its equipment asks for next (``next_poll``; equipment without it is polled at every
    tick), the next whole second of an Admin time, the next save due."""
    now = unit.now()
    poll = unit.equipment.next_poll(now) if has(unit.equipment, PollHint) else now
    if poll <= now:
        return now
    sm = unit.innermost()
    times = unit.accounting.next_change(unit.status.unit_mode_current, sm.table.states[sm.current].number)
    return min(poll, times, unit.saving.next_save(unit.save_interval))


async def run_units(units: Sequence[PackMLUnit], period: float = 0.1) -> None:
    """Call every unit's ``tick`` every ``period`` seconds until cancelled: one task for all the units
    of a cell, in ``units``' order, letting other work run between groups of units."""
    while True:
        for i, unit in enumerate(units):
            if i and not i % TICK_GROUP:
                await asyncio.sleep(0)
            if unit.quiet_until > unit.now():
                continue  # nothing due before then (``next_tick``)
            try:
                unit.tick()
            except Exception:
                log.exception("%s: tick failed", unit.name)
        await asyncio.sleep(period)
