"""The simulated PackML unit on a fake clock (and once on the real event loop)."""

from __future__ import annotations

import asyncio
import contextlib

import pytest
from helpers import FakeClock, packml_tables, wait_until

from uacell.packml import PackMLDescriptorDataType, PackMLUnit, SimulatedUnit
from uacell.packml.equipment import EquipmentBase
from uacell.packml.model import run_units


def states(unit: PackMLUnit) -> tuple[str, str | None, str | None]:
    """``unit.states`` read afresh: a call changes it, so no earlier assert on it tells its type."""
    return unit.states


def sim_unit(**sim_kw: object) -> tuple[PackMLUnit, SimulatedUnit, FakeClock]:
    clock = FakeClock(1000.0)
    sim = SimulatedUnit(**{"acting_time": 0.5, **sim_kw})  # type: ignore[arg-type]
    unit = PackMLUnit(sim, tables=packml_tables(), clock=clock, mach_speed=120.0)
    return unit, sim, clock


def advance(unit: PackMLUnit, clock: FakeClock, seconds: float, step: float = 0.1) -> None:
    end = clock.now + seconds
    while clock.now < end - 1e-9:
        clock.now = min(end, clock.now + step)
        unit.tick()


def test_acting_states_take_the_configured_time() -> None:
    unit, _sim, clock = sim_unit(acting_times={"Starting": 2.0})
    unit.reset_machine()
    advance(unit, clock, 0.4)
    assert unit.state == "Resetting"
    advance(unit, clock, 0.1)
    assert unit.state == "Idle"
    unit.start([PackMLDescriptorDataType(1, "Batch", value=7.0)])
    advance(unit, clock, 1.9)
    assert unit.state == "Starting"
    advance(unit, clock, 0.1)
    assert unit.state == "Execute"


def test_production_counts_at_mach_speed() -> None:
    unit, sim, clock = sim_unit(defect_share=0.1, consumed_per_package=2.0)
    unit.reset_machine()
    advance(unit, clock, 0.5)
    unit.start([PackMLDescriptorDataType(1, "Batch", value=7.0)])
    assert sim.start_parameters == (PackMLDescriptorDataType(1, "Batch", value=7.0),)
    advance(unit, clock, 0.5)
    assert unit.state == "Execute"
    advance(unit, clock, 10.0)  # 120 packages/min for 10 s
    a = unit.admin
    assert a.prod_processed_count[0].count == 20
    assert a.prod_defective_count[0].count == 2
    assert a.prod_consumed_count[0].count == 40
    unit.hold()
    advance(unit, clock, 5.0)
    assert unit.state == "Held" and a.prod_processed_count[0].count == 20  # no production outside Execute
    unit.unhold()
    advance(unit, clock, 0.5)
    unit.set_mach_speed(60.0)
    advance(unit, clock, 10.0)
    assert a.prod_processed_count[0].count == 30 and a.prod_processed_count[0].acc_count == 30


def test_job_size_completes_the_job() -> None:
    unit, _sim, clock = sim_unit(job_size=5)
    unit.reset_machine()
    advance(unit, clock, 0.5)
    unit.start([])
    advance(unit, clock, 0.5 + 2.5)  # 5 packages at 120/min
    assert unit.state in ("Completing", "Complete")
    advance(unit, clock, 0.5)
    assert unit.state == "Complete" and unit.admin.prod_processed_count[0].count == 5


def test_stop_while_starting_cancels_the_pending_completion() -> None:
    unit, _sim, clock = sim_unit()
    unit.reset_machine()
    advance(unit, clock, 0.5)
    unit.start([])
    advance(unit, clock, 0.3)
    unit.stop()
    advance(unit, clock, 0.3)
    assert states(unit) == ("Cleared", "Stopping", None)
    advance(unit, clock, 0.3)
    assert states(unit) == ("Cleared", "Stopped", None)


