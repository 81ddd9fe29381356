"""The pure PackML model: every (state, command, unit mode), random sequences, the full walk, Start."""

from __future__ import annotations

import contextlib
import math
from typing import Any

import pytest
from helpers import packml_tables
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from uacell.core.errors import CallError
from uacell.core.fsm import Change
from uacell.packml import (
    BASE,
    EXECUTE,
    MACHINE,
    UNIT,
    EquipmentBase,
    EUInformation,
    PackMLDescriptorDataType,
    PackMLIngredientsDataType,
    PackMLProductDataType,
    PackMLRemoteInterfaceDataType,
    PackMLUnit,
)

D = PackMLDescriptorDataType
ABORT, CLEAR = (BASE, "Abort"), (BASE, "Clear")
STOP, MRESET = (MACHINE, "Stop"), (MACHINE, "Reset")
XRESET, START, HOLD, UNHOLD = (EXECUTE, "Reset"), (EXECUTE, "Start"), (EXECUTE, "Hold"), (EXECUTE, "Unhold")
SUSPEND, UNSUSPEND, TOCOMPLETE = (EXECUTE, "Suspend"), (EXECUTE, "Unsuspend"), (EXECUTE, "ToComplete")
MACHINE_METHODS: list[tuple[str | None, str]] = [
    ABORT,
    CLEAR,
    STOP,
    MRESET,
    XRESET,
    START,
    HOLD,
    UNHOLD,
    SUSPEND,
    UNSUSPEND,
    TOCOMPLETE,
]
UNIT_METHODS: list[tuple[str | None, str]] = [
    (UNIT, m) for m in ("SetUnitMode", "SetMachSpeed", "SetProduct", "SetParameter", "RemoteCommand", "SetInterlock")
]
DONE = "done"  # the running acting state completes

# OPC 30050 v1.01 (ISA-TR88) commands per state, typed here on purpose (the model derives it from the NodeSet tables).
ALLOWED_PRODUCE: dict[str, set[tuple[Any, str]]] = {
    "Stopped": {MRESET, ABORT},
    "Resetting": {STOP, ABORT},
    "Idle": {START, STOP, ABORT},
    "Starting": {STOP, HOLD, ABORT},
    "Execute": {STOP, HOLD, SUSPEND, ABORT, TOCOMPLETE},
    "Completing": {STOP, ABORT},
    "Complete": {XRESET, STOP, ABORT},
    "Holding": {STOP, ABORT},
    "Held": {STOP, UNHOLD, ABORT},
    "Unholding": {STOP, HOLD, ABORT},
    "Suspending": {STOP, HOLD, ABORT},
    "Suspended": {STOP, HOLD, UNSUSPEND, ABORT},
    "Unsuspending": {STOP, HOLD, ABORT},
    "Stopping": {ABORT},
    "Clearing": {ABORT},
    "Aborting": set(),
    "Aborted": {CLEAR},
}
# Decision 26.
MODE_DISABLED = {1: set(), 2: {"Suspend"}, 3: {"Start", "Suspend", "Hold", "ToComplete"}}
SET_UNIT_MODE_STATES = {"Stopped", "Idle", "Aborted"}
JOB_STATES = {
    "Starting",
    "Execute",
    "Completing",
    "Holding",
    "Held",
    "Unholding",
    "Suspending",
    "Suspended",
    "Unsuspending",
}

_IDLE = [MRESET, DONE]
_EXECUTE = [*_IDLE, START, DONE]
_HELD = [*_EXECUTE, HOLD, DONE]
_SUSPENDED = [*_EXECUTE, SUSPEND, DONE]
PATHS: dict[str, list[Any]] = {
    "Stopped": [],
    "Aborting": [ABORT],
    "Aborted": [ABORT, DONE],
    "Clearing": [ABORT, DONE, CLEAR],
    "Resetting": [MRESET],
    "Idle": _IDLE,
    "Stopping": [*_IDLE, STOP],
    "Starting": [*_IDLE, START],
    "Execute": _EXECUTE,
    "Completing": [*_EXECUTE, TOCOMPLETE],
    "Complete": [*_EXECUTE, TOCOMPLETE, DONE],
    "Holding": [*_EXECUTE, HOLD],
    "Held": _HELD,
    "Unholding": [*_HELD, UNHOLD],
    "Suspending": [*_EXECUTE, SUSPEND],
    "Suspended": _SUSPENDED,
    "Unsuspending": [*_SUSPENDED, UNSUSPEND],
}


def args_for(method: str) -> tuple[Any, ...]:
    return {
        "Start": ([D(1, "Length", value=12.5)],),
        "SetUnitMode": (1,),
        "SetMachSpeed": (50.0,),
        "SetProduct": ([PackMLProductDataType(7, (D(1, value=1.0),))],),
        "SetParameter": ([D(3, value=3.0)],),
        "RemoteCommand": ([PackMLRemoteInterfaceDataType(2, 5, 400)],),
        "SetInterlock": (0, True),
    }.get(method, ())


