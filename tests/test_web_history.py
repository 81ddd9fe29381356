"""The history view's pure parts: the state timeline of nested machines and a robot's program runs."""

from __future__ import annotations

from uacell.web.history import Segment, program_runs, timeline


def test_timeline_takes_the_innermost_active_machine() -> None:
    base = [(0.0, "Cleared")]
    machine = [(0.0, "Stopped"), (10.0, "Running"), (40.0, "Stopping"), (42.0, "Stopped")]
    execute = [(0.0, None), (10.0, "Resetting"), (12.0, "Idle"), (20.0, "Execute"), (40.0, None)]
    got = timeline([base, machine, execute], 5.0, 50.0)
    assert got == [
        Segment("Stopped", 5.0, 10.0),
        Segment("Resetting", 10.0, 12.0),
        Segment("Idle", 12.0, 20.0),
        Segment("Execute", 20.0, 40.0),
        Segment("Stopping", 40.0, 42.0),
        Segment("Stopped", 42.0, 50.0),
    ]
    assert got[3].json()["seconds"] == 20.0


def test_timeline_before_any_value_is_empty_and_equal_states_merge() -> None:
    assert timeline([[(10.0, "Idle"), (20.0, "Idle")]], 0.0, 30.0) == [Segment("Idle", 10.0, 30.0)]
    assert timeline([[]], 0.0, 30.0) == []


def test_program_runs_are_the_executing_spans_named_by_the_loaded_program() -> None:
    states = [(0.0, "Idle"), (5.0, "Ready"), (10.0, "Executing"), (25.0, "Ready"), (30.0, "Executing")]
    programs = [(0.0, ""), (4.0, "pick.robot"), (28.0, "place.robot")]
    assert program_runs(states, programs, 0.0, 40.0) == [
        Segment("pick.robot", 10.0, 25.0),
        Segment("place.robot", 30.0, 40.0),
    ]