def test_injected_fault_aborts_with_alarm() -> None:
    unit, sim, clock = sim_unit()
    unit.reset_machine()
    advance(unit, clock, 0.5)
    unit.start([])
    advance(unit, clock, 0.5)
    sim.inject_fault(42, "bottle jam")
    assert states(unit) == ("Aborting", None, None)
    advance(unit, clock, 0.5)
    assert states(unit) == ("Aborted", None, None)
    a = unit.admin
    assert (a.stop_reason.id, a.stop_reason.message, a.stop_reason.category) == (42, "bottle jam", 1)
    assert [(x.id, x.trigger) for x in a.alarm] == [(42, True)]
    assert a.alarm_history[-1].id == 42
    unit.clear()
    assert sim.fault_active is None and a.alarm == []
    advance(unit, clock, 0.5)
    assert states(unit) == ("Cleared", "Stopped", None)


def test_admin_times_follow_states() -> None:
    unit, _sim, clock = sim_unit()
    advance(unit, clock, 5.0)  # Stopped (2) in Produce (1)
    unit.reset_machine()
    advance(unit, clock, 0.5)  # Resetting
    advance(unit, clock, 3.0)  # Idle (4)
    a = unit.admin
    assert a.state_cumulative_time[1][2] == 5
    assert a.state_cumulative_time[1][4] == 3
    assert a.state_current_time[1][4] == 3 and sum(map(sum, a.state_current_time)) == 3
    assert a.mode_cumulative_time[1] == 8 and a.mode_current_time[1] == 8
    assert a.acc_time_since_reset == 8
    unit.set_unit_mode(2)
    advance(unit, clock, 2.0)
    assert a.mode_current_time == [0, 0, 2, 0] and a.mode_cumulative_time[2] == 2
    assert a.state_cumulative_time[2][4] == 2
    unit.reset_counters()
    assert a.acc_time_since_reset == 0 and a.mode_cumulative_time == [0, 0, 0, 0]


@pytest.mark.asyncio
async def test_real_time_run_loop() -> None:
    unit = PackMLUnit(SimulatedUnit(acting_time=0.01), tables=packml_tables())
    task = asyncio.create_task(unit.run(period=0.002))
    try:
        unit.reset_machine()
        for _ in range(200):
            await asyncio.sleep(0.002)
            if unit.state == "Idle":
                break
        assert unit.state == "Idle"
    finally:
        task.cancel()


@pytest.mark.asyncio
async def test_one_run_loop_ticks_every_unit() -> None:
    clock = FakeClock(10.0)
    units = [PackMLUnit(SimulatedUnit(acting_time=1.0), tables=packml_tables(), name=n, clock=clock) for n in "AB"]
    task = asyncio.create_task(run_units(units, period=0.002))
    try:
        for unit in units:
            unit.reset_machine()
        clock.advance(1.0)  # the acting states end on the units' own clock, at the next tick of each
        for _ in range(500):
            await asyncio.sleep(0.002)
            if all(u.state == "Idle" for u in units):
                break
        assert [u.state for u in units] == ["Idle", "Idle"]
        assert [u.admin.acc_time_since_reset for u in units] == [1, 1]
    finally:
        task.cancel()


def test_timers_across_mode_changes() -> None:
    unit, _sim, clock = sim_unit()
    unit.reset_machine()
    advance(unit, clock, 0.5)
    advance(unit, clock, 4.0)  # Idle (4) in Produce (1)
    a = unit.admin
    assert a.state_current_time[1][4] == 4 and a.mode_current_time[1] == 4
    unit.set_unit_mode(1)  # the mode it already has: not a change, the current times keep running
    advance(unit, clock, 1.0)
    assert a.state_current_time[1][4] == 5 and a.mode_current_time[1] == 5
    unit.set_unit_mode(3)  # a real change: time in the new mode (and in the state within it) starts at 0
    advance(unit, clock, 2.0)
    assert a.mode_current_time == [0, 0, 0, 2] and a.state_current_time[3][4] == 2
    assert sum(map(sum, a.state_current_time)) == 2
    assert a.state_cumulative_time[1][4] == 5 and a.state_cumulative_time[3][4] == 2
    assert a.mode_cumulative_time[1] == 5 and a.mode_cumulative_time[3] == 2
    unit.stop()  # Idle -> Stopping -> Stopped in Manual
    advance(unit, clock, 0.5)
    advance(unit, clock, 1.0)
    assert a.state_current_time[3][2] == 1 and a.state_cumulative_time[3][7] == 0  # Stopping took 0.5 s
    assert a.mode_current_time[3] == 3 and a.acc_time_since_reset == 9