def walk(unit: PackMLUnit, steps: list[Any]) -> None:
    for step in steps:
        if step == DONE:
            assert unit.state_complete(), f"nothing to complete in {unit.state}"
        else:
            unit.command(step[0], step[1], *args_for(step[1]))


def snapshot(unit: PackMLUnit) -> tuple[Any, ...]:
    machines = [(m.current, m.active, m.last_transition) for m in unit.machines.values()]
    return (machines, unit.values())


def states(unit: PackMLUnit) -> tuple[str, str | None, str | None]:
    """``unit.states`` read afresh: a call changes it, so no earlier assert on it tells its type."""
    return unit.states


def new_unit(**kw: Any) -> PackMLUnit:
    return PackMLUnit(EquipmentBase(), tables=packml_tables(), **kw)


def test_tables_have_all_26_transitions_and_entry_states() -> None:
    unit = new_unit()
    counts = {name: len(m.table.transitions) for name, m in unit.machines.items()}
    assert counts == {BASE: 3, MACHINE: 4, EXECUTE: 19}
    assert unit.machine.parent_state == "Cleared" and unit.execute.parent_state == "Running"
    # Decision 23: initial Base Cleared / Machine Stopped, Execute inactive.
    assert states(unit) == ("Cleared", "Stopped", None)
    assert unit.acting_state is None


@pytest.mark.parametrize("mode", [1, 2, 3])
@pytest.mark.parametrize("call", MACHINE_METHODS + UNIT_METHODS, ids=lambda c: f"{c[0] or 'Unit'}.{c[1]}")
@pytest.mark.parametrize("state", list(PATHS))
def test_every_state_command_and_mode(state: str, call: tuple[Any, str], mode: int) -> None:
    unit = new_unit()
    walk(unit, PATHS[state])
    assert unit.state == state
    unit.status.unit_mode_current = mode  # modes only change in a few states; set it directly here
    machine_name, method = call
    if machine_name is UNIT:
        expected = {
            "SetUnitMode": state in SET_UNIT_MODE_STATES,
            "SetProduct": state not in JOB_STATES,
            "SetParameter": state not in JOB_STATES,
        }.get(method, True)
    else:
        expected = call in ALLOWED_PRODUCE[state] and method not in MODE_DISABLED[mode]
    assert unit.executable(machine_name, method) is expected
    before = snapshot(unit)
    if not expected:
        with pytest.raises(CallError) as err:
            unit.command(machine_name, method, *args_for(method))
        assert err.value.status == "BadInvalidState"
        assert snapshot(unit) == before  # decision 22: nothing changes
        return
    unit.command(machine_name, method, *args_for(method))
    if machine_name is not UNIT:
        sm = unit.machines[machine_name]
        table_transition = sm.table.caused_by(method, before[0][list(unit.machines).index(machine_name)][0])
        assert table_transition is not None  # the command was allowed: the table has its transition
        assert sm.last_transition == table_transition
        assert sm.current == table_transition.to_state


def test_entering_cleared_starts_at_clearing_and_running_at_resetting() -> None:
    unit = new_unit()
    unit.reset_machine()
    assert states(unit) == ("Cleared", "Running", "Resetting")
    unit.abort()
    assert states(unit) == ("Aborting", None, None)
    unit.state_complete()
    unit.clear()
    assert states(unit) == ("Cleared", "Clearing", None)
    assert unit.status.state_change_in_process and unit.status.state_requested == 2
    unit.state_complete()
    assert states(unit) == ("Cleared", "Stopped", None)
    assert not unit.status.state_change_in_process and unit.status.state_requested == 2


