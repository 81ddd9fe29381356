"""The simulated UR controller's state: robot mode, safety status, the loaded program and its motion.

Pure model, no sockets: the Dashboard Server (``dashboard.py``) and the Modbus server (``modbus.py``)
read and drive one :class:`URSim`, and so do the tests through its control methods. Time comes from an
injected clock; motion and timed transitions are computed when the state is read (``advance``), so a
test with a fake clock sees exactly what it set up.

What follows UR's public documentation (PolyScope 5.x, e-Series) and what is our own choice:

- Robot modes and safety modes/statuses are UR's enumerations (Primary Interface / Dashboard Server
  docs; the numbers are those of the Modbus register map and of UR's Client Library ``datatypes.h``).
- ``power on`` passes through POWER_ON to IDLE after ``boot_seconds``; ``brake release`` goes to
  RUNNING (from POWER_OFF it powers on first, as UR's own client-library tests expect of PolyScope 5).
- A protective stop pauses the program; it stays latched until ``unlock protective stop``, which UR
  refuses during the first 5 s ("Cannot unlock protective stop until 5s after occurrence...").
- An emergency stop (system or robot) powers the arm off and stops the program; the status stays
  latched while the button is pressed; after release the arm stays POWER_OFF and a safety popup shows.
- A FAULT or VIOLATION powers off and stays latched until ``restart safety``, after which the robot is
  POWER_OFF with safety NORMAL (UR's Client Library waits for "Robotmode: POWER_OFF" after it).
- A safeguard stop pauses the program while the input is open; the program resumes when it closes
  (automatic reset). Our choice: the program stays PAUSED until ``play``, as with a manual reset.
- Motion (our choice): while a program plays, each joint moves on a smooth path around its start pose;
  the program ends by itself after its duration (``program_seconds``), or when a test calls
  :meth:`URSim.finish_program`.
"""

from __future__ import annotations

import enum
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path


class RobotMode(enum.Enum):
    """UR robot modes, numbered as in the Modbus register 258 / Primary Interface (NO_CONTROLLER is -1)."""

    NO_CONTROLLER = -1
    DISCONNECTED = 0
    CONFIRM_SAFETY = 1
    BOOTING = 2
    POWER_OFF = 3
    POWER_ON = 4
    IDLE = 5
    BACKDRIVE = 6
    RUNNING = 7


class SafetyStatus(enum.Enum):
    """UR safety modes/statuses, numbered as in the Modbus register 266 / Primary Interface."""

    NORMAL = 1
    REDUCED = 2
    PROTECTIVE_STOP = 3
    RECOVERY = 4
    SAFEGUARD_STOP = 5
    SYSTEM_EMERGENCY_STOP = 6
    ROBOT_EMERGENCY_STOP = 7
    VIOLATION = 8
    FAULT = 9
    AUTOMATIC_MODE_SAFEGUARD_STOP = 12
    SYSTEM_THREE_POSITION_ENABLING_STOP = 13


class ProgramState(enum.Enum):
    STOPPED = "STOPPED"
    PLAYING = "PLAYING"
    PAUSED = "PAUSED"


# Statuses in which a program may run (motion allowed)
RUNNABLE = frozenset({SafetyStatus.NORMAL, SafetyStatus.REDUCED})
EMERGENCY = frozenset({SafetyStatus.SYSTEM_EMERGENCY_STOP, SafetyStatus.ROBOT_EMERGENCY_STOP})
LATCHED_FAULTS = frozenset({SafetyStatus.FAULT, SafetyStatus.VIOLATION})
SAFEGUARDS = frozenset(
    {
        SafetyStatus.SAFEGUARD_STOP,
        SafetyStatus.AUTOMATIC_MODE_SAFEGUARD_STOP,
        SafetyStatus.SYSTEM_THREE_POSITION_ENABLING_STOP,
    }
)
PROTECTIVE_UNLOCK_DELAY = 5.0  # s, UR: "Cannot unlock protective stop until 5s after occurrence"
UNNAMED = "<unnamed>"  # PolyScope's name for a program that has no file

JOINT_NAMES = ("base", "shoulder", "elbow", "wrist1", "wrist2", "wrist3")
HOME = (0.0, -1.5708, 1.5708, -1.5708, -1.5708, 0.0)  # rad: a usual UR "home" pose
AMPLITUDE = (0.8, 0.3, 0.4, 0.5, 0.5, 1.0)  # rad, how far each joint swings while a program plays
PERIOD = 4.0  # s, one swing


