"""A Universal Robots e-Series arm as a ``RobotEquipment``: the ``ur-dashboard`` driver (docs/equipment.md,
"Robots by Universal Robots").

    [[robots.controllers]]
    name = "UR5e"
    equipment = { driver = "ur-dashboard", host = "10.0.0.9" }
    programs = { pick_and_place = "pick_and_place.urp", palletize = "pallet/palletize.urp" }

Programs stay on the robot: LoadByName ``load``s ``<name>.urp`` (or the file ``programs`` gives), and
Programs lists the configured names and the program the robot reports loaded (PolyScope 5's Dashboard
cannot list its files). GetReady is ``power on`` then ``brake release`` (confirmed by robot mode
RUNNING), StandDown ``power off``; Start ``play`` (confirmed by ``programState`` PLAYING); Stop ``stop``
or ``pause`` by stop mode; the run ends when ``programState`` says STOPPED. Joints, robot mode and
safety mode come from UR's Modbus server, program state, remote control and operational mode from the
Dashboard. Acknowledging ProtectiveStop unlocks it (``unlock protective stop``), ControllerFault
``restart safety``, EmergencyStop closes the safety popup.
"""

from __future__ import annotations

import asyncio
import logging
import re
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

from uacell.core.background import stop_task
from uacell.core.errors import CallError
from uacell.gateway import DriverSettings
from uacell.gateway.errors import CommunicationError, DashboardError
from uacell.gateway.modbus import SHARED
from uacell.gateway.retry import keep_trying, poll_backoff
from uacell.gateway.signal_robot import program_key
from uacell.gateway.ur_link import (
    EMERGENCY_MODES,
    FAULT_MODES,
    NOT_REMOTE,
    POWER_OFF_MODE,
    ROBOT_MODES,
    SAFE_MODES,
    SAFEGUARD_MODES,
    SAFETY_MODES,
    Dashboard,
    URState,
    read_state,
)
from uacell.robotics import equipment as eq
from uacell.robotics.program import Kind, Program
from uacell.robotics.sim import DEFAULT_AXES

log = logging.getLogger(__name__)

FAULT, COMMUNICATION, ESTOP, PSTOP, SAFEGUARD = (
    "ControllerFault", "CommunicationLost", "EmergencyStop", "ProtectiveStop", "SafeguardStop",
)  # fmt: skip
SETTINGS = ("host", "port", "modbus_port", "unit", "timeout", "poll", "confirm_timeout", "power_timeout", "programs")
FILE_NAME = re.compile(r"^[A-Za-z0-9_][A-Za-z0-9_ ./-]{0,200}$")
# uacell's stop modes on the robot: "stop" ends the program (Start begins it again), "pause" holds it
# (Start resumes it), None lets it run to its end
STOPS: dict[eq.StopMode, str | None] = {
    eq.StopMode.ON_PATH: "stop",
    eq.StopMode.QUICK_STOP: "stop",
    eq.StopMode.END_OF_INSTRUCTION: "pause",
    eq.StopMode.PROCESS_STOP: "pause",
    eq.StopMode.END_OF_CYCLE: None,
}
PAUSED_POINTER = 1  # the pointer of a paused program: Start resumes it; 0 (ResetToProgramStart) restarts it
MODES = {"MANUAL": 1, "AUTOMATIC": 3}  # get operational mode -> OperationalModeEnumeration


def program_file(name: str, configured: Mapping[str, Any]) -> str:
    """The file ``load`` takes for ``name``: its ``programs`` entry, else ``<name>.urp``."""
    value = configured.get(name)
    file = value if isinstance(value, str) else name
    return file if file.endswith(".urp") else f"{file}.urp"


@dataclass(frozen=True)
class Timing:
    poll: float = 0.05  # seconds between two reads of the robot's state
    confirm_timeout: float = 5.0  # seconds a command may take to show (play, stop, load)
    power_timeout: float = 30.0  # seconds power on and brake release may take together


