"""Robot remote-operation signals (pure): preconditions, writes, pulse ends and confirmations."""

from __future__ import annotations

from dataclasses import replace

import pytest

from uacell.core.errors import CallError
from uacell.gateway.handshake import Write
from uacell.gateway.signals import DEFAULT_MAP, RobotStatus, SignalOp

READY = RobotStatus(remote_ready=True, drives_are_on=True, program_echo=3, at_start=True)


def test_default_map_has_no_address_twice_in_a_table() -> None:
    seen = [(table, address) for table, address, _ in DEFAULT_MAP.values()]
    assert len(seen) == len(set(seen))


def test_load_writes_number_then_strobe_confirmed_by_echo() -> None:
    op = SignalOp.load(7, READY, now=0.0, timeout=1.0, pulse_width=0.2)
    assert op.writes == (Write("program_number", 7), Write("program_strobe", True))
    assert op.pulse_end(0.1) == ()
    assert op.observe(READY, 0.1) is False  # echo still 3
    assert op.pulse_end(0.2) == (Write("program_strobe", False),)
    assert op.pulse_end(0.3) == ()  # only once
    assert op.observe(RobotStatus(remote_ready=True, drives_are_on=True, program_echo=7), 0.3) is True


def test_load_by_name_writes_the_string_tag_confirmed_by_the_names_echo() -> None:
    op = SignalOp.load("PICK01", READY, now=0.0, timeout=1.0, pulse_width=0.2)
    assert op.writes == (Write("program_name", "PICK01"), Write("program_strobe", True))
    assert op.observe(RobotStatus(remote_ready=True, program_echo=3, program_name_echo="PICK0"), 0.1) is False
    assert op.observe(RobotStatus(remote_ready=True, program_name_echo="PICK01"), 0.2) is True
    for bad in ("", "Größe"):
        with pytest.raises(CallError) as err:
            SignalOp.load(bad, READY, now=0.0, timeout=1.0, pulse_width=0.2)
        assert err.value.status == "BadInvalidArgument"
    # a program selected by name only counts as selected for Start
    named = RobotStatus(remote_ready=True, drives_are_on=True, program_name_echo="PICK01")
    assert SignalOp.start(named, now=0.0, timeout=1.0, pulse_width=0.2).writes == (Write("start", True),)


def test_start_stop_and_the_pulse_ended_on_confirmation() -> None:
    op = SignalOp.start(READY, now=0.0, timeout=1.0, pulse_width=0.5)
    assert op.writes == (Write("start", True),)
    running = RobotStatus(remote_ready=True, drives_are_on=True, program_echo=3, running=True)
    assert op.observe(running, 0.05) is True
    assert op.pulse_end(0.05) == (Write("start", False),)  # ended early: confirmed
    stop = SignalOp.stop(running, now=1.0, timeout=1.0, pulse_width=0.1)
    assert stop.observe(running, 1.5) is False
    assert stop.observe(READY, 1.6) is True


@pytest.mark.parametrize(
    ("status", "needs"),
    [
        (RobotStatus(drives_are_on=True, program_echo=3), "remote ready"),
        (RobotStatus(remote_ready=True, program_echo=3), "drives on"),
        (RobotStatus(remote_ready=True, drives_are_on=True), "a selected program"),
        (RobotStatus(remote_ready=True, drives_are_on=True, program_echo=3, fault=True), "no fault"),
    ],
)
def test_start_refused_names_what_is_missing(status: RobotStatus, needs: str) -> None:
    with pytest.raises(CallError, match=needs) as err:
        SignalOp.start(status, now=0.0, timeout=1.0, pulse_width=0.1)
    assert err.value.status == "BadInvalidState"


