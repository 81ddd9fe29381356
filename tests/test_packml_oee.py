"""OEE of a PackML unit: exact figures of a scripted run with an injected clock (docs/packml.md, "OEE")."""

from __future__ import annotations

from datetime import UTC, datetime, time

import pytest
from helpers import FakeClock, packml_tables

from uacell.packml import EXECUTE, MACHINE, PackMLUnit
from uacell.packml.equipment import EquipmentBase
from uacell.packml.oee import OEE, parse_shifts, shift_start

MRESET, START, HOLD, UNHOLD = (MACHINE, "Reset"), (EXECUTE, "Start"), (EXECUTE, "Hold"), (EXECUTE, "Unhold")
SUSPEND, UNSUSPEND = (EXECUTE, "Suspend"), (EXECUTE, "Unsuspend")


def scripted_run(window_hours: float) -> PackMLUnit:
    """Stopped 600 s, Resetting 60, Idle 240, Starting 60, Execute 3600 (100 made, 4 bad at 1800 s),
    Suspending 30 + Suspended 1200 + Unsuspending 30 (line loss), Execute 1800 (50 made, 1 bad at
    1200 s), Held 300; design speed 2/min."""
    clock = FakeClock(1000.0)
    unit = PackMLUnit(
        EquipmentBase(), tables=packml_tables(), clock=clock, mach_design_speed=2.0, oee_window_hours=window_hours
    )

    def step(seconds: float, call: tuple[str, str] | None = None, done: bool = False) -> None:
        clock.advance(seconds)
        if call is not None:
            unit.command(call[0], call[1], *(([],) if call == START else ()))
        if done:
            assert unit.state_complete()

    step(600, MRESET)  # Stopped 600
    step(60, done=True)  # Resetting 60 -> Idle
    step(240, START)  # Idle 240
    step(60, done=True)  # Starting 60 -> Execute
    assert unit.state == "Execute"
    clock.advance(1800)
    unit.report_production(processed=100, defective=4)
    step(1800, SUSPEND)  # Execute 3600
    step(30, done=True)  # Suspending 30
    step(1200, UNSUSPEND)  # Suspended 1200
    step(30, done=True)  # Unsuspending 30 -> Execute
    clock.advance(1200)
    unit.report_production(processed=50, defective=1)
    step(600, HOLD)  # Execute 1800
    step(0, done=True)
    step(300, UNHOLD)  # Held 300
    return unit


def test_oee_of_a_scripted_run_over_the_whole_run() -> None:
    f = scripted_run(window_hours=8.0).oee_figures()
    planned = 600 + 60 + 240 + 60 + 3600 + 1800 + 300  # the line's loss (Suspend*) is not planned time
    assert f.planned == pytest.approx(planned) and f.execute == pytest.approx(5400)
    assert f.availability == pytest.approx(5400 / planned)
    assert f.performance == pytest.approx(150 / (2.0 * 5400 / 60))
    assert f.quality == pytest.approx(145 / 150)
    assert f.oee == pytest.approx(5400 / planned * 150 / 180 * 145 / 150)
    assert (f.processed, f.good) == (150, 145)


def test_oee_over_the_last_hour_only() -> None:
    unit = scripted_run(window_hours=1.0)
    f = unit.oee_figures()
    # the run ends at 8920 s: the last hour from 5320 s holds Execute 240, the line's loss 1260,
    # Execute 1800, Held 300
    assert f.execute == pytest.approx(240 + 1800)
    assert f.planned == pytest.approx(240 + 1800 + 300)
    assert (f.processed, f.good) == (50, 49)
    assert f.performance == pytest.approx(50 / (2.0 * 2040 / 60))
    values = unit.values()
    assert values["OEE/Availability"] == round(2040 / 2340, 3)
    assert values["OEE/ProcessedCount"] == 50


def test_oee_zero_denominators_are_zero() -> None:
    f = OEE(120.0).figures(10.0)
    assert (f.availability, f.performance, f.quality, f.oee) == (0.0, 0.0, 0.0, 0.0)


def test_shift_calendar_window() -> None:
    shifts = parse_shifts(["22:00", "06:00", "14:00"])
    assert shifts == (time(6), time(14), time(22))
    assert shift_start(datetime(2026, 1, 2, 5, 0, tzinfo=UTC), shifts) == datetime(2026, 1, 1, 22, 0, tzinfo=UTC)
    oee = OEE(60.0, window_hours=24.0, shifts=shifts)
    # 13:00..14:30 wall time: Execute all along; 10 made before 14:00, 30 after
    wall0 = datetime(2026, 1, 2, 13, 0, tzinfo=UTC)
    oee.span(0.0, 5400.0, 1, "Execute")
    oee.count(1800.0, 10, 0)
    oee.count(4000.0, 30, 3)
    f = oee.figures(5400.0, wall0.replace(hour=14, minute=30))
    assert f.execute == pytest.approx(1800.0)  # since 14:00
    assert (f.processed, f.good) == (30, 27)
    assert f.performance == pytest.approx(30 / (60.0 * 30))  # 60/min over 30 min
    with pytest.raises(ValueError, match="not HH:MM"):
        parse_shifts(["6h"])