class URRobot:
    def __init__(
        self, part: str, dashboard: Dashboard, modbus: Any, unit: int, programs: Mapping[str, Any],
        axes: Sequence[eq.AxisInfo], timing: Timing,
    ) -> None:  # fmt: skip
        self.part, self.dashboard, self.modbus, self.unit, self.timing = part, dashboard, modbus, unit, timing
        self.configured = dict(programs)
        self._axes = tuple(axes)
        self.state: URState | None = None
        self.program_state = ""  # STOPPED / PLAYING / PAUSED
        self.loaded = ""  # the program file the robot reports loaded
        self.remote = False
        self.operational_mode = 0
        self.reachable = False
        self._listeners: list[eq.AlarmListener] = []
        self._power: list[Callable[[bool], None]] = []
        self._axis_listeners: list[Callable[[], None]] = []
        self._safety_listeners: list[Callable[[], None]] = []
        self._alarms: dict[str, bool] = {}
        self._stop_requested = False
        self._poller: asyncio.Task[None] | None = None
        self._background: set[asyncio.Task[None]] = set()
        self._closed = False
        self._slow_at = 0.0

    # -- what the model reads --------------------------------------------------------------------
    @property
    def axes(self) -> Sequence[eq.AxisInfo]:
        return self._axes

    @property
    def alarm_names(self) -> Sequence[str]:
        return (FAULT, COMMUNICATION, ESTOP, PSTOP, SAFEGUARD)

    def add_alarm_listener(self, listener: eq.AlarmListener) -> None:
        self._listeners.append(listener)

    def add_power_listener(self, listener: Callable[[bool], None]) -> None:
        self._power.append(listener)
        if self.state is not None:
            listener(self.state.arm_running)

    def add_axis_listener(self, listener: Callable[[], None]) -> None:
        self._axis_listeners.append(listener)

    def add_safety_listener(self, listener: Callable[[], None]) -> None:
        self._safety_listeners.append(listener)

    def axis_states(self) -> Sequence[eq.AxisState]:
        s = self.state
        if s is None:
            return [eq.AxisState(0.0, 0.0) for _ in self._axes]
        return [
            eq.AxisState(s.positions[i] if i < len(s.positions) else 0.0, s.speeds[i] if i < len(s.speeds) else 0.0)
            for i in range(len(self._axes))
        ]

    def safety_report(self) -> eq.SafetyReport | None:
        if self.state is None or not self.reachable:
            return None
        mode = 4 if self.remote and self.operational_mode != 1 else self.operational_mode
        return eq.SafetyReport(mode, self.state.emergency_stopped, self.state.protective_stopped)

    # -- the controller's programs (ProgramCatalogue) --------------------------------------------
    def program_names(self) -> Sequence[str]:
        names = set(self.configured)
        if self.loaded:
            names.add(self.loaded.rsplit("/", 1)[-1].removesuffix(".urp"))
        return sorted(names)

    def find_program(self, name: str) -> str | None:
        """A configured name, else any name that can be a program file (the robot says if it has it)."""
        return name if name in self.configured or FILE_NAME.match(name) else None

    async def select(self, task: str, name: str) -> None:
        file = program_file(name, self.configured)
        reply = await self._command(f"load {file}")
        if reply.startswith("File not found"):
            raise eq.UnknownProgram(reply)
        if reply.startswith("Error while loading"):
            raise eq.ProgramRejected(reply)
        if not reply.startswith("Loading program"):
            raise eq.EquipmentError(f"load {file}: {reply}")
        await self._until(lambda: self.loaded.endswith(file), f"the robot did not report {file} loaded", slow=True)

    async def load(self, task: str, program: Program) -> None:
        """A file in Programs: the robot takes no files; its program of the same name is loaded."""
        if program.kind is Kind.MODULE:
            return  # the robot's programs hold their own subprograms
        key = program_key(program.name)
        name = next((n for n in self.configured if program_key(n) == key), program.name)
        try:
            await self.select(task, name)
        except eq.UnknownProgram as e:
            raise eq.ProgramRejected(
                f"the robot takes no program files and has no program {program.name}: {e}"
            ) from None

    async def unload(self, task: str, name: str) -> None:
        return  # the robot keeps its program loaded until the next load

    # -- the state poll ---------------------------------------------------------------------------
    async def start(self) -> None:
        await self._read()
        self._poller = asyncio.get_running_loop().create_task(self._poll(), name=f"{self.part} ur")

    async def _poll(self) -> None:
        poll = self.timing.poll
        await asyncio.sleep(poll)
        await keep_trying(self._read_once, first=poll_backoff(poll), pause=poll, closed=lambda: self._closed)

    async def _read_once(self) -> bool:
        await self._read()
        return self.reachable

    async def _read(self, slow: bool = False) -> None:
        try:
            if not self.modbus.connected and not await self.modbus.connect():
                raise CommunicationError(f"{self.modbus.name}: no connection")
            state = await read_state(self.modbus, self.unit, len(self._axes))
            self.program_state, _, _ = (await self.dashboard.ask("programState")).partition(" ")
            now = time.monotonic()
            if slow or now >= self._slow_at or not self.reachable:  # once a second: what changes seldom
                self._slow_at = now + 1.0
                loaded = await self.dashboard.ask("get loaded program")
                self.loaded = loaded.removeprefix("Loaded program:").strip() if loaded.startswith("Loaded") else ""
                remote = (await self.dashboard.ask("is in remote control")).lower() == "true"
                mode = MODES.get((await self.dashboard.ask("get operational mode")).upper(), 0)
                if (remote, mode) != (self.remote, self.operational_mode):
                    remote_changed = remote != self.remote
                    self.remote, self.operational_mode = remote, mode
                    self._tell_all(self._safety_listeners)
                    if remote_changed and self.state is not None:
                        for power in list(self._power):  # what a start needs changed: Executable follows
                            power(self.state.arm_running)
        except (CommunicationError, DashboardError) as e:
            self._lost(str(e))
            return
        self._observe(state)

    def _lost(self, why: str) -> None:
        if self.reachable:
            self.reachable = False
            log.warning("%s: lost the robot (%s), retrying", self.part, why)
            self._alarm(COMMUNICATION, True, why)
            self._tell_all(self._safety_listeners)
        self.dashboard.close()

    def _observe(self, state: URState) -> None:
        before, self.state = self.state, state
        if not self.reachable:
            self.reachable = True
            log.info("%s: the robot answers", self.part)
            self._alarm(COMMUNICATION, False, "")
        mode = state.safety_mode
        name = SAFETY_MODES.get(mode, str(mode))
        self._alarm(ESTOP, mode in EMERGENCY_MODES or state.emergency_stopped, f"safety mode {name}")
        self._alarm(PSTOP, mode == 3 or state.protective_stopped, "protective stop")
        self._alarm(FAULT, mode in FAULT_MODES, f"safety mode {name}")
        self._alarm(SAFEGUARD, mode in SAFEGUARD_MODES, f"safety mode {name}")
        if before is None or before.arm_running != state.arm_running:
            for power in list(self._power):
                power(state.arm_running)
        if before is None or (before.positions, before.speeds) != (state.positions, state.speeds):
            self._tell_all(self._axis_listeners)
        if before is None or (before.emergency_stopped, before.protective_stopped) != (
            state.emergency_stopped,
            state.protective_stopped,
        ):
            self._tell_all(self._safety_listeners)

    def _alarm(self, name: str, active: bool, message: str) -> None:
        if self._alarms.get(name, False) != active:
            self._alarms[name] = active
            for listener in list(self._listeners):
                listener(name, active, message if active else "")

    @staticmethod
    def _tell_all(listeners: list[Callable[[], None]]) -> None:
        for listener in list(listeners):
            listener()

    # -- commands ---------------------------------------------------------------------------------
    async def _command(self, command: str) -> str:
        """One Dashboard command; a refusal for Local control after the pendant went Remote is asked
        again on a new connection (UR's server judges a connection by when it was opened)."""
        try:
            reply = await self.dashboard.ask(command)
            if reply.startswith(NOT_REMOTE) and (await self.dashboard.ask("is in remote control")).lower() == "true":
                await self.dashboard.connect()
                reply = await self.dashboard.ask(command)
        except DashboardError as e:
            self._lost(str(e))
            raise CallError("BadCommunicationError", str(e)) from None
        if reply.startswith(NOT_REMOTE):
            raise eq.StartRefused(f"{command}: the robot is in Local control (its pendant): {reply}")
        return reply

    async def _until(
        self, done: Callable[[], bool], why: str, timeout: float | None = None, slow: bool = False
    ) -> None:
        deadline = time.monotonic() + (timeout or self.timing.confirm_timeout)
        while True:
            await self._read(slow)
            if not self.reachable:
                raise CallError("BadCommunicationError", f"lost the robot at {self.dashboard.name}")
            if done():
                return
            if time.monotonic() >= deadline:
                raise CallError("BadTimeout", why)
            await asyncio.sleep(self.timing.poll / 2)

    def _mode(self) -> str:
        return ROBOT_MODES.get(self.state.robot_mode, "?") if self.state else "unknown"

    async def power_up(self) -> None:
        power = self.timing.power_timeout
        try:
            await self._command("power on")
            await self._until(
                lambda: self.state is not None and self.state.robot_mode in (5, 7), "", self.timing.power_timeout
            )
            await self._command("brake release")
            await self._until(lambda: self.state is not None and self.state.arm_running, "", power)
        except (CallError, eq.StartRefused) as e:
            raise eq.NotPowered(f"the arm did not power up (robot mode {self._mode()}): {e}") from None

    async def power_down(self) -> None:
        try:
            await self._command("power off")
            await self._until(lambda: self.state is not None and self.state.robot_mode <= POWER_OFF_MODE, "")
        except (CallError, eq.StartRefused) as e:
            raise eq.EquipmentError(f"the arm did not power off (robot mode {self._mode()}): {e}") from None

    def start_refusal(self) -> str | None:
        """Local control, or the arm not ready to move (a safety stop aside: a condition)."""
        if self.state is None or not self.reachable:
            return None
        if not self.remote:
            return "the robot is in Local control (its pendant), not Remote"
        if not self.state.arm_running:
            return f"the arm is not ready to move (robot mode {self._mode()})"
        return None

    async def begin(self, task: str, pointer: int, mode: eq.ExecutionMode) -> None:
        """``play``, answered once ``programState`` says PLAYING. A program paused and then reset to its
        start (pointer 0) is stopped first, so it begins again."""
        await self._read(slow=True)  # remote control as it is now
        if not self.reachable:
            raise CallError("BadCommunicationError", f"no answer from {self.dashboard.name}")
        assert self.state is not None
        if self.state.safety_mode not in SAFE_MODES:
            raise eq.AlarmStop(f"safety mode {SAFETY_MODES.get(self.state.safety_mode, self.state.safety_mode)}")
        if not self.remote:
            raise eq.StartRefused("the robot is in Local control (its pendant), not Remote")
        if not self.state.arm_running:
            raise eq.StartRefused(f"the arm is not ready to move (robot mode {self._mode()})")
        if self.program_state == "PAUSED" and pointer == 0:
            await self._command("stop")
        self._stop_requested = False
        reply = await self._command("play")
        if not reply.startswith("Starting program"):
            raise eq.StartRefused(f"play: {reply}")
        await self._until(lambda: self.program_state == "PLAYING", "the robot did not confirm play")

    async def run(self, task: str, pointer: int, mode: eq.ExecutionMode, progress: eq.Progress) -> eq.RunOutcome:
        if self.program_state != "PLAYING":
            try:
                await self.begin(task, pointer, mode)
            except CallError as e:
                raise eq.EquipmentError(f"the robot did not start: {e}") from None
        try:
            while True:
                await asyncio.sleep(self.timing.poll)
                if self._closed:
                    raise eq.EquipmentError("the driver was closed while the program ran")
                if not self.reachable:
                    raise eq.EquipmentError(f"lost the robot at {self.dashboard.name} while it ran")
                assert self.state is not None
                if self.state.safety_mode not in SAFE_MODES:
                    raise eq.AlarmStop(
                        f"safety mode {SAFETY_MODES.get(self.state.safety_mode, self.state.safety_mode)}"
                    )
                if self.program_state == "PAUSED":
                    return eq.RunOutcome(PAUSED_POINTER, completed=False)
                if self.program_state == "STOPPED":
                    return eq.RunOutcome(0, completed=not self._stop_requested)
        finally:
            self._stop_requested = False

    async def stop(self, task: str, mode: eq.StopMode) -> None:
        self._stop_requested = True
        command = STOPS[mode]
        if command is None:
            return  # EndOfCycle: the program runs to its end
        try:
            reply = await self._command(command)
        except eq.StartRefused as e:
            raise eq.EquipmentError(str(e)) from None
        if reply.startswith("Failed") and self.program_state == "PLAYING":
            raise eq.EquipmentError(f"{command}: {reply}")

    # -- alarms acknowledged (AlarmReset) ---------------------------------------------------------
    def alarm_acknowledged(self, name: str) -> None:
        command = {PSTOP: "unlock protective stop", FAULT: "restart safety", ESTOP: "close safety popup"}.get(name)
        if command is not None and self.reachable:
            task = asyncio.get_running_loop().create_task(self._acknowledge(command))
            self._background.add(task)
            task.add_done_callback(self._background.discard)

    async def _acknowledge(self, command: str) -> None:
        try:
            reply = await self._command(command)
            log.info("%s: %s: %s", self.part, command, reply)
            if command != "close safety popup":
                await self._command("close safety popup")
        except (CallError, eq.EquipmentError) as e:
            log.warning("%s: %s failed: %s", self.part, command, e)

    async def close(self) -> None:
        self._closed = True
        for task in [self._poller, *self._background]:
            await stop_task(task)  # never held up by the transport
        await self.dashboard.aclose()
        await SHARED.release(self.modbus)


async def ur_dashboard(spec: Any) -> URRobot:
    """The equipment factory of the ``ur-dashboard`` driver (``spec``: a ControllerEquipmentSpec)."""
    settings = DriverSettings("ur-dashboard", spec.part, spec.settings, SETTINGS)
    host = settings.host("the robot")
    timeout = settings.real("timeout", 2.0)
    timing = Timing(**settings.reals(Timing, "poll", "confirm_timeout", "power_timeout"))
    programs = dict(settings.get("programs", {}))
    dashboard = Dashboard(host, int(settings.get("port", 29999)), timeout)
    modbus = SHARED.connection(host, int(settings.get("modbus_port", 502)), timeout, spec.part)
    axes = tuple(getattr(spec, "axes", ())) or DEFAULT_AXES
    robot = URRobot(spec.part, dashboard, modbus, int(settings.get("unit", 1)), programs, axes, timing)
    await robot.start()  # unreachable at start: uacell serves anyway, the part reports it
    return robot
