"""The pure ISA-TR88 / OPC 30050 PackML unit: three nested state machines, unit modes, Status, Admin.

The transitions are the NodeSet's (``PackMLTables``, handed in by the caller); this module adds only
what the tables cannot say: which sub-state a machine is entered at (decision 23), when the unit mode
disables a command (decision 26), the rules of the unit methods, and the Status/Admin bookkeeping (decisions 28, 29).
Every public operation either succeeds or raises ``CallError`` having changed nothing (decision 22).
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import dataclasses
import functools
import logging
import time
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from datetime import time as dt_time
from typing import Any

from uacell.capabilities import Reachable
from uacell.conditions import ConditionSet
from uacell.errors import CallError
from uacell.fsm import Reason, StateMachine
from uacell.models.tables import FsmTable, TableLoader, TransitionInfo
from uacell.packml.admin_store import AdminStore
from uacell.packml.equipment import EquipmentBase, NamedConditions, PackMLEquipment
from uacell.packml.oee import OEE, Figures
from uacell.packml.types import (
    EUInformation,
    PackMLAlarmDataType,
    PackMLCountDataType,
    PackMLDescriptorDataType,
    PackMLProductDataType,
    PackMLRemoteInterfaceDataType,
    ProductionMaintenanceModeEnum,
    alarm_from_json,
    alarm_to_json,
    check_float,
    count_from_json,
    count_to_json,
    validate_descriptors,
    validate_products,
    validate_remote_interfaces,
)

log = logging.getLogger(__name__)

BASE = "BaseStateMachine"
MACHINE = "MachineState"
EXECUTE = "ExecuteState"
UNIT = None  # machine_name of the unit's own methods (SetUnitMode, ...) in executable()/command()
UNIT_METHODS = ("SetUnitMode", "SetMachSpeed", "SetProduct", "SetParameter", "RemoteCommand", "SetInterlock")

Mode = ProductionMaintenanceModeEnum
COMPLETE = "complete"  # a step that ends an acting state (PackMLTables.steps, path)
# Decision 23: the sub-state a machine is entered at when its parent enters the hosting state.
ENTRY_STATE = {MACHINE: "Clearing", EXECUTE: "Resetting"}
# Decision 26.
MODE_DISABLED: dict[int, frozenset[str]] = {
    Mode.MAINTENANCE: frozenset({"Suspend"}),
    Mode.MANUAL: frozenset({"Start", "Suspend", "Hold", "ToComplete"}),
}
SET_UNIT_MODE_STATES = frozenset({"Stopped", "Idle", "Aborted"})
# uacell's rule: products and parameters change only while no job runs (between Start and Complete).
JOB_STATES = frozenset(
    {"Starting", "Execute", "Completing", "Holding", "Held", "Unholding", "Suspending", "Suspended", "Unsuspending"}
)
# StopReason.ID for a commanded stop: the ISA-TR88 command number (Stop 3, Hold 4, Suspend 6, Abort 8).
STOP_COMMAND_IDS = {"Stop": 3, "Hold": 4, "Suspend": 6, "Abort": 8}
TICK_GROUP = 10  # run_units lets the event loop run other work after every this many units
STATE_COLUMNS = 18  # StateCurrentTime/StateCumulativeTime second index: TR88 state numbers 0..17
INT32_WRAP = 2**31
PACKAGES = EUInformation("http://www.opcfoundation.org/UA/units/un/cefact", 5262926, "pkg", "package")

# The stored Admin values as clients read them (decision 28): published only once they are durable.
DURABLE_KEYS = (
    "Admin/ProdProcessedCount",
    "Admin/ProdDefectiveCount",
    "Admin/ProdConsumedCount",
    "Admin/ModeCumulativeTime",
    "Admin/StateCumulativeTime",
    "Admin/AccTimeSinceReset",
    "Admin/StopReason",
    "Admin/AlarmHistory",
)
DURABLE_TIMES = frozenset({"Admin/ModeCumulativeTime", "Admin/StateCumulativeTime", "Admin/AccTimeSinceReset"})
_DURABLE_NOT_TIMES = tuple(k for k in DURABLE_KEYS if k not in DURABLE_TIMES)
# A change of the stored times alone (a whole second passed) is stored, and then published, at most this
# often (seconds): the three times pass their whole seconds at different instants.
TIMES_SAVE_PERIOD = 1.0
# The unit's own methods (PackMLBaseObjectType), by the model method that answers each.
_UNIT_METHODS = {
    "SetUnitMode": "set_unit_mode",
    "SetMachSpeed": "set_mach_speed",
    "SetProduct": "set_product",
    "SetParameter": "set_parameter",
    "RemoteCommand": "remote_command",
    "SetInterlock": "set_interlock",
}
# Decision 47: an operation that names what it changes (``_operation(touched=...)``) publishes only those
# values, the derived ones (decision 29) and, when a whole second passed, the times and OEE figures;
# every other operation rebuilds and compares all values. The values an operation may name: TOUCHABLE.
TIMES = "times"  # the touched mark of the Admin times and OEE figures (_account)
DURABLE = "durable"  # the touched mark of the stored values (a save became durable)

Listener = Callable[[dict[str, Any]], None]


@dataclass(frozen=True)
class PackMLTables:
    """The three PackML state-machine tables, handed to ``PackMLUnit`` by whoever knows the NodeSets."""

    base: FsmTable
    machine: FsmTable
    execute: FsmTable

    @classmethod
    def load(cls, tables: TableLoader) -> PackMLTables:
        loaded = cls(
            base=tables("PackML", "PackMLBaseStateMachineType"),
            machine=tables("PackML", "PackMLMachineStateMachineType"),
            execute=tables("PackML", "PackMLExecuteStateMachineType"),
        )
        loaded.base.check_names(("Cleared",))
        loaded.machine.check_names(("Stopped", ENTRY_STATE[MACHINE]))
        loaded.execute.check_names(("Idle", "Execute", ENTRY_STATE[EXECUTE], *JOB_STATES))
        return loaded

    def steps(self) -> dict[str, list[tuple[str, str]]]:
        """Each innermost state's steps, from the NodeSet's transitions: (the method that causes a
        transition from it or from a state hosting it, the innermost state that leads to) and, for an
        acting state, (``COMPLETE``, where it ends). A transition into a state hosting a sub-machine
        leads to that machine's entry state (decision 23)."""
        tables = {BASE: self.base, MACHINE: self.machine, EXECUTE: self.execute}

        def entry(table: FsmTable, state: str) -> str:
            sub = table.states[state].submachine
            return entry(tables[sub], ENTRY_STATE[sub]) if sub in tables else state

        def leaves(table: FsmTable, state: str) -> list[str]:
            sub = table.states[state].submachine
            if sub not in tables:
                return [state]
            return [leaf for inner in tables[sub].states for leaf in leaves(tables[sub], inner)]

        out: dict[str, list[tuple[str, str]]] = {
            name: [] for t in tables.values() for name, info in t.states.items() if info.submachine not in tables
        }
        for table in tables.values():
            for t in table.transitions.values():
                for leaf in leaves(table, t.from_state):
                    out[leaf].append((t.causes[0] if t.causes else COMPLETE, entry(table, t.to_state)))
        return out


