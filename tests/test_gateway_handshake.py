"""The PackTags command handshake (pure): write order and each way a request ends."""

from __future__ import annotations

import pytest

from uacell.core.errors import CallError
from uacell.gateway.handshake import Handshake, PlcStatus, Write

IDLE = PlcStatus(state_current=4, unit_mode_current=1, cmd_change_request=False)
PENDING = PlcStatus(state_current=4, unit_mode_current=1, cmd_change_request=True)


def test_start_writes_parameters_then_command_then_request() -> None:
    hs = Handshake.command("Start", IDLE, now=0.0, timeout=1.0, parameters=[12.5, 3])
    assert hs.writes == (
        Write("Command.Parameter[0].Value", 12.5),
        Write("Command.Parameter[1].Value", 3.0),
        Write("Command.CntrlCmd", 2),
        Write("Command.CmdChangeRequest", True),
    )
    assert hs.undo == (Write("Command.CmdChangeRequest", False),)


def test_accepted_when_state_moves_or_change_in_process() -> None:
    hs = Handshake.command("Start", IDLE, now=0.0, timeout=1.0)
    assert hs.observe(PENDING, now=0.1) is False
    assert hs.observe(PlcStatus(3, 1, cmd_change_request=False), now=0.2) is True  # Idle -> Starting
    hs2 = Handshake.command("Start", IDLE, now=0.0, timeout=1.0)
    assert hs2.observe(PlcStatus(4, 1, False, state_change_in_process=True), now=0.1) is True


def test_refused_timeout_and_lost_connection() -> None:
    hs = Handshake.command("Hold", IDLE, now=0.0, timeout=1.0)
    with pytest.raises(CallError) as refused:
        hs.observe(IDLE, now=0.1)  # request cleared, state unchanged
    assert refused.value.status == "BadInvalidState"
    hs = Handshake.command("Stop", IDLE, now=0.0, timeout=1.0)
    assert hs.observe(PENDING, now=0.99) is False
    with pytest.raises(CallError) as late:
        hs.observe(PENDING, now=1.0)
    assert late.value.status == "BadTimeout"
    hs = Handshake.command("Stop", IDLE, now=0.0, timeout=1.0)
    with pytest.raises(CallError) as lost:
        hs.observe(PlcStatus(4, 1, True, connected=False), now=0.1)
    assert lost.value.status == "BadCommunicationError"


@pytest.mark.parametrize(
    ("name", "status", "params", "code"),
    [
        ("Start", PENDING, (), "BadInvalidState"),
        ("Start", PlcStatus(4, 1, False, state_change_in_process=True), (), "BadInvalidState"),
        ("Start", PlcStatus(4, 1, False, connected=False), (), "BadCommunicationError"),
        ("Jump", IDLE, (), "BadInvalidArgument"),
        ("Stop", IDLE, (1.0,), "BadInvalidArgument"),
    ],
)
def test_refused_before_any_write(name: str, status: PlcStatus, params: tuple[float, ...], code: str) -> None:
    with pytest.raises(CallError) as err:
        Handshake.command(name, status, now=0.0, timeout=1.0, parameters=params)
    assert err.value.status == code


def test_unit_mode_handshake() -> None:
    hs = Handshake.unit_mode(2, IDLE, now=0.0, timeout=1.0)
    assert hs.writes == (Write("Command.UnitMode", 2), Write("Command.UnitModeChangeRequest", True))
    assert hs.observe(PlcStatus(4, 1, False, unit_mode_change_request=True), now=0.1) is False
    assert hs.observe(PlcStatus(4, 2, False), now=0.2) is True
    with pytest.raises(CallError) as bad:
        Handshake.unit_mode(0, IDLE, now=0.0, timeout=1.0)
    assert bad.value.status == "BadInvalidArgument" and bad.value.argument == 0
    hs = Handshake.unit_mode(3, IDLE, now=0.0, timeout=1.0)
    with pytest.raises(CallError) as refused:
        hs.observe(IDLE, now=0.1)
    assert refused.value.status == "BadInvalidState"