def test_full_walk_with_all_three_machines() -> None:
    unit = new_unit()
    changes: list[Change] = []
    for m in unit.machines.values():
        m.listeners.append(changes.append)
    expected: list[tuple[Any, tuple[str, str | None, str | None]]] = [
        (MRESET, ("Cleared", "Running", "Resetting")),
        (DONE, ("Cleared", "Running", "Idle")),
        (START, ("Cleared", "Running", "Starting")),
        (DONE, ("Cleared", "Running", "Execute")),
        (HOLD, ("Cleared", "Running", "Holding")),
        (DONE, ("Cleared", "Running", "Held")),
        (UNHOLD, ("Cleared", "Running", "Unholding")),
        (DONE, ("Cleared", "Running", "Execute")),
        (SUSPEND, ("Cleared", "Running", "Suspending")),
        (DONE, ("Cleared", "Running", "Suspended")),
        (UNSUSPEND, ("Cleared", "Running", "Unsuspending")),
        (DONE, ("Cleared", "Running", "Execute")),
        (TOCOMPLETE, ("Cleared", "Running", "Completing")),
        (DONE, ("Cleared", "Running", "Complete")),
        (XRESET, ("Cleared", "Running", "Resetting")),
        (DONE, ("Cleared", "Running", "Idle")),
        (STOP, ("Cleared", "Stopping", None)),
        (DONE, ("Cleared", "Stopped", None)),
        (ABORT, ("Aborting", None, None)),
        (DONE, ("Aborted", None, None)),
        (CLEAR, ("Cleared", "Clearing", None)),
        (DONE, ("Cleared", "Stopped", None)),
    ]
    for step, states in expected:
        walk(unit, [step])
        assert unit.states == states, step
    taken = [(c.machine.name, c.transition.name if c.transition else f"enter {c.to_state}") for c in changes]
    assert taken == [
        (MACHINE, "StoppedToRunning"),
        (EXECUTE, "enter Resetting"),
        (EXECUTE, "ResettingToIdle"),
        (EXECUTE, "IdleToStarting"),
        (EXECUTE, "StartingToExecute"),
        (EXECUTE, "ExecuteToHolding"),
        (EXECUTE, "HoldingToHeld"),
        (EXECUTE, "HeldToUnholding"),
        (EXECUTE, "UnholdingToExecute"),
        (EXECUTE, "ExecuteToSuspending"),
        (EXECUTE, "SuspendingToSuspended"),
        (EXECUTE, "SuspendedToUnsuspending"),
        (EXECUTE, "UnsuspendingToExecute"),
        (EXECUTE, "ExecuteToCompleting"),
        (EXECUTE, "CompletingToComplete"),
        (EXECUTE, "CompleteToResetting"),
        (EXECUTE, "ResettingToIdle"),
        (MACHINE, "RunningToStopping"),
        (MACHINE, "StoppingToStopped"),
        (BASE, "ClearedToAborting"),
        (BASE, "AbortingToAborted"),
        (BASE, "AbortedToCleared"),
        (MACHINE, "enter Clearing"),
        (MACHINE, "ClearingToStopped"),
    ]
    assert unit.status.start_parameters == (D(1, "Length", value=12.5),)


def test_acting_state_commands_answered_at_once_not_queued() -> None:
    unit = new_unit()
    walk(unit, [MRESET])  # Resetting runs
    with pytest.raises(CallError):
        unit.start([])  # not queued for Idle
    unit.state_complete()
    assert unit.state == "Idle"  # and Start was not performed afterwards
    unit.start([])
    unit.hold()  # OPC extension StartingToHolding, allowed while Starting runs
    assert unit.state == "Holding"
    assert not unit.state_complete("Starting")  # a stale completion is ignored
    assert unit.state == "Holding"


def test_status_during_acting_states_and_speed() -> None:
    unit = new_unit(mach_speed=80.0)
    walk(unit, [*_IDLE, START])
    assert unit.status.state_change_in_process and unit.status.state_requested == 6
    assert unit.status.cur_mach_speed == 0.0
    unit.state_complete()
    assert not unit.status.state_change_in_process and unit.status.state_requested == 6
    assert unit.status.cur_mach_speed == 80.0
    unit.set_mach_speed(120.0)
    assert unit.status.cur_mach_speed == 120.0
    unit.hold()
    assert unit.status.cur_mach_speed == 0.0 and unit.status.state_requested == 11


def test_change_listener_reports_changed_values_only() -> None:
    unit = new_unit()
    seen: list[dict[str, Any]] = []
    unit.listeners.append(seen.append)
    unit.set_mach_speed(42.0)
    assert seen[-1]["Status/MachSpeed"] == 42.0 and "Status/CurMachSpeed" not in seen[-1]
    unit.reset_machine()
    assert seen[-1]["Status/StateChangeInProcess"] is True
    assert seen[-1]["Executable"][(MACHINE, "Stop")] is True


# --- Start (decision 25) ----------------------------------------------------------------------------


def idle_unit(**kw: Any) -> PackMLUnit:
    unit = new_unit(**kw)
    walk(unit, _IDLE)
    return unit


@pytest.mark.parametrize(
    ("parameters", "status", "fragment"),
    [
        (None, "BadArgumentsMissing", "needs the Parameter"),
        ([D(1, value=1.0), "x"], "BadInvalidArgument", "Parameter[1] is not a PackMLDescriptorDataType"),
        ([D(5, value=1.0), D(5, value=2.0)], "BadInvalidArgument", "Parameter[1].ID 5 is not unique"),
        ([D(1, value=math.nan)], "BadInvalidArgument", "Parameter[0] (ID 1) Value must be a finite Float"),
        ([D(1, value=math.inf)], "BadInvalidArgument", "finite Float"),
        ([D(1, value=1e39)], "BadInvalidArgument", "finite Float"),
        ([D(2**31, value=1.0)], "BadInvalidArgument", "Parameter[0].ID must be an Int32"),
    ],
)
def test_start_argument_errors(parameters: Any, status: str, fragment: str) -> None:
    unit = idle_unit()
    before = snapshot(unit)
    with pytest.raises(CallError) as err:
        unit.start(parameters)
    assert err.value.status == status and fragment in err.value.message
    if status == "BadInvalidArgument":
        assert err.value.argument == 0
    assert snapshot(unit) == before