def _i32(x: float) -> int:
    # Admin times and counts roll over at 2^31-1 (OPC 30050 §6.3.4).
    return int(x) % INT32_WRAP


@dataclass
class Status:
    """PackMLStatusObjectType values, plus uacell's StartParameters."""

    unit_mode_current: int = Mode.PRODUCE
    unit_mode_requested: bool = False
    unit_mode_change_in_process: bool = False
    state_requested: int = 0
    state_change_in_process: bool = False
    mach_speed: float = 0.0
    mach_speed_range: tuple[float, float] = (0.0, 600.0)
    cur_mach_speed: float = 0.0
    equipment_blocked: bool = False
    equipment_starved: bool = False
    material_interlocked: bool = False
    material_interlock: list[bool] = field(default_factory=list)
    parameter: tuple[PackMLDescriptorDataType, ...] = ()
    remote_parameter: tuple[PackMLRemoteInterfaceDataType, ...] = ()
    product: tuple[PackMLProductDataType, ...] = ()
    start_parameters: tuple[PackMLDescriptorDataType, ...] = ()


@dataclass
class Admin:
    """PackMLAdminObjectType values (times in whole seconds, Int32 with roll-over)."""

    parameter: tuple[PackMLDescriptorDataType, ...] = ()
    alarm: list[PackMLAlarmDataType] = field(default_factory=list)
    alarm_extent: int = 10
    alarm_history: list[PackMLAlarmDataType] = field(default_factory=list)
    alarm_history_extent: int = 50
    warning: list[PackMLAlarmDataType] = field(default_factory=list)
    warning_extent: int = 10
    stop_reason: PackMLAlarmDataType = field(default_factory=lambda: PackMLAlarmDataType(0))
    stop_reason_extent: int = 1
    mode_current_time: list[int] = field(default_factory=list)
    mode_cumulative_time: list[int] = field(default_factory=list)
    state_current_time: list[list[int]] = field(default_factory=list)
    state_cumulative_time: list[list[int]] = field(default_factory=list)
    prod_consumed_count: list[PackMLCountDataType] = field(default_factory=list)
    prod_processed_count: list[PackMLCountDataType] = field(default_factory=list)
    prod_defective_count: list[PackMLCountDataType] = field(default_factory=list)
    acc_time_since_reset: int = 0
    mach_design_speed: float = 0.0