def test_timeout_fault_and_lost_connection_end_the_operation() -> None:
    op = SignalOp.start(READY, now=0.0, timeout=1.0, pulse_width=5.0)
    with pytest.raises(CallError, match="running still False, not True, after 1 s") as late:
        op.observe(READY, 1.0)
    assert late.value.status == "BadTimeout"
    assert op.pulse_end(1.0) == (Write("start", False),)  # nothing left set after a timeout
    op = SignalOp.start(READY, now=0.0, timeout=1.0, pulse_width=0.1)
    with pytest.raises(CallError, match="fault 42") as fault:
        op.observe(RobotStatus(remote_ready=True, drives_are_on=True, fault=True, fault_code=42), 0.1)
    assert fault.value.status == "BadInvalidState"
    op = SignalOp.load(2, READY, now=0.0, timeout=1.0, pulse_width=0.1)
    with pytest.raises(CallError) as lost:
        op.observe(RobotStatus(connected=False), 0.1)
    assert lost.value.status == "BadCommunicationError"
    with pytest.raises(CallError) as no_conn:
        SignalOp.stop(RobotStatus(connected=False), now=0.0, timeout=1.0, pulse_width=0.1)
    assert no_conn.value.status == "BadCommunicationError"


def test_reset_waits_while_the_fault_is_still_set() -> None:
    faulted = RobotStatus(remote_ready=True, fault=True, fault_code=9)
    op = SignalOp.reset(faulted, now=0.0, timeout=1.0, pulse_width=0.1)
    assert op.observe(faulted, 0.05) is False
    assert op.observe(RobotStatus(remote_ready=True), 0.2) is True
    assert op.pulse_end(0.2) == (Write("reset", False),)
    still = SignalOp.reset(faulted, now=0.0, timeout=1.0, pulse_width=0.1)
    # a controller that keeps its fault: the reset times out
    with pytest.raises(CallError, match="fault still True") as err:
        still.observe(faulted, 1.0)
    assert err.value.status == "BadTimeout"


def test_a_load_that_times_out_says_what_the_controller_shows() -> None:
    op = SignalOp.load(7, READY, now=0.0, timeout=2.5, pulse_width=0.1)
    assert op.observe(replace(READY, program_echo=3), 2.4) is False
    with pytest.raises(CallError) as late:
        op.observe(replace(READY, program_echo=3), 2.5)
    assert late.value.status == "BadTimeout"
    assert str(late.value).endswith("program_echo still 3, not 7, after 2.5 s"), str(late.value)


def test_reset_after_the_fault_fell_is_a_plain_pulse() -> None:
    """A fault that fell by itself and is acknowledged afterwards: the pulse, for its width only."""
    op = SignalOp.reset(READY, now=0.0, timeout=1.0, pulse_width=0.1)
    assert op.writes == (Write("reset", True),)
    assert op.observe(READY, 0.05) is False
    assert op.pulse_end(0.05) == ()
    assert op.observe(READY, 0.1) is True
    assert op.pulse_end(0.1) == (Write("reset", False),)


def test_drives_off_is_confirmed_also_during_a_fault() -> None:
    faulted = RobotStatus(remote_ready=True, drives_are_on=True, fault=True, fault_code=9)
    off = SignalOp.drives(False, faulted, now=0.0, timeout=1.0)
    assert off.observe(faulted, 0.05) is False  # waits for the drives, the fault is no refusal
    assert off.observe(RobotStatus(remote_ready=True, fault=True, fault_code=9), 0.1) is True
    on = SignalOp.drives(True, RobotStatus(remote_ready=True, fault=True), now=0.0, timeout=1.0)
    with pytest.raises(CallError) as err:
        on.observe(RobotStatus(remote_ready=True, fault=True), 0.05)
    assert err.value.status == "BadInvalidState"


def test_drives_held_not_pulsed() -> None:
    op = SignalOp.drives(True, RobotStatus(remote_ready=True), now=0.0, timeout=1.0)
    assert op.writes == (Write("drives_on", True),)
    assert op.pulse_end(10.0) == ()
    assert op.observe(RobotStatus(remote_ready=True, drives_are_on=True), 0.1) is True
    with pytest.raises(CallError, match="program number 0"):
        SignalOp.load(0, READY, now=0.0, timeout=1.0, pulse_width=0.1)