def _seen(unit: PackMLUnit) -> tuple[object, ...]:
    a = unit.admin
    return (
        unit.state, a.acc_time_since_reset, a.state_current_time, a.state_cumulative_time, a.mode_cumulative_time,
        a.prod_processed_count[0].count, unit.status.cur_mach_speed,
    )  # fmt: skip


def test_a_waiting_unit_skips_the_ticks_that_would_change_nothing() -> None:
    """``run_units`` skips a unit until its ``quiet_until``: the same states, times and counts at
    every step as a unit ticked at every step, with about three ticks a second while it waits."""
    every, _sim, every_clock = sim_unit(acting_time=0.35)
    quiet, _sim2, quiet_clock = sim_unit(acting_time=0.35)
    ticks = {"every": 0, "quiet": 0}

    def run(seconds: float, step: float = 0.1) -> None:
        end = every_clock.now + seconds
        while every_clock.now < end - 1e-9:
            every_clock.now = quiet_clock.now = min(end, every_clock.now + step)
            every.tick()
            ticks["every"] += 1
            if quiet.quiet_until <= quiet.now():  # run_units' rule
                quiet.tick()
                ticks["quiet"] += 1
            assert _seen(quiet) == _seen(every), every_clock.now

    def both(command: str, *args: object) -> None:
        getattr(every, command)(*args)
        getattr(quiet, command)(*args)

    run(0.05)
    both("reset_machine")
    run(1.0)
    assert quiet.state == "Idle"
    ticks.update(every=0, quiet=0)
    run(20.0)  # waiting in Idle
    assert ticks["every"] == 200 and ticks["quiet"] <= 80, ticks
    both("start")
    run(10.0)  # Starting, then producing in Execute: every tick
    assert quiet.state == "Execute" and quiet.admin.prod_processed_count[0].count == 19
    both("set_mach_speed", 60.0)
    run(5.0)
    both("stop")
    run(3.0)
    assert quiet.state == "Stopped"


@pytest.mark.asyncio
async def test_run_units_ticks_only_the_units_with_something_due() -> None:
    clock = FakeClock(10.0)  # never moves: a waiting unit's next whole second never comes
    waiting = PackMLUnit(SimulatedUnit(acting_time=0.0), tables=packml_tables(), name="Waiting", clock=clock)
    plain = PackMLUnit(EquipmentBase(), tables=packml_tables(), name="Plain", clock=clock)  # says nothing
    ticks = {"Waiting": 0, "Plain": 0}
    for unit in (waiting, plain):
        original = unit.tick

        def counted(unit: PackMLUnit = unit, original: object = original) -> None:
            ticks[unit.name] += 1
            original()  # type: ignore[operator]

        unit.tick = counted  # type: ignore[method-assign]
    task = asyncio.create_task(run_units([waiting, plain], period=0.001))
    try:
        await wait_until(lambda: ticks["Plain"] >= 30)
        assert ticks["Waiting"] == 1  # its first tick said: nothing before the next whole second
        waiting.reset_machine()  # an operation: ticked at the next round (Resetting ends at once)
        await wait_until(lambda: waiting.state == "Idle", timeout=10)
        assert ticks["Waiting"] >= 2
    finally:
        task.cancel()
        with contextlib.suppress(asyncio.CancelledError):
            await task