class PackMLUnit:
    """One PackML unit (an instance of PackMLBaseObjectType), free of OPC UA."""

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
            MACHINE, machine_t, "Stopped", parent=self.base, parent_state=_hosting(base_t.states.values(), MACHINE)
        )
        self.execute = StateMachine(
            EXECUTE, execute_t, "Idle", parent=self.machine, parent_state=_hosting(machine_t.states.values(), EXECUTE)
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

        rows = max(self.supported_modes) + 1
        self._mode_cum = [0.0] * rows
        self._state_cum = [[0.0] * STATE_COLUMNS for _ in range(rows)]
        self._mode_cur = 0.0
        self._state_cur = 0.0
        self._acc = 0.0
        self._times_shown: tuple[int, ...] | None = None  # what the Admin times were last built from
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

        # OEE over its window, from every span _account hands it and every production report (oee.py)
        self.oee = OEE(self.admin.mach_design_speed, oee_window_hours, oee_shifts)

        self.listeners: list[Listener] = []
        # OPC 10000-9 alarm conditions the equipment declares (a gateway's CommunicationLost), in
        # <unit>/Conditions (decision 45); PackML's own alarms stay Admin.Alarm and Admin.Warning
        self.conditions = ConditionSet(equipment.condition_names if isinstance(equipment, NamedConditions) else ())
        self._depth = 0
        # Changes that may have altered a published value, counted; an operation publishes only if the
        # count moved since the last publish (a tick that changes no whole second publishes nothing).
        self._changes = 0
        self._published_changes = -1
        self._touched: set[str] | None = None  # what changed since the last publish (None: anything)
        self._pending: list[str | None] = []
        # The acting state a command entered and that command's context: the state's completion runs
        # in it, so its AuditUpdateStateEvent names the caller (decision 38).
        self._cause: tuple[str, contextvars.Context] | None = None
        self._stop_armed = True  # the next stop event becomes StopReason (first out)
        self._last_account = clock()
        self._last_save = self._last_account
        self._saved: dict[str, Any] = {}  # the durable values as last stored: what clients may see
        self._submitted: dict[str, Any] | None = None  # the durable values last handed to the store
        self._save_failing = False
        self._publishing = False
        self._times_due = False  # stored times changed, to be saved at a tick (TIMES_SAVE_PERIOD)
        self._last_values: dict[str, Any] = {}
        if store is not None:
            self._load(store)
            self._saved = self._submitted = self._durable()  # what clients will first see is what was stored
        self._refresh()
        self._last_values = self.values()
        self.equipment: PackMLEquipment = equipment if equipment is not None else EquipmentBase()
        self.equipment.attach(self)

    # --- reading -----------------------------------------------------------------------------

    def now(self) -> float:
        return self._clock()

    def innermost(self) -> StateMachine:
        """The deepest active machine; its current state is the unit's TR88 state."""
        sm = self.base
        while (child := sm.hosted()) is not None:  # from the top down: the base is always active
            sm = child
        return sm

    @property
    def state(self) -> str:
        return self.innermost().current

    @property
    def state_number(self) -> int:
        sm = self.innermost()
        return sm.table.states[sm.current].number

    @property
    def states(self) -> tuple[str, str | None, str | None]:
        """(Base, Machine, Execute) current states, None for an inactive machine."""
        return (
            self.base.current,
            self.machine.current if self.machine.active else None,
            self.execute.current if self.execute.active else None,
        )

    @property
    def acting_state(self) -> str | None:
        """The acting state that is running (it ends when the equipment completes it), if any."""
        sm = self.innermost()
        return sm.current if (sm.name, sm.current) in self._sc else None

    @property
    def cur_mach_speed(self) -> float:
        return self.status.cur_mach_speed

    @property
    def unit_mode(self) -> int:
        return self.status.unit_mode_current

    @property
    def reachable(self) -> bool:
        """False while equipment that says so (a gateway driver's ``reachable``) cannot reach its PLC."""
        equipment = getattr(self, "equipment", None)  # none yet while the unit is being made
        return bool(equipment.reachable) if isinstance(equipment, Reachable) else True

    def check_reachable(self) -> None:
        """Bad_CommunicationError while the equipment cannot reach its PLC: nothing is tried."""
        if not self.reachable:
            raise CallError("BadCommunicationError", f"{self.name}: the PLC cannot be reached")

    def check_command(self, machine_name: str | None, method: str) -> None:
        """Would ``method`` of ``machine_name`` be accepted now (CallError if not)? Nothing changes."""
        self.check_reachable()
        why = self._refusal(machine_name, method)
        if why is not None:
            if machine_name is not UNIT and (
                machine_name not in self.machines or method not in self.machines[machine_name].table.methods
            ):
                raise CallError("BadMethodInvalid", why)
            raise CallError("BadInvalidState", why)

    def executable(self, machine_name: str | None, method: str) -> bool:
        """True exactly when calling ``method`` now could succeed (decision 4)."""
        if not self.reachable:
            return False
        known = self._executable_now().get((machine_name, method))
        return known if known is not None else self._refusal(machine_name, method) is None

    @property
    def executable_inputs(self) -> tuple[Any, ...]:
        """Everything Executable of the unit's methods depends on: the three machines' states, the
        unit mode, the material interlocks and whether the equipment is reachable. The dispatcher
        re-evaluates the methods only when it changed."""
        s = self.status
        # The three machines' own current states decide which are active, hence the unit's state.
        return (
            self.base.current, self.machine.current, self.execute.current,
            s.unit_mode_current, bool(s.material_interlock), s.material_interlocked, self.reachable,
        )  # fmt: skip

    def _executable_now(self) -> dict[tuple[str | None, str], bool]:
        """Executable of every method, recomputed only when ``executable_inputs`` changed."""
        key = self.executable_inputs
        if key != self._executable_key:
            self._executable_memo = {k: self._refusal(*k) is None for k in self.methods()}
            self._executable_key = key
        return self._executable_memo

    def methods(self) -> list[tuple[str | None, str]]:
        """Every (machine_name, method) the unit offers; machine_name None for the unit's methods."""
        out: list[tuple[str | None, str]] = [(UNIT, m) for m in UNIT_METHODS]
        for sm in self.machines.values():
            out.extend((sm.name, m) for m in sorted(sm.table.methods))
        return out

    def values(self) -> dict[str, Any]:
        """Every Status/Admin value by browse path relative to the unit, plus ``Executable``."""
        s, a = self.status, self.admin
        # Fresh containers of immutable items: listeners may keep them without copying.
        return {
            "Status/UnitModeCurrent": s.unit_mode_current,
            "Status/UnitModeRequested": s.unit_mode_requested,
            "Status/UnitModeChangeInProcess": s.unit_mode_change_in_process,
            **self._derived(),
            "Status/MachSpeed/EURange": s.mach_speed_range,
            "Status/CurMachSpeed/EURange": s.mach_speed_range,
            "Status/EquipmentBlocked": s.equipment_blocked,
            "Status/EquipmentStarved": s.equipment_starved,
            "Status/MaterialInterlocked": s.material_interlocked,
            "Status/MaterialInterlock": list(s.material_interlock),
            "Status/StartParameters": list(s.start_parameters),
            **{key: value(self) for key, value in TOUCHABLE.items()},
            "Admin/Parameter": list(a.parameter),
            "Admin/Alarm": list(a.alarm),
            "Admin/AlarmExtent": a.alarm_extent,
            "Admin/AlarmHistoryExtent": a.alarm_history_extent,
            "Admin/Warning": list(a.warning),
            "Admin/WarningExtent": a.warning_extent,
            "Admin/StopReasonExtent": a.stop_reason_extent,
            "Admin/MachDesignSpeed": a.mach_design_speed,
            **self._durable(),
            **self._times(),
            **self.oee_values(),
            # unreachable equipment (a gateway's PLC away): nothing is Executable
            "Executable": dict(self._executable_now()) if self.reachable else dict.fromkeys(self.methods(), False),
        }

    def oee_figures(self) -> Figures:
        """OEE over its window up to the last accounting (a transition, a count or a tick)."""
        wall = self._wall() - timedelta(seconds=max(0.0, self._clock() - self._last_account))
        return self.oee.figures(self._last_account, wall)

    def oee_values(self) -> dict[str, float | int]:
        """The OEE variables under the unit (uacell's namespace), figures rounded to 3 decimals (0.1 %)."""
        return {k: round(v, 3) if isinstance(v, float) else v for k, v in self.oee_figures().values().items()}

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
                self._acknowledge_alarms()
            self._take(sm, t, reason)
            acting = self.acting_state
            self._cause = (acting, contextvars.copy_context()) if acting is not None else None

    # --- equipment side (UnitPort) -------------------------------------------------------------

    def state_complete(self, state: str | None = None) -> bool:
        """The running acting state (``state``, if given) is done: take its SC transition."""
        acting = self.acting_state
        if acting is None or (state is not None and state != acting):
            log.debug("%s: ignoring completion of %s (unit is %s)", self.name, state, self.state)
            return False
        if self._depth:
            self._pending.append(acting)  # called from inside a hook: take it once the hook returns
            return True
        with self._operation():
            return self._complete_now(acting)

    def path_to(self, state: str) -> list[tuple[str, str]]:
        """The fewest TR88 steps from the unit's innermost state to ``state`` (``path``): for equipment
        whose PLC moved on by itself (a gateway), to follow it there."""
        return path(self._steps, self.state, state)

    def state_numbered(self, number: int) -> str | None:
        """The TR88 state with StateNumber ``number`` (the NodeSet's numbers), if any."""
        for sm in self.machines.values():
            for name, info in sm.table.states.items():
                if info.number == number:
                    return name
        return None

    def equipment_command(self, method: str) -> None:
        """A transition the machine itself takes (same rules as for clients); innermost machine first."""
        for sm in reversed(self.base.walk()):
            if method in sm.table.methods and self._refusal(sm.name, method) is None:
                self._machine_command(sm.name, method, reason=Reason.SYSTEM)
                return
        raise CallError("BadInvalidState", f"{method} is not possible in {self.state}")

    def report_production(self, processed: int = 0, defective: int = 0, consumed: int | Mapping[int, int] = 0) -> None:
        with self._operation():
            a = self.admin
            if processed or defective:
                self._account()  # the spans up to now, before the counts
                self.oee.count(self._clock(), processed, defective)
            if processed:
                a.prod_processed_count[0] = _counted(a.prod_processed_count[0], processed)
            if defective:
                a.prod_defective_count[0] = _counted(a.prod_defective_count[0], defective)
            amounts = consumed if isinstance(consumed, Mapping) else {a.prod_consumed_count[0].id: consumed}
            for material, amount in amounts.items():
                if not amount:
                    continue
                for i, c in enumerate(a.prod_consumed_count):
                    if c.id == material:
                        a.prod_consumed_count[i] = _counted(c, amount)
                        break
                else:
                    raise ValueError(f"no ProdConsumedCount with ID {material}")

    def fault(self, alarm_id: int, message: str, *, value: int = 0, category: int = 1) -> None:
        with self._operation():
            alarm = PackMLAlarmDataType(alarm_id, value, message, category, self._wall(), None, True)
            _push(self.admin.alarm, alarm, self.admin.alarm_extent)
            _push(self.admin.alarm_history, alarm, self.admin.alarm_history_extent)
            log.warning("%s: fault %s: %s", self.name, alarm_id, message)
            if self._refusal(BASE, "Abort") is None:
                self._machine_command(BASE, "Abort", reason=Reason.ERROR, stop_reason=alarm)
            else:
                self._record_stop(alarm)

    def warning(self, warning_id: int, message: str, *, active: bool = True) -> None:
        with self._operation():
            w = self.admin.warning
            w[:] = [x for x in w if x.id != warning_id]
            if active:
                _push(
                    w,
                    PackMLAlarmDataType(warning_id, 0, message, 0, self._wall(), None, True),
                    self.admin.warning_extent,
                )

    def equipment_unit_mode(self, mode: int) -> bool:
        """The equipment changed the unit mode by itself (a PLC's panel): take it as the current mode.
        A mode the unit does not support is refused (False, logged), nothing changes."""
        if isinstance(mode, bool) or not isinstance(mode, int) or mode not in self.supported_modes:
            log.warning("%s: the equipment reports unit mode %r, not a supported mode", self.name, mode)
            return False
        if mode == self.status.unit_mode_current:
            return True
        with self._operation():
            self._account()
            self.status.unit_mode_current = mode
            self._mode_cur = self._state_cur = 0.0
            self.save()
        return True

    def equipment_alarms(self, alarms: Mapping[int, str]) -> None:
        """The alarms the equipment has active now (ID -> message): Admin.Alarm becomes that list;
        an alarm that is new is also added to AlarmHistory, one that went is acknowledged there."""
        with self._operation():
            a = self.admin
            active = {x.id: x for x in a.alarm}
            if set(active) == set(alarms):
                return
            now = self._wall()
            gone = {(x.id, x.date_time) for x in a.alarm if x.id not in alarms}
            a.alarm_history[:] = [
                dataclasses.replace(h, ack_date_time=now, trigger=False) if (h.id, h.date_time) in gone else h
                for h in a.alarm_history
            ]
            a.alarm[:] = [x for x in a.alarm if x.id in alarms]
            for alarm_id, message in alarms.items():
                if alarm_id not in active:
                    alarm = PackMLAlarmDataType(alarm_id, 0, message, 1, now, None, True)
                    _push(a.alarm, alarm, a.alarm_extent)
                    _push(a.alarm_history, alarm, a.alarm_history_extent)

    def equipment_speeds(self, mach_speed: float | None = None, cur_mach_speed: float | None = None) -> None:
        """The equipment's own MachSpeed and CurMachSpeed (a PLC owns them): shown as reported, not
        checked against the EURange (the machine runs at what it runs at). A reported CurMachSpeed
        replaces the derived one (MachSpeed in Execute, else 0) from then on."""
        touched = ("Status/MachSpeed",) if mach_speed is not None else ()
        with self._operation(touched=touched):
            if mach_speed is not None:
                self.status.mach_speed = float(mach_speed)
            if cur_mach_speed is not None:
                self._reported_cur_mach_speed = float(cur_mach_speed)

    def equipment_condition(self, name: str, active: bool, message: str) -> None:
        """The equipment raises (``active``) or clears its condition ``name`` (one of its
        ``condition_names``)."""
        self.conditions.alarm(name, active, message)

    def set_blocked(self, blocked: bool) -> None:
        with self._operation():
            self.status.equipment_blocked = bool(blocked)

    def set_starved(self, starved: bool) -> None:
        with self._operation():
            self.status.equipment_starved = bool(starved)

    # --- unit methods (decisions 26, 27) -------------------------------------------------------

    def check_unit_mode(self, mode: int) -> None:
        """Would SetUnitMode(``mode``) be accepted now (CallError if not)? Nothing changes."""
        if isinstance(mode, bool) or not isinstance(mode, int) or mode not in self.supported_modes:
            raise CallError(
                "BadInvalidArgument",
                f"RequestedMode {mode!r} is not a supported mode ({sorted(self.supported_modes)})",
                argument=0,
            )
        self._check(UNIT, "SetUnitMode")

    def set_unit_mode(self, mode: int) -> None:
        self.check_unit_mode(mode)
        with self._operation():
            s = self.status
            s.unit_mode_requested = s.unit_mode_change_in_process = True
            self._publish()  # clients may see the request in process before the new mode
            try:
                self.equipment.on_unit_mode(mode)
            finally:
                s.unit_mode_requested = s.unit_mode_change_in_process = False
            self._account()
            if s.unit_mode_current != mode:  # the same mode again is no change: current times keep running
                s.unit_mode_current = int(mode)
                self._mode_cur = self._state_cur = 0.0
            self.save()

    def set_mach_speed(self, speed: float) -> None:
        value = check_float(speed, "RequestedMachineSpeed", 0)
        low, high = self.status.mach_speed_range
        if not low <= value <= high:
            raise CallError(
                "BadInvalidArgument",
                f"RequestedMachineSpeed {value} is outside the EURange [{low}, {high}]",
                argument=0,
            )
        self.equipment.on_mach_speed(value)
        with self._operation(touched=("Status/MachSpeed",)):
            self.status.mach_speed = value

    def set_product(self, products: Sequence[PackMLProductDataType]) -> None:
        items = validate_products(list(products), argument=0, where="Product")
        self._check(UNIT, "SetProduct")
        self.equipment.on_product(items)
        with self._operation(touched=("Status/Product",)):
            self.status.product = items

    def set_parameter(self, parameters: Sequence[PackMLDescriptorDataType]) -> None:
        items = validate_descriptors(list(parameters), argument=0, where="Parameter")
        self._check(UNIT, "SetParameter")
        self.equipment.on_parameter(items)
        with self._operation(touched=("Status/Parameter",)):
            self.status.parameter = items

    def remote_command(self, commands: Sequence[PackMLRemoteInterfaceDataType]) -> None:
        items = validate_remote_interfaces(list(commands), argument=0, where="RemoteInterface")
        self.equipment.on_remote_command(items)
        with self._operation(touched=("Status/RemoteParameter",)):
            self.status.remote_parameter = items

    def set_interlock(self, interlock_id: int, state: bool) -> None:
        """State true = interlocked: MaterialInterlock[id] becomes false (its bit means "ready")."""
        n = len(self.status.material_interlock)
        if isinstance(interlock_id, bool) or not isinstance(interlock_id, int) or not 0 <= interlock_id < n:
            raise CallError(
                "BadInvalidArgument",
                f"InterlockId {interlock_id!r} is not an index of MaterialInterlock (0..{n - 1})",
                argument=0,
            )
        if not isinstance(state, bool):
            raise CallError("BadInvalidArgument", f"State must be a Boolean, got {state!r}", argument=1)
        self.equipment.on_interlock(interlock_id, state)
        with self._operation():
            self.status.material_interlock[interlock_id] = not state
            self.status.material_interlocked = not all(self.status.material_interlock)

    # --- admin data ----------------------------------------------------------------------------

    def reset_counters(self) -> None:
        """Reset times and Count fields (AccCount is kept); there is no OPC UA method for this."""
        with self._operation():
            self._account()
            self._mode_cum = [0.0] * len(self._mode_cum)
            self._state_cum = [[0.0] * STATE_COLUMNS for _ in self._state_cum]
            self._mode_cur = self._state_cur = self._acc = 0.0
            self._times_shown = None
            self._account()
            for counts in (
                self.admin.prod_processed_count,
                self.admin.prod_defective_count,
                self.admin.prod_consumed_count,
            ):
                counts[:] = [dataclasses.replace(c, count=0) for c in counts]
            self.save()

    def save(self) -> None:
        """Hand the durable Admin data to the store (if the unit has one). The store tells the unit once
        the data is durable (at once, or later from a writer thread); only then do clients see the stored
        values (decision 28). Failures are logged."""
        self._save(self._durable())

    def _save(self, durable: dict[str, Any]) -> None:
        self._last_save = self._clock()
        self._times_due = False
        if self.store is None:
            return
        self._submitted = durable
        self.store.submit(self._admin_json(), functools.partial(self._stored, durable))

    def _stored(self, durable: dict[str, Any], error: OSError | None) -> None:
        if error is not None:
            # Retried at the next change of a stored value: log the failure once, not at every try. A
            # failing disk does not freeze the values clients see.
            if not self._save_failing:
                log.error("%s: cannot save PackML admin data to %s", self.name, self.store_path, exc_info=error)
            self._save_failing = True
        elif self._save_failing:
            log.warning("%s: PackML admin data saved to %s again", self.name, self.store_path)
            self._save_failing = False
        if durable != self._saved:
            self._saved = durable
            self._changes += 1
            self._touch((DURABLE,))
        if self._depth == 0 and not self._publishing and self._changes != self._published_changes:
            self._publish()  # stored later, outside any change: publish now

    async def run(self, period: float = 0.1) -> None:
        """Call ``tick`` every ``period`` seconds until cancelled (a server ticks its units with one
        ``run_units``)."""
        await run_units([self], period)

    @property
    def storing(self) -> bool:
        """A stored value other than a time (a count, StopReason, AlarmHistory) changed and is not yet
        durable, hence not yet published: a call that made such a change answers once it is."""
        submitted = self._submitted
        if self.store is None or submitted is None:
            return False
        saved = self._saved
        return any(submitted[k] != saved[k] for k in _DURABLE_NOT_TIMES)

    @property
    def store_path(self) -> str:
        return str(self.store.path) if self.store is not None else "(no store)"

    def tick(self) -> None:
        """Advance time: Admin times, the equipment's ``poll``, a throttled save; publish changes."""
        with self._operation(changes=False):  # accounts the time when it ends (and before any transition)
            self.equipment.poll(self._clock())
            since = self._clock() - self._last_save
            if since >= self.save_interval or (self._times_due and since >= TIMES_SAVE_PERIOD):
                self._account()
                self.save()

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
            self._changes += 1
            self._touch(touched)
        try:
            yield
        finally:
            self._depth -= 1
            if self._depth == 0:
                while self._pending:
                    state = self._pending.pop(0)
                    self._depth += 1
                    self._changes += 1
                    self._touch(None)
                    try:
                        self._complete_now(state)
                    finally:
                        self._depth -= 1
                self._account()
                if self._changes != self._published_changes:
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
        self._state_cur = 0.0
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

    def _acknowledge_alarms(self) -> None:
        now = self._wall()
        active = {(a.id, a.date_time) for a in self.admin.alarm}
        self.admin.alarm_history[:] = [
            dataclasses.replace(h, ack_date_time=now, trigger=False) if (h.id, h.date_time) in active else h
            for h in self.admin.alarm_history
        ]
        self.admin.alarm.clear()

    def _mode_name(self) -> str:
        try:
            return Mode(self.status.unit_mode_current).name.title()
        except ValueError:
            return str(self.status.unit_mode_current)

    def _account(self) -> None:
        """Add the time since the last call to the current mode/state, and refresh Admin times."""
        now = self._clock()
        dt = max(0.0, now - self._last_account)
        self._last_account = now
        sm = self.innermost()
        mode, state = self.status.unit_mode_current, sm.table.states[sm.current].number
        self.oee.span(now - dt, now, mode, sm.current)
        self._mode_cum[mode] += dt
        self._state_cum[mode][state] += dt
        self._mode_cur += dt
        self._state_cur += dt
        self._acc += dt
        # Only the current mode's and state's entries moved: rebuild the Admin times (whole seconds) only
        # when one of those changed a whole second, or the mode or state changed.
        shown = (
            mode, state, _i32(self._mode_cur), _i32(self._state_cur), _i32(self._mode_cum[mode]),
            _i32(self._state_cum[mode][state]), _i32(self._acc),
        )  # fmt: skip
        if shown == self._times_shown:
            return
        self._times_shown = shown
        self._changes += 1
        self._touch((TIMES,))
        a = self.admin
        a.mode_current_time = [0] * len(self._mode_cum)
        a.mode_current_time[mode] = _i32(self._mode_cur)
        a.mode_cumulative_time = [_i32(x) for x in self._mode_cum]
        a.state_current_time = [[0] * STATE_COLUMNS for _ in self._state_cum]
        a.state_current_time[mode][state] = _i32(self._state_cur)
        a.state_cumulative_time = [[_i32(x) for x in row] for row in self._state_cum]
        a.acc_time_since_reset = _i32(self._acc)

    def _durable(self) -> dict[str, Any]:
        """The durable Admin values as clients read them (whole seconds, counts), by DURABLE_KEYS."""
        a = self.admin
        return {
            "Admin/ProdProcessedCount": list(a.prod_processed_count),
            "Admin/ProdDefectiveCount": list(a.prod_defective_count),
            "Admin/ProdConsumedCount": list(a.prod_consumed_count),
            "Admin/ModeCumulativeTime": list(a.mode_cumulative_time),
            "Admin/StateCumulativeTime": [list(r) for r in a.state_cumulative_time],
            "Admin/AccTimeSinceReset": a.acc_time_since_reset,
            "Admin/StopReason": a.stop_reason,
            "Admin/AlarmHistory": list(a.alarm_history),
        }

    def _times(self) -> dict[str, Any]:
        """The Admin times that are not stored (the current mode's and state's)."""
        a = self.admin
        return {
            "Admin/ModeCurrentTime": list(a.mode_current_time),
            "Admin/StateCurrentTime": [list(r) for r in a.state_current_time],
        }

    def _derived(self) -> dict[str, Any]:
        """The Status values ``_refresh`` derives from the states and the speed (decision 29)."""
        s = self.status
        return {
            "Status/StateRequested": s.state_requested,
            "Status/StateChangeInProcess": s.state_change_in_process,
            "Status/CurMachSpeed": s.cur_mach_speed,
        }

    def _touched_values(self, touched: set[str]) -> dict[str, Any]:
        """The values an operation that named what it changed may have changed (decision 47)."""
        values = self._derived()
        for key in touched:
            if key in TOUCHABLE:
                values[key] = TOUCHABLE[key](self)
        if TIMES in touched:
            durable = self._durable()
            values.update({k: durable[k] for k in DURABLE_TIMES})
            values.update(self._times())
            values.update(self.oee_values())
        if DURABLE in touched:
            values.update(self._durable())
        return values

    def _touch(self, touched: Iterable[str] | None) -> None:
        """Mark values changed for the next publish: ``touched`` names them, None means any."""
        if touched is None:
            self._touched = None
        elif self._touched is not None:
            self._touched.update(touched)

    def _publish(self) -> None:
        self._refresh()
        touched = self._touched
        if self._depth == 0:  # a publish inside an operation (SetUnitMode's request) leaves the rest due
            self._touched = set()
        values = self.values() if touched is None else self._touched_values(touched)
        if self.store is not None:
            # Decision 28: store before publishing, so that a crash never loses a value a client has read.
            submitted = self._submitted
            moved = [k for k in DURABLE_KEYS if k in values and (submitted is None or values[k] != submitted[k])]
            if moved and DURABLE_TIMES.issuperset(moved) and self._clock() - self._last_save < TIMES_SAVE_PERIOD:
                self._times_due = True  # only time passed: stored at a tick, once a second at most
            elif moved:
                self._publishing = True
                try:
                    self._save(self._durable())
                finally:
                    self._publishing = False
            # clients see the stored values, the newer ones once stored
            values.update({k: v for k, v in self._saved.items() if k in values})
        if self._depth == 0:
            self._published_changes = self._changes
        last = self._last_values
        changed = {k: v for k, v in values.items() if last.get(k, _MISSING) != v}
        last.update(values)
        if not changed:
            return
        for listener in list(self.listeners):
            try:
                listener(changed)
            except Exception:
                log.exception("%s: change listener failed", self.name)

    def _admin_json(self) -> dict[str, Any]:
        a = self.admin
        return {
            "unit": self.name,
            "saved_at": self._wall().isoformat(),
            "prod_processed_count": [count_to_json(c) for c in a.prod_processed_count],
            "prod_defective_count": [count_to_json(c) for c in a.prod_defective_count],
            "prod_consumed_count": [count_to_json(c) for c in a.prod_consumed_count],
            "mode_cumulative_time": list(self._mode_cum),
            "state_cumulative_time": [list(r) for r in self._state_cum],
            "acc_time_since_reset": self._acc,
            "stop_reason": alarm_to_json(a.stop_reason),
            "alarm_history": [alarm_to_json(x) for x in a.alarm_history],
        }

    def _load(self, store: AdminStore) -> None:
        data = store.load()
        if data is None:
            return
        try:
            a = self.admin
            for key, counts in (
                ("prod_processed_count", a.prod_processed_count),
                ("prod_defective_count", a.prod_defective_count),
                ("prod_consumed_count", a.prod_consumed_count),
            ):
                stored = {c.id: c for c in map(count_from_json, data.get(key, []))}
                counts[:] = [
                    dataclasses.replace(c, count=stored[c.id].count, acc_count=stored[c.id].acc_count)
                    if c.id in stored
                    else c
                    for c in counts
                ]
            for i, x in enumerate(data.get("mode_cumulative_time", [])[: len(self._mode_cum)]):
                self._mode_cum[i] = float(x)
            for i, row in enumerate(data.get("state_cumulative_time", [])[: len(self._state_cum)]):
                for j, x in enumerate(row[:STATE_COLUMNS]):
                    self._state_cum[i][j] = float(x)
            self._acc = float(data.get("acc_time_since_reset", 0.0))
            if data.get("stop_reason"):
                a.stop_reason = alarm_from_json(data["stop_reason"])
            history = [alarm_from_json(x) for x in data.get("alarm_history", [])]
            a.alarm_history = history[-a.alarm_history_extent :]
        except (KeyError, TypeError, ValueError) as exc:
            log.warning("%s: stored PackML admin data is inconsistent (%s); using defaults", self.name, exc)
            return
        self._account()


_MISSING = object()


# The values an operation may name as all it changed (decision 47), each read on its own.
TOUCHABLE: dict[str, Callable[[PackMLUnit], Any]] = {
    "Status/MachSpeed": lambda u: u.status.mach_speed,
    "Status/Parameter": lambda u: list(u.status.parameter),
    "Status/RemoteParameter": lambda u: list(u.status.remote_parameter),
    "Status/Product": lambda u: list(u.status.product),
}


async def run_units(units: Sequence[PackMLUnit], period: float = 0.1) -> None:
    """Call every unit's ``tick`` every ``period`` seconds until cancelled: one task for all the units
    of a cell, in ``units``' order, letting other work run between groups of units."""
    while True:
        for i, unit in enumerate(units):
            if i and not i % TICK_GROUP:
                await asyncio.sleep(0)
            try:
                unit.tick()
            except Exception:
                log.exception("%s: tick failed", unit.name)
        await asyncio.sleep(period)


def path(steps: Mapping[str, Sequence[tuple[str, str]]], current: str, target: str) -> list[tuple[str, str]]:
    """The fewest ``steps`` (``PackMLTables.steps``) from the innermost state ``current`` to
    ``target``; [] when they are the same or there is no way."""
    if current == target or current not in steps or target not in steps:
        return []
    came: dict[str, tuple[str, tuple[str, str]]] = {}
    queue = [current]
    for state in queue:  # breadth first: the queue grows while it is walked
        for step in steps[state]:
            following = step[1]
            if following in came or following == current:
                continue
            came[following] = (state, step)
            if following == target:
                found = []
                while following != current:
                    before, taken = came[following]
                    found.append(taken)
                    following = before
                return found[::-1]
            queue.append(following)
    return []


def _hosting(states: Iterable[Any], submachine: str) -> str:
    return next(str(s.name) for s in states if s.submachine == submachine)


def _counted(c: PackMLCountDataType, n: int) -> PackMLCountDataType:
    return dataclasses.replace(c, count=_i32(c.count + n), acc_count=_i32(c.acc_count + n))


def _push(items: list[PackMLAlarmDataType], item: PackMLAlarmDataType, extent: int) -> None:
    items.append(item)
    del items[: max(0, len(items) - extent)]
