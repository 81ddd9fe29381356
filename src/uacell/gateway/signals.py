"""Robot remote-operation signals: the default Modbus map and each operation's handshake (pure).

An operation is a set of writes, then (for a pulse) the writes that end the pulse, confirmed by a
status bit within a timeout. Pulse ends are written when the pulse width has passed or the
operation ended, whichever comes first, also on a timeout, so no signal is left set. The caller
feeds ``observe`` only status read after the writes completed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from uacell.core.errors import CallError
from uacell.gateway.handshake import Write

# the signals every status read carries (with the name's echo and the safety signals, when they are used)
STATUS_SIGNALS = (
    "remote_ready",
    "drives_are_on",
    "running",
    "program_end",
    "at_start",
    "fault",
    "program_echo",
    "fault_code",
)

# the axes' units -> degrees
UNITS = {"deg": 1.0, "rad": 180.0 / math.pi, "mrad": 0.18 / math.pi}
# signal -> (Modbus table, address, type); every entry overridable from the cell file
DEFAULT_MAP: dict[str, tuple[str, int, str]] = {
    # to the robot
    "start": ("coil", 0, "bool"),
    "stop": ("coil", 1, "bool"),
    "reset": ("coil", 2, "bool"),
    "drives_on": ("coil", 3, "bool"),
    "program_strobe": ("coil", 4, "bool"),
    "program_number": ("holding", 0, "uint16"),
    "program_name": ("holding", 10, "string:8"),  # selection by name: read only when a program uses it
    # from the robot
    "remote_ready": ("discrete", 0, "bool"),
    "drives_are_on": ("discrete", 1, "bool"),
    "running": ("discrete", 2, "bool"),
    "program_end": ("discrete", 3, "bool"),
    "at_start": ("discrete", 4, "bool"),
    "fault": ("discrete", 5, "bool"),
    "program_echo": ("input", 0, "uint16"),
    "fault_code": ("input", 1, "uint16"),
    "program_name_echo": ("input", 10, "string:8"),
    # safety, read only when ``map`` names them (their defaults are where the example controller has them)
    "emergency_stop": ("discrete", 6, "bool"),
    "protective_stop": ("discrete", 7, "bool"),
    "operational_mode": ("input", 2, "uint16"),  # an OperationalModeEnumeration value (0..4)
}
NAME_SIGNALS = ("program_name", "program_name_echo")  # in use only for a programs entry that is a name
SAFETY_SIGNALS = ("emergency_stop", "protective_stop", "operational_mode")  # in use only when mapped


@dataclass(frozen=True)
class RobotStatus:
    remote_ready: bool = False
    drives_are_on: bool = False
    running: bool = False
    program_end: bool = False
    at_start: bool = False
    fault: bool = False
    program_echo: int = 0
    fault_code: int = 0
    program_name_echo: str = ""
    connected: bool = True
    emergency_stop: bool = False
    protective_stop: bool = False
    operational_mode: int = 0
    positions: tuple[float, ...] = ()  # degrees, one per axis, when the axes are mapped
    speeds: tuple[float, ...] = ()  # degrees/s


class SignalOp:
    """One operation in flight; build with the class methods, then ``observe`` and ``pulse_end``."""

    def __init__(
        self,
        name: str,
        writes: tuple[Write, ...],
        pulse_off: tuple[Write, ...],
        confirm: tuple[str, bool | int | str] | None,
        now: float,
        timeout: float,
        pulse_width: float,
        fault_ends: bool = True,
    ) -> None:
        self.name = name
        self.writes = writes
        self._pulse_off = pulse_off
        self._confirm = confirm  # (signal, value) the controller shows once it acted; None: a plain pulse
        self._timeout = timeout
        self._deadline = now + timeout
        self._pulse_until = now + pulse_width
        self._fault_ends = fault_ends
        self.pulses = tuple(w.tag for w in pulse_off)  # the pulse signals this operation sets
        self.done = False

    def pulse_end(self, now: float) -> tuple[Write, ...]:
        """The writes that end the pulse, once: when its width has passed or the operation ended."""
        if self._pulse_off and (self.done or now >= self._pulse_until):
            out, self._pulse_off = self._pulse_off, ()
            return out
        return ()

    def observe(self, status: RobotStatus, now: float) -> bool:
        """True once the controller confirmed; False while waiting; CallError when it will not."""
        if self.done:
            return True
        if not status.connected:
            self.done = True
            raise CallError("BadCommunicationError", f"{self.name}: the robot controller connection was lost")
        if self._confirm is not None and getattr(status, self._confirm[0]) == self._confirm[1]:
            self.done = True
            return True
        if status.fault and self._fault_ends:
            self.done = True
            raise CallError("BadInvalidState", f"{self.name}: the controller reports fault {status.fault_code}")
        if now >= self._deadline:
            self.done = True
            if self._confirm is None:  # a plain pulse: done when its time has passed
                return True
            signal, wanted = self._confirm
            raise CallError(
                "BadTimeout",
                f"{self.name}: the controller did not confirm in time: {signal} still"
                f" {getattr(status, signal)!r}, not {wanted!r}, after {self._timeout:g} s",
            )
        return False

    @classmethod
    def load(
        cls, selection: int | str, status: RobotStatus, now: float, timeout: float, pulse_width: float
    ) -> SignalOp:
        """Select a program by number (``program_number``, confirmed by ``program_echo``) or by name
        (the string tag ``program_name``, confirmed by ``program_name_echo``), then the strobe."""
        _reachable(status)
        if isinstance(selection, str):
            if not selection or not selection.isascii():
                raise CallError("BadInvalidArgument", f"program name {selection!r} is not ASCII text", argument=0)
            tag, echo = "program_name", "program_name_echo"
        else:
            if not 0 < selection <= 0xFFFF:
                raise CallError("BadInvalidArgument", f"program number {selection} is not 1..65535", argument=0)
            tag, echo = "program_number", "program_echo"
        if status.running:
            raise CallError("BadInvalidState", "a program is running")
        return cls(
            "load",
            (Write(tag, selection), Write("program_strobe", True)),
            (Write("program_strobe", False),),
            (echo, selection),
            now,
            timeout,
            pulse_width,
        )

    @classmethod
    def start(cls, status: RobotStatus, now: float, timeout: float, pulse_width: float) -> SignalOp:
        """Start pulse; needs remote ready, drives on, a selected program, no fault; confirmed by running."""
        _reachable(status)
        missing = start_missing(status)
        if missing:
            raise CallError("BadInvalidState", "start needs " + ", ".join(missing))
        return cls(
            "start", (Write("start", True),), (Write("start", False),), ("running", True), now, timeout, pulse_width
        )

    @classmethod
    def stop(cls, status: RobotStatus, now: float, timeout: float, pulse_width: float) -> SignalOp:
        """Stop pulse; confirmed by not running."""
        _reachable(status)
        if not status.running:
            raise CallError("BadInvalidState", "no program is running")
        return cls(
            "stop", (Write("stop", True),), (Write("stop", False),), ("running", False), now, timeout, pulse_width
        )

    @classmethod
    def reset(cls, status: RobotStatus, now: float, timeout: float, pulse_width: float) -> SignalOp:
        """Acknowledge pulse: with the fault bit set, confirmed by its falling; without (a fault that
        fell by itself, acknowledged afterwards), a plain pulse of ``pulse_width``."""
        _reachable(status)
        if not status.fault:
            return cls(
                "reset", (Write("reset", True),), (Write("reset", False),), None,
                now, pulse_width, pulse_width, fault_ends=False,
            )  # fmt: skip
        return cls(
            "reset",
            (Write("reset", True),),
            (Write("reset", False),),
            ("fault", False),
            now,
            timeout,
            pulse_width,
            fault_ends=False,
        )

    @classmethod
    def drives(cls, on: bool, status: RobotStatus, now: float, timeout: float) -> SignalOp:
        """Drives on (held) for GetReady, off for StandDown; confirmed by the drives-on bit."""
        _reachable(status)
        return cls(
            "drives on" if on else "drives off",
            (Write("drives_on", on),),
            (),
            ("drives_are_on", on),
            now,
            timeout,
            0.0,
            fault_ends=on,  # drives may always be switched off, also during a fault
        )


def start_missing(status: RobotStatus) -> list[str]:
    """What a start needs and the controller does not show (empty: it may start); a fault aside."""
    return [
        what
        for what, ok in (
            ("remote ready (remote control)", status.remote_ready),
            ("drives on", status.drives_are_on),
            ("a selected program", status.program_echo != 0 or status.program_name_echo != ""),
            ("no fault", not status.fault),
            ("not running", not status.running),
        )
        if not ok
    ]


def _reachable(status: RobotStatus) -> None:
    if not status.connected:
        raise CallError("BadCommunicationError", "no connection to the robot controller")