def test_start_state_errors() -> None:
    unit = new_unit()
    with pytest.raises(CallError, match="not active") as err:
        unit.start([])  # Stopped: Execute is not active
    assert err.value.status == "BadInvalidState"
    unit = idle_unit()
    unit.set_unit_mode(3)
    with pytest.raises(CallError, match="disabled in unit mode Manual"):
        unit.start([])
    unit = idle_unit()
    unit.set_interlock(1, True)
    assert unit.status.material_interlocked and unit.status.material_interlock == [True, False, True, True]
    assert not unit.executable(EXECUTE, "Start")
    with pytest.raises(CallError, match="MaterialInterlocked"):
        unit.start([])
    unit.set_interlock(1, False)
    unit.start([])
    assert unit.state == "Starting"


def test_equipment_may_refuse_start_parameters() -> None:
    class Picky(EquipmentBase):
        def validate_start(self, parameters: Any) -> None:
            for i, p in enumerate(parameters):
                if p.id != 1:
                    raise CallError("BadInvalidArgument", f"Parameter[{i}].ID {p.id} is unknown", argument=0)

    unit = PackMLUnit(Picky(), tables=packml_tables())
    walk(unit, _IDLE)
    before = snapshot(unit)
    with pytest.raises(CallError, match="unknown"):
        unit.start([D(9, value=1.0)])
    assert snapshot(unit) == before


def test_start_parameters_kept_until_next_start() -> None:
    received: list[Any] = []

    class Eq(EquipmentBase):
        def on_starting(self, parameters: Any) -> None:
            received.append(tuple(parameters))

    unit = PackMLUnit(Eq(), tables=packml_tables())
    walk(unit, _IDLE)
    first = [D(1, "Speed", EUInformation(display_name="m/s"), 2.5)]
    unit.start(first)
    assert received == [tuple(first)]
    assert unit.values()["Status/StartParameters"] == first
    unit.stop()
    unit.state_complete()
    unit.abort()
    assert unit.values()["Status/StartParameters"] == first  # kept through Stop and Abort
    unit.state_complete()
    walk(unit, [CLEAR, DONE, MRESET, DONE])
    unit.start([])  # an empty array is fine
    assert unit.values()["Status/StartParameters"] == [] and received[-1] == ()
    assert unit.status.parameter == ()  # Status/Parameter belongs to SetParameter


# --- unit methods (decisions 26, 27) ------------------------------------------------------------------


@pytest.mark.parametrize("mode", [0, 4, -1, True, 1.0])
def test_set_unit_mode_unknown(mode: Any) -> None:
    unit = new_unit()
    with pytest.raises(CallError) as err:
        unit.set_unit_mode(mode)
    assert err.value.status == "BadInvalidArgument" and err.value.argument == 0
    assert unit.unit_mode == 1


def test_set_unit_mode_flags_and_restrictions() -> None:
    unit = new_unit()
    seen: list[dict[str, Any]] = []
    unit.listeners.append(seen.append)
    unit.set_unit_mode(2)
    assert seen[0]["Status/UnitModeChangeInProcess"] is True and seen[0]["Status/UnitModeRequested"] is True
    assert seen[-1]["Status/UnitModeCurrent"] == 2 and seen[-1]["Status/UnitModeChangeInProcess"] is False
    walk(unit, [*_IDLE, START, DONE])
    assert not unit.executable(EXECUTE, "Suspend") and unit.executable(EXECUTE, "Hold")
    with pytest.raises(CallError) as err:
        unit.set_unit_mode(1)  # not in Execute
    assert err.value.status == "BadInvalidState"


def test_set_mach_speed_range() -> None:
    unit = new_unit(mach_speed_range=(10.0, 200.0))
    for bad in (9.99, 200.5, math.nan, -math.inf):
        with pytest.raises(CallError) as err:
            unit.set_mach_speed(bad)
        assert err.value.status == "BadInvalidArgument" and err.value.argument == 0
    unit.set_mach_speed(200.0)
    assert unit.status.mach_speed == 200.0


def test_set_product_and_parameter_validation_and_state() -> None:
    unit = new_unit()
    product = PackMLProductDataType(1, (D(1, value=1.0),), (PackMLIngredientsDataType(10, (D(1, value=2.0),)),))
    unit.set_product([product])
    assert unit.status.product == (product,)
    dup_ingredient = PackMLProductDataType(2, (), (PackMLIngredientsDataType(3), PackMLIngredientsDataType(3)))
    with pytest.raises(CallError, match=r"Product\[0\].Ingredients\[1\].IngredientID 3 is not unique"):
        unit.set_product([dup_ingredient])
    with pytest.raises(CallError, match=r"ProcessVariables\[0\] \(ID 1\) Value"):
        unit.set_product([PackMLProductDataType(3, (D(1, value=math.nan),))])
    with pytest.raises(CallError, match="ProductID 1 is not unique"):
        unit.set_product([product, product])
    assert unit.status.product == (product,)
    unit.set_parameter([D(4, value=4.0)])
    walk(unit, [*_IDLE, START])
    with pytest.raises(CallError) as err:
        unit.set_parameter([D(5, value=5.0)])
    assert err.value.status == "BadInvalidState"
    assert unit.status.parameter == (D(4, value=4.0),)


