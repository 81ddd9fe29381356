"""A robot behind remote-operation signals, as a ``RobotEquipment``, whatever carries the signals
(``SignalIO``): ``ModbusSignalsRobot`` runs the ``modbus-signals`` driver (``robot``, Modbus registers)
and the ``opcua-signals`` driver (``opcua_robot``, a PLC's OPC UA variables) alike. What it does with
each method and signal is described in ``robot``'s module doc.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from collections.abc import Awaitable, Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from uacell.core.background import stop_task
from uacell.core.errors import CallError
from uacell.gateway.errors import CommunicationError
from uacell.gateway.handshake import Write
from uacell.gateway.retry import keep_trying, poll_backoff
from uacell.gateway.signals import RobotStatus, SignalOp, start_missing
from uacell.robotics import equipment as eq
from uacell.robotics.program import Kind, Program

log = logging.getLogger(__name__)

FAULT, COMMUNICATION = "ControllerFault", "CommunicationLost"
ESTOP, PSTOP = "EmergencyStop", "ProtectiveStop"  # conditions, when their signals are mapped


def program_key(name: str) -> str:
    """``pick_and_place``, ``PickAndPlace`` and ``pick-and-place`` name the same program."""
    return re.sub(r"[^a-z0-9]", "", name.lower())


@dataclass(frozen=True)
class Timing:
    poll: float = 0.05  # seconds between status reads
    confirm_timeout: float = 5.0  # seconds a handshake may take
    pulse_width: float = 0.2  # seconds a pulse stays set (at most; it ends once confirmed)
    pulse_gap: float = 0.05  # seconds a pulse signal stays low before it is set again


async def perform(
    op: SignalOp,
    write: Callable[[tuple[Write, ...]], Awaitable[None]],
    status: Callable[[], Awaitable[RobotStatus]],
    poll: float,
    clock: Callable[[], float],
) -> None:
    """Run a signal operation over a transport: ``op``'s writes, then status reads every ``poll`` until
    it is confirmed (pulse ends written on the way, and at the end); CallError with the op's code when
    it fails, Bad_CommunicationError when the transport does."""
    try:
        await write(op.writes)
        try:
            while True:
                await write(op.pulse_end(clock()))
                if op.observe(await status(), clock()):
                    return
                await asyncio.sleep(poll)
        finally:
            await write(op.pulse_end(float("inf")) if op.done else ())
    except CommunicationError as exc:
        raise CallError("BadCommunicationError", f"{op.name}: {exc}") from None


class SignalIO(Protocol):
    """The transport of the signal operations: Modbus registers (``ModbusRobotIO``) or a PLC's OPC UA
    variables (``opcua_robot.OpcuaRobotIO``)."""

    signals: tuple[str, ...]  # the signals ``status`` reads
    motion: Any  # where the axes are (None: not mapped)

    @property
    def name(self) -> str: ...

    async def status(self) -> RobotStatus: ...

    async def perform(self, op: SignalOp) -> None: ...

    async def write_signal(self, signal: str, value: bool | int | str) -> None: ...

    async def close(self) -> None: ...


class ModbusSignalsRobot:
    """The remote-operation signals of a robot controller as a ``RobotEquipment``, whatever carries
    them (``SignalIO``): the modbus-signals and opcua-signals drivers."""

    def __init__(
        self,
        part: str,
        io: SignalIO,
        conn: object | None,
        programs: Mapping[str, int | str],
        axes: Sequence[eq.AxisInfo],
        timing: Timing,
    ) -> None:
        self.part, self.io, self.conn, self.timing = part, io, conn, timing
        self.programs = {program_key(k): v for k, v in programs.items()}
        self._names = {program_key(k): k for k in programs}  # the configured spelling
        self._axes = tuple(axes)
        self._listeners: list[eq.AlarmListener] = []
        self._power_listeners: list[Callable[[bool], None]] = []
        self._power_op = False  # uacell is switching the drives (GetReady / StandDown)
        self._begun: set[str] = set()  # tasks whose start the controller confirmed, run not yet watching
        self._background: set[asyncio.Task[None]] = set()
        self._read = asyncio.Event()  # set (and replaced) after every poll
        self._low_since: dict[str, float] = {}  # pulse signal -> when it was last written low
        self._fault_acked = False  # ControllerFault was acknowledged since the fault rose
        self._axis_listeners: list[Callable[[], None]] = []
        self._safety_listeners: list[Callable[[], None]] = []
        safety = set(io.signals)
        self._alarms = (FAULT, COMMUNICATION, *((ESTOP,) if "emergency_stop" in safety else ()))
        self._alarms += (PSTOP,) if "protective_stop" in safety else ()
        self._reports_safety = bool(safety & {"emergency_stop", "protective_stop", "operational_mode"})
        self.status = RobotStatus(connected=False)
        self._seen = self.status  # the last status read while the controller answered
        self.reachable = False
        self._poller: asyncio.Task[None] | None = None
        self._stop_requested = False
        self._phase: str | None = None  # of the run under way: "starting", "running"
        self._closed = False

    # -- what the model reads ---------------------------------------------------------------------

    @property
    def axes(self) -> Sequence[eq.AxisInfo]:
        return self._axes

    @property
    def alarm_names(self) -> Sequence[str]:
        return self._alarms

    def add_alarm_listener(self, listener: eq.AlarmListener) -> None:
        self._listeners.append(listener)

    def add_power_listener(self, listener: Callable[[bool], None]) -> None:
        self._power_listeners.append(listener)
        if self.status.connected:
            listener(self.status.drives_are_on)  # as the controller is now

    # -- the controller's programs (ProgramCatalogue) ---------------------------------------------

    def program_names(self) -> Sequence[str]:
        return sorted(self._names.values())

    def find_program(self, name: str) -> str | None:
        return self._names.get(program_key(name))

    async def select(self, task: str, name: str) -> None:
        selection = self.programs.get(program_key(name))
        if selection is None:
            raise eq.UnknownProgram(f"{name} is not in programs")
        t = self.timing
        await self._perform(lambda s, now: SignalOp.load(selection, s, now, t.confirm_timeout, t.pulse_width))

    def axis_states(self) -> Sequence[eq.AxisState]:
        """From the last status read: the mapped axis registers (``motion``), else 0."""
        positions, speeds = self.status.positions, self.status.speeds
        return [
            eq.AxisState(positions[i] if i < len(positions) else 0.0, speeds[i] if i < len(speeds) else 0.0)
            for i in range(len(self._axes))
        ]

    def add_axis_listener(self, listener: Callable[[], None]) -> None:
        if self.io.motion is not None:  # without mapped axes they never change: nothing to tell
            self._axis_listeners.append(listener)

    def safety_report(self) -> eq.SafetyReport | None:
        if not self._reports_safety or not self.status.connected:
            return None
        s = self.status
        return eq.SafetyReport(s.operational_mode, s.emergency_stop, s.protective_stop)

    def add_safety_listener(self, listener: Callable[[], None]) -> None:
        self._safety_listeners.append(listener)

    # -- the status poll ----------------------------------------------------------------------

    async def start(self) -> None:
        """Read the controller once (so the first calls know it), then keep polling."""
        self._observe(await self.io.status())
        self._poller = asyncio.get_running_loop().create_task(self._poll(), name=f"{self.part} signals")

    async def _poll(self) -> None:
        poll = self.timing.poll
        await asyncio.sleep(poll)
        await keep_trying(self._poll_once, first=poll_backoff(poll), pause=poll, closed=lambda: self._closed)

    async def _poll_once(self) -> bool:
        status = await self.io.status()
        self._observe(status)
        read, self._read = self._read, asyncio.Event()
        read.set()
        return status.connected

    async def _next_status(self) -> RobotStatus:
        """The status the poller reads next (at most ``poll`` plus a read from now)."""
        if self._poller is None or self._poller.done():  # no poller (a driver built by hand): read
            self._observe(await self.io.status())
            return self.status
        await self._read.wait()
        return self.status

    def _observe(self, status: RobotStatus) -> None:
        """Tell what changed since the controller last answered (a fault that cleared while it was
        away clears its condition when it answers again)."""
        self.status = status
        before = self._seen
        if status.connected != self.reachable:
            self.reachable = status.connected
            if status.connected:
                log.info("%s: the controller at %s answers", self.part, self.io.name)
            else:
                log.warning("%s: lost the controller at %s (retrying)", self.part, self.io.name)
            self._tell(COMMUNICATION, not status.connected, f"no answer from {self.io.name}")
        if not status.connected:
            return
        self._seen = status
        # a new code while the fault stays active renews the message until it is acknowledged (the
        # bit and the code are two reads: the code may come one poll later); after that, only a
        # fault that rises again asks for an acknowledgement again
        renewed = status.fault and status.fault_code != before.fault_code and not self._fault_acked
        if status.fault != before.fault or renewed:
            self._fault_acked = False
            self._tell(FAULT, status.fault, f"controller fault {status.fault_code}" if status.fault else "")
        if status.emergency_stop != before.emergency_stop and ESTOP in self._alarms:
            self._tell(ESTOP, status.emergency_stop, "emergency stop" if status.emergency_stop else "")
        if status.protective_stop != before.protective_stop and PSTOP in self._alarms:
            self._tell(PSTOP, status.protective_stop, "protective stop" if status.protective_stop else "")
        if (status.positions, status.speeds) != (before.positions, before.speeds):
            for axes in list(self._axis_listeners):
                axes()
        safety = (status.operational_mode, status.emergency_stop, status.protective_stop)
        if safety != (before.operational_mode, before.emergency_stop, before.protective_stop) or not before.connected:
            for listener in list(self._safety_listeners):
                listener()
        if start_missing(status) != start_missing(before) and status.drives_are_on == before.drives_are_on:
            for power in list(self._power_listeners):  # what a start needs changed: Executable follows
                power(status.drives_are_on)
        if status.drives_are_on != before.drives_are_on or not before.connected:
            for power in list(self._power_listeners):
                power(status.drives_are_on)
            if before.connected and before.drives_are_on and not self._power_op:
                # the controller switched its drives off (a fault, its panel): uacell's drives_on is
                # cleared too, so they never come back by themselves; GetReady switches them on again
                self._spawn(self._drop_drives())

    def _spawn(self, coro: Any) -> None:
        task = asyncio.get_running_loop().create_task(coro)
        self._background.add(task)
        task.add_done_callback(self._background.discard)

    async def _drop_drives(self) -> None:
        try:
            await self.io.write_signal("drives_on", False)
        except CallError as e:
            log.warning("%s: could not clear drives_on: %s", self.part, e)

    # -- the reset handshake (AlarmReset) ---------------------------------------------------------

    def alarm_acknowledged(self, name: str) -> None:
        """Acknowledging ControllerFault pulses ``reset`` (confirmed by the fault bit falling, when
        it is set); the answer to Acknowledge does not wait for it."""
        if name == FAULT:
            self._fault_acked = True
        if name == FAULT and self.reachable:
            self._spawn(self.reset())

    async def reset(self) -> None:
        """The reset handshake; a controller that keeps its fault leaves the condition active."""
        t = self.timing
        try:
            await self._perform(lambda s, now: SignalOp.reset(s, now, t.confirm_timeout, t.pulse_width))
            log.info("%s: reset sent to the controller", self.part)
        except CallError as e:
            log.warning("%s: the controller kept its fault after the reset: %s", self.part, e)

    def _tell(self, name: str, active: bool, message: str) -> None:
        for listener in list(self._listeners):
            listener(name, active, message)

    # -- operations -------------------------------------------------------------------------------

    async def _perform(self, make: Any) -> None:
        """Build an operation from the status now (``make(status, now)``) and run its handshake."""
        status = await self.io.status()
        self._observe(status)
        op: SignalOp = make(status, time.monotonic())
        # a pulse signal stays low for ``pulse_gap`` before it is set again, so that a controller
        # scanning slower than uacell writes sees the edge
        wait = max(
            (self._low_since.get(s, 0.0) + self.timing.pulse_gap - time.monotonic() for s in op.pulses), default=0.0
        )
        if wait > 0:
            await asyncio.sleep(wait)
            status = await self.io.status()
            self._observe(status)
            op = make(status, time.monotonic())
        try:
            await self.io.perform(op)
        finally:
            now = time.monotonic()
            self._low_since.update((s, now) for s in op.pulses)
            self._observe(await self.io.status())

    async def power_up(self) -> None:
        self._power_op = True
        try:
            await self._perform(lambda s, now: SignalOp.drives(True, s, now, self.timing.confirm_timeout))
        except CallError as e:
            await self._drop_drives()  # not left asking for drives that did not come on
            raise eq.NotPowered(f"drives did not come on: {e}") from None
        finally:
            self._power_op = False

    async def power_down(self) -> None:
        self._power_op = True
        try:
            await self._perform(lambda s, now: SignalOp.drives(False, s, now, self.timing.confirm_timeout))
        except CallError as e:
            raise eq.EquipmentError(f"drives did not go off: {e}") from None
        finally:
            self._power_op = False

    async def load(self, task: str, program: Program) -> None:
        """A file in Programs: the controller takes no files, so its program of the same name is
        selected (the file's text stays uacell's); none of that name: refused (Status -2)."""
        if program.kind is Kind.MODULE:
            return  # the controller holds its modules; nothing to select
        selection = self.programs.get(program_key(program.name))
        if selection is None:
            known = ", ".join(self.program_names()) or "none"
            raise eq.ProgramRejected(
                f"the controller takes no program files and holds no program {program.name}"
                f" (no number or name for it in programs; it holds: {known})"
            )
        t = self.timing
        await self._perform(lambda s, now: SignalOp.load(selection, s, now, t.confirm_timeout, t.pulse_width))

    def start_refusal(self) -> str | None:
        """What a start needs and the controller does not show (a fault aside: a condition)."""
        missing = [m for m in start_missing(self.status) if m not in ("no fault", "not running")]
        return "start needs " + ", ".join(missing) if missing and self.status.connected else None

    async def begin(self, task: str, pointer: int, mode: eq.ExecutionMode) -> None:
        """The start pulse, answered once ``running`` confirms it (ConfirmedStart). Refused at once,
        nothing written: a fault (eq.AlarmStop), anything else the start needs (eq.StartRefused)."""
        status = await self.io.status()
        self._observe(status)
        if not status.connected:
            raise CallError("BadCommunicationError", f"no answer from {self.io.name}")
        if status.fault:
            raise eq.AlarmStop(f"controller fault {status.fault_code}")
        missing = start_missing(status)
        if missing:
            raise eq.StartRefused("start needs " + ", ".join(missing))
        t = self.timing
        self._phase = "starting"
        try:
            await self._perform(lambda s, now: SignalOp.start(s, now, t.confirm_timeout, t.pulse_width))
        except CallError as e:
            self._phase = None
            if e.status == "BadInvalidState":
                raise eq.AlarmStop(f"controller fault {self.status.fault_code} on start") from None
            raise
        self._begun.add(task)

    async def unload(self, task: str, name: str) -> None:
        return  # the selection stays on the controller until the next one

    async def run(self, task: str, pointer: int, mode: eq.ExecutionMode, progress: eq.Progress) -> eq.RunOutcome:
        try:
            if task not in self._begun:  # called without ``begin`` (the conformance kit): start now
                try:
                    await self.begin(task, pointer, mode)
                except CallError as e:
                    raise eq.EquipmentError(f"the controller did not start: {e}") from None
            self._begun.discard(task)
            self._phase = "running"
            if self._stop_requested:  # asked while the start was being confirmed: it applies to this run
                await self._send_stop()
            status = self.status
            while True:
                if self._closed:
                    raise eq.EquipmentError("the driver was closed while the program ran")
                if not status.connected:
                    raise eq.EquipmentError(f"lost the controller at {self.io.name} while it ran")
                if status.fault:
                    raise eq.AlarmStop(f"controller fault {status.fault_code}")
                if not status.running:
                    if status.program_end and not self._stop_requested:
                        return eq.RunOutcome(0, completed=True)
                    return eq.RunOutcome(pointer, completed=False)
                status = await self._next_status()  # the poller's next read: no request of its own
        finally:
            self._phase = None
            self._stop_requested = False

    async def stop(self, task: str, mode: eq.StopMode) -> None:
        """Every stop mode is the controller's stop signal; a stop asked before the start was
        confirmed is sent once it is (``run`` sends it)."""
        self._stop_requested = True
        if self._phase == "running":
            await self._send_stop()

    async def _send_stop(self) -> None:
        t = self.timing
        try:
            await self._perform(lambda s, now: SignalOp.stop(s, now, t.confirm_timeout, t.pulse_width))
        except CallError as e:
            if e.status == "BadInvalidState" and not self.status.running:
                return  # it ended by itself meanwhile: the run reports how
            raise eq.EquipmentError(f"the controller did not stop: {e}") from None

    async def close(self) -> None:
        self._closed = True
        for task in [self._poller, *self._background]:
            await stop_task(task)  # never held up by the transport
        await self.io.close()


def check_programs(programs: Any) -> dict[str, int | str]:
    """The ``programs`` setting: program name -> number or the controller's name for it."""
    if not isinstance(programs, Mapping):
        raise ValueError("programs must map program names to numbers (or to the names the controller knows)")
    for key, value in programs.items():
        if isinstance(value, bool) or not isinstance(value, int | str) or value in ("", 0):
            raise ValueError(f"programs: {key} = {value!r}: a program number (1..65535) or a name (a string)")
    return dict(programs)