@dataclass
class URSim:
    """One simulated controller. Every field is what the real controller would report right now."""

    programs_dir: Path
    clock: Callable[[], float] = time.monotonic
    boot_seconds: float = 0.05  # POWER_ON -> IDLE after power on
    program_seconds: float | None = None  # a playing program ends after this long (None: never by itself)
    unlock_delay: float = PROTECTIVE_UNLOCK_DELAY
    serial_number: str = "20235500042"
    robot_model: str = "UR5"
    software_version: str = "5.19.0.1210631"
    software_date: str = "Oct 23 2024"

    robot_mode: RobotMode = RobotMode.POWER_OFF
    safety: SafetyStatus = SafetyStatus.NORMAL
    program_state: ProgramState = ProgramState.STOPPED
    loaded: Path | None = None
    remote_control: bool = True
    remote_epoch: int = 0  # bumped on every local/remote switch: connections opened before must reconnect
    operational_mode: str = "AUTOMATIC"  # NONE, MANUAL or AUTOMATIC ("get operational mode")
    popup: str | None = None
    safety_popup: bool = False
    emergency_button: bool = False  # an emergency stop input is held
    safeguard_input: bool = False  # a safeguard stop input is open
    log: list[str] = field(default_factory=list)
    program_runs: int = 0  # programs started (play from STOPPED)
    programs_finished: int = 0  # programs that reached their end

    joints: list[float] = field(default_factory=lambda: list(HOME))
    speeds: list[float] = field(default_factory=lambda: [0.0] * 6)
    _origin: list[float] = field(default_factory=lambda: list(HOME))
    _played: float = 0.0  # s of play time of the current run
    _last: float | None = None
    _booted_at: float | None = None
    _protective_at: float | None = None

    # -- time ------------------------------------------------------------------------------------
    def advance(self) -> None:
        """Bring motion and timed transitions up to the clock's now."""
        now = self.clock()
        last, self._last = self._last, now
        if self.robot_mode is RobotMode.POWER_ON and self._booted_at is not None:
            if now - self._booted_at >= self.boot_seconds:
                self.robot_mode = RobotMode.IDLE
        moving = (
            self.program_state is ProgramState.PLAYING
            and self.robot_mode is RobotMode.RUNNING
            and self.safety in RUNNABLE
        )
        if not moving or last is None:
            self.speeds = [0.0] * 6
            return
        dt = max(0.0, now - last)
        played = self._played + dt
        if self.program_seconds is not None and played >= self.program_seconds:
            self._pose(self.program_seconds)
            self.speeds = [0.0] * 6
            self._end_program()
            return
        self._played = played
        self._pose(played)

    def _pose(self, t: float) -> None:
        w = 2 * math.pi / PERIOD
        self.joints = [o + a * math.sin(w * t) for o, a in zip(self._origin, AMPLITUDE, strict=True)]
        self.speeds = [a * w * math.cos(w * t) for a in AMPLITUDE]

    def _end_program(self) -> None:
        self.program_state = ProgramState.STOPPED
        self._played = 0.0
        self.programs_finished += 1

    def _halt(self) -> None:
        """Motion stops where it is (the joints keep their position)."""
        self.speeds = [0.0] * 6

    # -- what the Dashboard Server reports -------------------------------------------------------
    @property
    def program_name(self) -> str:
        return self.loaded.name if self.loaded is not None else UNNAMED

    def resolve(self, name: str) -> Path:
        """A program path as PolyScope resolves it: relative names are under the programs directory."""
        path = Path(name)
        return path if path.is_absolute() else self.programs_dir / path

    def programs(self) -> list[str]:
        """The program files the controller holds (``*.urp`` in the programs directory), sorted."""
        return sorted(p.name for p in self.programs_dir.glob("*.urp") if p.is_file())

    # -- commands (the Dashboard Server calls these after its own checks) ------------------------
    def load(self, path: Path) -> None:
        self.advance()
        self.loaded = path
        self.program_state = ProgramState.STOPPED
        self._played = 0.0

    def can_play(self) -> bool:
        self.advance()
        return (
            self.loaded is not None
            and self.robot_mode is RobotMode.RUNNING
            and self.safety in RUNNABLE
            and self.program_state is not ProgramState.PLAYING
        )

    def play(self) -> None:
        if self.program_state is ProgramState.STOPPED:
            self._origin = list(self.joints)
            self._played = 0.0
            self.program_runs += 1
        self.program_state = ProgramState.PLAYING
        self._last = self.clock()

    def stop(self) -> bool:
        self.advance()
        if self.program_state is ProgramState.STOPPED:
            return False
        self.program_state = ProgramState.STOPPED
        self._played = 0.0
        self._halt()
        return True

    def pause(self) -> bool:
        self.advance()
        if self.program_state is not ProgramState.PLAYING:
            return False
        self.program_state = ProgramState.PAUSED
        self._halt()
        return True

    def power_on(self) -> None:
        self.advance()
        if self.safety in EMERGENCY or self.safety in LATCHED_FAULTS:
            return  # the controller answers but the arm cannot power up
        if self.robot_mode in (RobotMode.POWER_OFF, RobotMode.CONFIRM_SAFETY):
            self.robot_mode = RobotMode.POWER_ON
            self._booted_at = self.clock()
            self.advance()

    def power_off(self) -> None:
        self.advance()
        self.stop()
        if self.robot_mode is not RobotMode.NO_CONTROLLER:
            self.robot_mode = RobotMode.POWER_OFF
        self._booted_at = None

    def brake_release(self) -> None:
        self.advance()
        if self.robot_mode is RobotMode.POWER_OFF:
            self.power_on()  # PolyScope 5 powers on first; refused under e-stop or fault
        if self.robot_mode in (RobotMode.POWER_ON, RobotMode.IDLE):
            self._booted_at = None
            self.robot_mode = RobotMode.RUNNING

    def unlock_protective_stop(self) -> bool:
        """False while UR's 5 s wait after the stop has not passed."""
        self.advance()
        if self.safety is not SafetyStatus.PROTECTIVE_STOP:
            return True
        assert self._protective_at is not None
        if self.clock() - self._protective_at < self.unlock_delay:
            return False
        self.safety = SafetyStatus.NORMAL
        self._protective_at = None
        return True

    def restart_safety(self) -> None:
        self.advance()
        self.stop()
        self.robot_mode = RobotMode.POWER_OFF
        self._booted_at = None
        self._protective_at = None
        self.safety_popup = False
        if self.emergency_button:
            return  # the button is still pressed: the stop stays
        self.safety = SafetyStatus.SAFEGUARD_STOP if self.safeguard_input else SafetyStatus.NORMAL

    # -- the test's hands on the cell (not reachable from the Dashboard Server) ------------------
    def set_remote_control(self, on: bool) -> None:
        """The pendant's Local/Remote toggle. Dashboard clients connected before must reconnect."""
        if on != self.remote_control:
            self.remote_control = on
            self.remote_epoch += 1

    def emergency_stop(self, robot: bool = False) -> None:
        """Press an emergency stop: the system input (default) or the robot's (pendant) button."""
        self.advance()
        self.emergency_button = True
        self.safety = SafetyStatus.ROBOT_EMERGENCY_STOP if robot else SafetyStatus.SYSTEM_EMERGENCY_STOP
        self.stop()
        self.robot_mode = RobotMode.POWER_OFF
        self._booted_at = None

    def release_emergency_stop(self) -> None:
        """Release the button: the arm stays off, PolyScope shows a safety popup."""
        self.advance()
        self.emergency_button = False
        if self.safety in EMERGENCY:
            self.safety = SafetyStatus.NORMAL
            self.safety_popup = True

    def protective_stop(self) -> None:
        """A protective stop (collision, limit...): the program pauses, latched until unlocked."""
        self.advance()
        self.safety = SafetyStatus.PROTECTIVE_STOP
        self._protective_at = self.clock()
        self.safety_popup = True
        self.pause()

    def fault(self, status: SafetyStatus = SafetyStatus.FAULT) -> None:
        """A safety FAULT or VIOLATION: power off, latched until ``restart safety``."""
        assert status in LATCHED_FAULTS
        self.advance()
        self.safety = status
        self.safety_popup = True
        self.stop()
        self.robot_mode = RobotMode.POWER_OFF
        self._booted_at = None

    def safeguard_stop(self, open_: bool, status: SafetyStatus = SafetyStatus.SAFEGUARD_STOP) -> None:
        """Open (or close) a safeguard input: motion pauses while it is open."""
        assert status in SAFEGUARDS
        self.advance()
        self.safeguard_input = open_
        if open_ and self.safety in RUNNABLE:
            self.safety = status
            self.pause()
        elif not open_ and self.safety in SAFEGUARDS:
            self.safety = SafetyStatus.NORMAL

    def finish_program(self) -> None:
        """The running program reaches its end now."""
        self.advance()
        if self.program_state is not ProgramState.STOPPED:
            self._halt()
            self._end_program()

    def reboot(self) -> None:
        """The controller restarts: power off, no program loaded, no latched popup (the cell stays)."""
        self.robot_mode = RobotMode.POWER_OFF
        self.program_state = ProgramState.STOPPED
        self.loaded = None
        self.popup = None
        self.safety_popup = False
        self._booted_at = None
        self._protective_at = None
        self._played = 0.0
        self.speeds = [0.0] * 6
        if self.emergency_button:
            self.safety = SafetyStatus.SYSTEM_EMERGENCY_STOP
        elif self.safety not in EMERGENCY:
            self.safety = SafetyStatus.SAFEGUARD_STOP if self.safeguard_input else SafetyStatus.NORMAL

    def reset(self) -> None:
        """A fresh cell: no button pressed, no safeguard open, Remote control, AUTOMATIC; rebooted."""
        self.emergency_button = self.safeguard_input = False
        self.safety = SafetyStatus.NORMAL
        self.set_remote_control(True)
        self.operational_mode = "AUTOMATIC"
        self.joints = list(HOME)
        self.reboot()

    def snapshot(self) -> dict[str, object]:
        """What the control socket's ``state`` answers (JSON-ready)."""
        self.advance()
        return {
            "robot_mode": self.robot_mode.name,
            "safety": self.safety.name,
            "program_state": self.program_state.value,
            "loaded": str(self.loaded) if self.loaded else None,
            "remote_control": self.remote_control,
            "operational_mode": self.operational_mode,
            "safety_popup": self.safety_popup,
            "popup": self.popup,
            "joints": list(self.joints),
            "speeds": list(self.speeds),
            "program_runs": self.program_runs,
            "programs_finished": self.programs_finished,
        }