def test_remote_command_and_interlock() -> None:
    unit = new_unit(interlocks=2)
    cmd = PackMLRemoteInterfaceDataType(2, 5, 400, (D(1, value=1.0),))
    unit.remote_command([cmd])
    assert unit.values()["Status/RemoteParameter"] == [cmd]
    with pytest.raises(CallError, match="Int32"):
        unit.remote_command([PackMLRemoteInterfaceDataType(2**40, 5, 400)])
    for bad_id in (-1, 2, True):
        with pytest.raises(CallError) as err:
            unit.set_interlock(bad_id, True)
        assert err.value.status == "BadInvalidArgument" and err.value.argument == 0


def test_fault_aborts_with_alarm_and_stop_reason() -> None:
    unit = new_unit()
    walk(unit, _EXECUTE)
    unit.fault(17, "jam at infeed", category=1)
    assert states(unit) == ("Aborting", None, None)
    assert [a.id for a in unit.admin.alarm] == [17] and unit.admin.alarm[0].trigger
    assert unit.admin.stop_reason.id == 17 and unit.admin.stop_reason.message == "jam at infeed"
    unit.fault(18, "second fault")  # first out: StopReason stays
    assert unit.admin.stop_reason.id == 17 and len(unit.admin.alarm) == 2
    unit.state_complete()
    unit.clear()
    assert unit.admin.alarm == [] and all(h.ack_date_time is not None for h in unit.admin.alarm_history)


def test_equipment_fault_category_and_failing_hook() -> None:
    class Broken(EquipmentBase):
        def on_starting(self, parameters: Any) -> None:
            raise RuntimeError("PLC unreachable")

    unit = PackMLUnit(Broken(), tables=packml_tables())
    walk(unit, _IDLE)
    unit.start([])  # the hook fails: the unit aborts with an alarm of category 0 naming the error
    assert states(unit) == ("Aborting", None, None)
    (alarm,) = unit.admin.alarm
    assert alarm.category == 0 and "PLC unreachable" in alarm.message
    unit = new_unit()
    unit.fault(5, "guard door")  # what a driver reports through the UnitPort: an equipment fault
    assert unit.admin.alarm[0].category == 1 and unit.admin.stop_reason.category == 1


def test_equipment_reports_warnings_blocked_starved_and_its_own_commands() -> None:
    unit = new_unit(warning_extent=2)
    walk(unit, _EXECUTE)
    for i in (1, 2, 3):
        unit.warning(i, f"low glue {i}")
    assert [w.id for w in unit.admin.warning] == [2, 3] and all(w.trigger for w in unit.admin.warning)
    unit.warning(2, "", active=False)
    assert [w.id for w in unit.admin.warning] == [3]
    assert unit.state == "Execute" and unit.admin.alarm == []  # warnings never stop the unit
    unit.set_blocked(True)
    unit.set_starved(True)
    assert unit.values()["Status/EquipmentBlocked"] is True and unit.values()["Status/EquipmentStarved"] is True
    unit.equipment_command("Suspend")  # e.g. starved: the same transition as the client's Suspend
    last = unit.execute.last_transition
    assert unit.state == "Suspending" and last is not None and last.name == "ExecuteToSuspending"
    with pytest.raises(CallError) as err:
        unit.equipment_command("Unhold")  # the same state rules as for clients
    assert err.value.status == "BadInvalidState" and unit.state == "Suspending"
    unit.state_complete()
    unit.equipment_command("Unsuspend")
    unit.state_complete()
    unit.equipment_command("ToComplete")
    assert unit.state == "Completing"


def test_commanded_stop_reason() -> None:
    unit = new_unit()
    walk(unit, _EXECUTE)
    unit.hold()
    assert unit.admin.stop_reason.id == 4 and unit.admin.stop_reason.message == "Hold commanded"
    unit.stop()  # first out: the Hold remains the reason
    assert unit.admin.stop_reason.id == 4


# --- random sequences -------------------------------------------------------------------------------

ACTIONS = st.one_of(
    st.sampled_from(MACHINE_METHODS),
    st.just(DONE),
    st.tuples(st.just(UNIT), st.just("SetUnitMode"), st.integers(0, 4)),
    st.tuples(st.just("fault"), st.integers(1, 5)),
)
WAIT_STATES = {"Stopped", "Idle", "Execute", "Complete", "Held", "Suspended", "Aborted"}


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(ACTIONS, max_size=40))
def test_random_command_sequences(actions: list[Any]) -> None:
    unit = new_unit()
    for action in actions:
        before = snapshot(unit)
        if action == DONE:
            acting = unit.acting_state
            assert unit.state_complete() is (acting is not None)
            if acting is None:
                assert snapshot(unit) == before
        elif action[0] == "fault":
            could_abort = unit.executable(BASE, "Abort")
            unit.fault(action[1], "fault")
            assert unit.base.current == ("Aborting" if could_abort else before[0][0][0])
        else:
            machine_name, method = action[0], action[1]
            args = (action[2],) if len(action) == 3 else args_for(method)
            executable = unit.executable(machine_name, method)
            try:
                unit.command(machine_name, method, *args)
            except CallError as err:
                assert err.status in {"BadInvalidState", "BadInvalidArgument"}
                assert not executable or err.status == "BadInvalidArgument"
                assert snapshot(unit) == before  # a refused command changes nothing
            else:
                assert executable
        check_invariants(unit)
    # Acting states always complete: completing repeatedly reaches a wait state.
    for _ in range(5):
        if unit.acting_state is None:
            break
        assert unit.state_complete()
    assert unit.acting_state is None and unit.state in WAIT_STATES


