"""The PackTags command handshake as a pure model (no transport, clock passed in).

A command (or a unit-mode change) is written as an ordered list of tag writes: Start's parameters
first, then the command number, then the change request. The PLC's scan takes the request and
clears it; the handshake watches the PLC's status and decides:

- the state moved (or ``StateChangeInProcess`` rose) -> accepted, the call answers Good;
- the request was cleared and nothing moved -> the PLC refused it: ``BadInvalidState``;
- the request is still set after ``timeout`` seconds -> ``BadTimeout``, and ``undo`` is the write
  that clears the request again so nothing is left half-written;
- the connection is lost -> ``BadCommunicationError`` (nothing is queued or retried).

Contract for the caller: ``observe`` is fed only status read after the last write completed, so a
cleared request really is the PLC's answer and not the value from before the write.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

from uacell.core.errors import CallError
from uacell.packml.model import TR88_COMMANDS


@dataclass(frozen=True)
class PlcStatus:
    """What the gateway last read from the PLC."""

    state_current: int
    unit_mode_current: int
    cmd_change_request: bool
    unit_mode_change_request: bool = False
    state_change_in_process: bool = False
    connected: bool = True


@dataclass(frozen=True)
class Write:
    tag: str  # a key of the tag map (uacell.gateway.packtags, uacell.gateway.signals)
    value: bool | int | float | str


class Handshake:
    """One command or unit-mode request in flight; build with ``command`` or ``unit_mode``."""

    def __init__(
        self, writes: tuple[Write, ...], request_tag: str, before: PlcStatus, now: float, timeout: float
    ) -> None:
        self.writes = writes
        self.undo = (Write(request_tag, False),)
        self._request_tag = request_tag
        self._before = before
        self._deadline = now + timeout
        self.done = False

    @classmethod
    def command(
        cls, name: str, status: PlcStatus, now: float, timeout: float, parameters: Sequence[float] = ()
    ) -> Handshake:
        """The writes for PackML command ``name``; CallError if it cannot be asked now."""
        number = TR88_COMMANDS.get(name)  # packml's one TR88 table
        if number is None:
            raise CallError("BadInvalidArgument", f"{name!r} is not a PackTags command")
        if parameters and name != "Start":
            raise CallError("BadInvalidArgument", f"only Start takes parameters, not {name}")
        _ready(status, status.cmd_change_request or status.state_change_in_process)
        writes = tuple(Write(f"Command.Parameter[{i}].Value", float(v)) for i, v in enumerate(parameters))
        writes += (Write("Command.CntrlCmd", number), Write("Command.CmdChangeRequest", True))
        return cls(writes, "Command.CmdChangeRequest", status, now, timeout)

    @classmethod
    def unit_mode(cls, mode: int, status: PlcStatus, now: float, timeout: float) -> Handshake:
        """The writes for a unit-mode change to ``mode`` (1..31)."""
        if not 1 <= mode <= 31:
            raise CallError("BadInvalidArgument", f"unit mode {mode} is not 1..31", argument=0)
        _ready(status, status.unit_mode_change_request)
        writes = (Write("Command.UnitMode", mode), Write("Command.UnitModeChangeRequest", True))
        return cls(writes, "Command.UnitModeChangeRequest", status, now, timeout)

    def observe(self, status: PlcStatus, now: float) -> bool:
        """True once the PLC accepted; False while still waiting; CallError when it will not."""
        if self.done:
            return True
        if not status.connected:
            raise CallError("BadCommunicationError", "the PLC connection was lost during the request")
        unit_mode = self._request_tag == "Command.UnitModeChangeRequest"
        if unit_mode:
            moved = status.unit_mode_current != self._before.unit_mode_current
            pending = status.unit_mode_change_request
        else:
            moved = status.state_current != self._before.state_current or status.state_change_in_process
            pending = status.cmd_change_request
        if moved:
            self.done = True
            return True
        if not pending:
            raise CallError("BadInvalidState", "the PLC took the request and did not act on it")
        if now >= self._deadline:
            raise CallError("BadTimeout", "the PLC did not take the request in time (not scanning or not in remote?)")
        return False


def _ready(status: PlcStatus, busy: bool) -> None:
    if not status.connected:
        raise CallError("BadCommunicationError", "no connection to the PLC")
    if busy:
        raise CallError("BadInvalidState", "the PLC is still handling an earlier request")