def check_invariants(unit: PackMLUnit) -> None:
    base, machine, execute = unit.states
    assert (machine is not None) == (base == "Cleared")
    assert (execute is not None) == (machine == "Running")
    assert unit.state not in ("Cleared", "Running")  # composite states are never the unit's state
    assert unit.status.state_change_in_process == (unit.acting_state is not None)
    expected_speed = unit.status.mach_speed if unit.state == "Execute" else 0.0
    assert unit.status.cur_mach_speed == expected_speed
    if unit.unit_mode == 3:
        assert unit.state in {"Stopped", "Idle", "Aborted", "Aborting", "Clearing", "Stopping", "Resetting"}


def test_docs_transition_numbers_match_the_tables() -> None:
    from pathlib import Path

    doc = (Path(__file__).parent.parent / "docs" / "packml.md").read_text(encoding="utf-8")
    machines = {"Base": BASE, "Machine": MACHINE, "Execute": EXECUTE}
    unit = new_unit()
    rows = [
        line.split("|")[1:6]
        for line in doc.splitlines()
        if line.split("|")[1:2] in ([" Base "], [" Machine "], [" Execute "])
    ]
    documented = {(machines[m.strip()], name.strip()): int(n) for m, n, name, *_ in rows if n.strip().isdigit()}
    actual = {
        (name, t): sm.table.transition_number(t) for name, sm in unit.machines.items() for t in sm.table.transitions
    }
    assert documented == actual


# The 26 transitions of OPC 30050 v1.01 (from -> to), typed here to check the NodeSet.
SPEC_TRANSITIONS = {
    BASE: {
        "ClearedToAborting": ("Cleared", "Aborting"),
        "AbortingToAborted": ("Aborting", "Aborted"),
        "AbortedToCleared": ("Aborted", "Cleared"),
    },
    MACHINE: {
        "ClearingToStopped": ("Clearing", "Stopped"),
        "StoppedToRunning": ("Stopped", "Running"),
        "RunningToStopping": ("Running", "Stopping"),
        "StoppingToStopped": ("Stopping", "Stopped"),
    },
    EXECUTE: {
        "ResettingToIdle": ("Resetting", "Idle"),
        "IdleToStarting": ("Idle", "Starting"),
        "StartingToExecute": ("Starting", "Execute"),
        "ExecuteToSuspending": ("Execute", "Suspending"),
        "SuspendingToSuspended": ("Suspending", "Suspended"),
        "SuspendedToUnsuspending": ("Suspended", "Unsuspending"),
        "UnsuspendingToExecute": ("Unsuspending", "Execute"),
        "ExecuteToHolding": ("Execute", "Holding"),
        "HoldingToHeld": ("Holding", "Held"),
        "HeldToUnholding": ("Held", "Unholding"),
        "UnholdingToExecute": ("Unholding", "Execute"),
        "ExecuteToCompleting": ("Execute", "Completing"),
        "CompletingToComplete": ("Completing", "Complete"),
        "CompleteToResetting": ("Complete", "Resetting"),
        "StartingToHolding": ("Starting", "Holding"),
        "UnsuspendingToHolding": ("Unsuspending", "Holding"),
        "SuspendedToHolding": ("Suspended", "Holding"),
        "SuspendingToHolding": ("Suspending", "Holding"),
        "UnholdingToHolding": ("Unholding", "Holding"),
    },
}


def test_all_26_transitions_come_from_the_nodeset_and_are_taken() -> None:
    unit = new_unit()
    tables = {
        name: {t.name: (t.from_state, t.to_state) for t in m.table.transitions.values()}
        for name, m in unit.machines.items()
    }
    assert tables == SPEC_TRANSITIONS
    taken: dict[str, set[str]] = {name: set() for name in unit.machines}

    def record(c: Change) -> None:
        if c.transition:
            taken[c.machine.name].add(c.transition.name)

    for state, path in PATHS.items():
        for step in [DONE, *sorted(ALLOWED_PRODUCE[state], key=str)]:
            if step == DONE and state not in {
                "Aborting",
                "Clearing",
                "Resetting",
                "Starting",
                "Completing",
                "Holding",
                "Unholding",
                "Suspending",
                "Unsuspending",
                "Stopping",
            }:
                continue
            unit = new_unit()
            walk(unit, path)
            for m in unit.machines.values():
                m.listeners.append(record)
            walk(unit, [step])
    assert taken == {name: set(ts) for name, ts in SPEC_TRANSITIONS.items()}


def test_equipment_changes_the_unit_mode_and_the_active_alarms_by_itself() -> None:
    unit = new_unit()
    walk(unit, _EXECUTE)
    seen: list[dict[str, Any]] = []
    unit.listeners.append(seen.append)
    assert unit.equipment_unit_mode(2) is True  # Maintenance, from the PLC's panel: no uacell rule asked
    assert unit.status.unit_mode_current == 2 and any(c.get("Status/UnitModeCurrent") == 2 for c in seen)
    assert unit.equipment_unit_mode(99) is False and unit.status.unit_mode_current == 2  # not a supported mode
    assert unit.equipment_unit_mode(True) is False
    unit.equipment_alarms({31: "PLC alarm 31", 32: "PLC alarm 32"})
    assert [(a.id, a.message, a.trigger) for a in unit.admin.alarm] == [
        (31, "PLC alarm 31", True),
        (32, "PLC alarm 32", True),
    ]
    assert [h.id for h in unit.admin.alarm_history][-2:] == [31, 32]
    unit.equipment_alarms({32: "PLC alarm 32"})  # 31 went: acknowledged in the history, gone from Alarm
    assert [a.id for a in unit.admin.alarm] == [32]
    (h31,) = [h for h in unit.admin.alarm_history if h.id == 31]
    assert h31.ack_date_time is not None and h31.trigger is False
    history = list(unit.admin.alarm_history)
    unit.equipment_alarms({32: "PLC alarm 32"})  # the same set: nothing changes
    assert unit.admin.alarm_history == history and unit.state == "Execute"  # alarms alone do not stop it


def test_conditions_the_equipment_declares() -> None:
    """An equipment's ``condition_names`` become the unit's alarm conditions (decision 45): raised and
    cleared by the equipment, acknowledged once per raise, with OPC 10000-9's status codes."""

    class Linked(EquipmentBase):
        condition_names = ("CommunicationLost",)

    unit = PackMLUnit(Linked(), tables=packml_tables())
    heard: list[tuple[str, bool, bool]] = []
    unit.conditions.condition_listeners.append(lambda c: heard.append((c.name, c.active, c.acked)))
    cond = unit.conditions.conditions["CommunicationLost"]
    assert (cond.active, cond.acked, cond.enabled) == (False, True, True)
    unit.equipment_condition("CommunicationLost", True, "no answer from the PLC")
    assert (cond.active, cond.acked, cond.message) == (True, False, "no answer from the PLC")
    unit.conditions.acknowledge("CommunicationLost", "cable checked")
    assert (cond.acked, cond.comment) == (True, "cable checked")
    with pytest.raises(CallError) as again:
        unit.conditions.acknowledge("CommunicationLost")
    assert again.value.status == "BadConditionBranchAlreadyAcked"
    with pytest.raises(CallError) as unknown:
        unit.conditions.acknowledge("Nope")
    assert unknown.value.status == "BadNodeIdUnknown"
    unit.equipment_condition("CommunicationLost", False, "the PLC answers")
    assert heard == [
        ("CommunicationLost", True, False),
        ("CommunicationLost", True, True),
        ("CommunicationLost", False, True),
    ]
    assert new_unit().conditions.conditions == {}  # a unit whose equipment declares none has none


def test_tr88_paths_from_the_nodeset_take_the_fewest_steps() -> None:
    """The steps between innermost states come from the NodeSet's transitions (entry states of
    decision 23); a gateway follows its PLC along the fewest of them."""
    from uacell.packml.model import COMPLETE, path

    graph = packml_tables().steps()
    assert len(graph) == 17  # every TR88 state
    assert set(graph["Clearing"]) == {(COMPLETE, "Stopped"), ("Abort", "Aborting")}  # Cleared's Abort, its end
    assert set(graph["Stopped"]) == {("Reset", "Resetting"), ("Abort", "Aborting")}  # Running's entry state

    assert path(graph, "Stopped", "Execute") == [
        ("Reset", "Resetting"), (COMPLETE, "Idle"), ("Start", "Starting"), (COMPLETE, "Execute"),
    ]  # fmt: skip
    assert path(graph, "Resetting", "Stopping") == [("Stop", "Stopping")]  # not through Idle
    assert path(graph, "Execute", "Aborted") == [("Abort", "Aborting"), (COMPLETE, "Aborted")]
    assert path(graph, "Held", "Execute") == [("Unhold", "Unholding"), (COMPLETE, "Execute")]
    assert path(graph, "Complete", "Idle") == [("Reset", "Resetting"), (COMPLETE, "Idle")]
    assert path(graph, "Idle", "Idle") == [] and path(graph, "Idle", "Nowhere") == []
    # every state reaches every other (the PLC may be anywhere when uacell starts)
    for a in graph:
        for b in graph:
            steps = path(graph, a, b)
            assert (steps == []) == (a == b), (a, b)
            state = a
            for action, following in steps:
                assert (action, following) in graph[state]
                state = following
            assert state == b


# --- publishing what an operation touched (decision 47) --------------------------------------------


class HeldWriter:
    """An Admin writer that stores only when told (``flush``): saves become durable later, as on a
    writer thread."""

    def __init__(self) -> None:
        self.queue: list[tuple[Any, dict[str, Any], Any]] = []

    def submit(self, store: Any, data: dict[str, Any], done: Any) -> None:
        self.queue.append((store, data, done))

    def flush(self) -> None:
        queue, self.queue = self.queue, []
        for store, data, done in queue:
            store.save(data)
            done(None)


PUBLISH_ACTIONS = st.one_of(
    st.sampled_from(MACHINE_METHODS),
    st.just(DONE),
    st.tuples(st.just("speed"), st.floats(0.0, 600.0)),
    st.tuples(st.just("product"), st.integers(1, 3)),
    st.tuples(st.just("parameter"), st.integers(1, 3)),
    st.tuples(st.just("remote"), st.integers(1, 3)),
    st.tuples(st.just("produce"), st.integers(1, 5)),
    st.tuples(st.just("interlock"), st.integers(0, 3), st.booleans()),
    st.tuples(st.just("tick"), st.floats(0.0, 2.5)),
    st.tuples(st.just("mode"), st.integers(1, 3)),
    st.just("flush"),
    st.tuples(st.just("fault"), st.integers(1, 5)),
)


def _twin(tmp: Any, clock: Any, everything: bool) -> tuple[PackMLUnit, HeldWriter, dict[str, Any]]:
    """A unit with a held Admin writer, and what its listeners were told (applied in order); with
    ``everything`` it publishes as before decision 47: every value rebuilt and compared."""
    from datetime import UTC, datetime, timedelta

    from uacell.packml.admin_store import AdminStore

    writer = HeldWriter()
    store = AdminStore(tmp / f"Filler1-{everything}.json", writer=writer)  # type: ignore[arg-type]
    start = datetime(2026, 11, 26, tzinfo=UTC)
    unit = new_unit(store=store, clock=clock, wall_clock=lambda: start + timedelta(seconds=clock()))
    if everything:
        unit.publishing.everything = True
    seen = unit.values()
    unit.listeners.append(seen.update)
    return unit, writer, seen


def _act(unit: PackMLUnit, writer: HeldWriter, clock: Any, action: Any) -> bool:
    """Do ``action``; True if it publishes everything it changed (a full operation)."""
    if action == DONE:
        unit.state_complete()
    elif action == "flush":
        writer.flush()
        return False
    elif action[0] == "speed":
        unit.set_mach_speed(action[1])
        return False
    elif action[0] in ("product", "parameter", "remote"):
        n = action[1]
        call = {
            "product": lambda: unit.set_product([PackMLProductDataType(n, (D(n, value=1.0),))]),
            "parameter": lambda: unit.set_parameter([D(n, value=float(n))]),
            "remote": lambda: unit.remote_command([PackMLRemoteInterfaceDataType(n, 5, 400, (D(n, value=2.0),))]),
        }[action[0]]
        with contextlib.suppress(CallError):  # SetProduct and SetParameter only between jobs
            call()
        return False
    elif action[0] == "produce":
        unit.report_production(action[1], 1, 2)
    elif action[0] == "interlock":
        unit.set_interlock(action[1], action[2])
    elif action[0] == "mode":
        with contextlib.suppress(CallError):
            unit.set_unit_mode(action[1])
    elif action[0] == "tick":
        unit.tick()
        return False
    elif action[0] == "fault":
        unit.fault(action[1], "fault")
    else:
        with contextlib.suppress(CallError):
            unit.command(action[0], action[1], *args_for(action[1]))
    return True


@settings(max_examples=120, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(st.lists(PUBLISH_ACTIONS, max_size=40))
def test_published_changes_add_up_to_the_values(tmp_path_factory: Any, actions: list[Any]) -> None:
    """Clients see the same values whether an operation publishes only what it touched (SetMachSpeed,
    SetProduct, SetParameter, RemoteCommand; decision 47) or every value is rebuilt and compared, as
    before: two units driven alike, one publishing everything. The OEE figures are exempt between
    whole seconds: they are published with the Admin times, and by every operation that publishes
    everything. Saves become durable only when the writer is flushed (decision 28 holds for both)."""
    from helpers import FakeClock

    tmp, clock = tmp_path_factory.mktemp("admin"), FakeClock()
    unit, writer, seen = _twin(tmp, clock, everything=False)
    twin, twin_writer, twin_seen = _twin(tmp, clock, everything=True)
    oee = set(unit.oee_values())
    for action in actions:
        if action[0] == "tick":
            clock.advance(action[1])
        full = _act(unit, writer, clock, action)
        _act(twin, twin_writer, clock, action)
        expected = twin_seen if full else {k: v for k, v in twin_seen.items() if k not in oee}
        assert {k: seen[k] for k in expected} == expected, action
    assert unit.values() == twin.values()
