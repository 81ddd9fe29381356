"""A Universal Robots Dashboard Server simulator: UR's TCP text protocol (port 29999 on a real robot).

Written from UR's public documentation only: the "Dashboard Server e-Series, port 29999" and
"Dashboard Server CB-Series, port 29999" articles (command table and return values, PolyScope 5.x,
e-Series), UR's Client Library (``dashboard_client_implementation_g5.cpp``, 2025: the reply pattern it
expects for each command, and its tests' expectations of PolyScope 5), and replies recorded from real
e-Series robots in UR's driver issue trackers (the remote-control refusal, the welcome line). The
replies are those of a PolyScope 5.19 controller, one line ending in ``\\n``; where no source gives
the exact string for a case, the reply is our choice and marked (*) below.

Protocol: on connect the server sends ``Connected: Universal Robots Dashboard Server``; then one reply
line per command line. Commands are matched without regard to case (the argument keeps its case).

==============================  =================================================================
command                         reply (success / failure)
==============================  =================================================================
load <program.urp>              ``Loading program: <path>`` / ``File not found: <program.urp>`` /
                                ``Error while loading program: <path>`` (an empty file; (*) also
                                while a program plays or is paused). <path> is the full path under
                                the programs directory (*: UR's clients accept it or the bare name)
play                            ``Starting program`` / ``Failed to execute: play`` (no program, arm
                                not RUNNING, or a safety stop)
stop                            ``Stopped`` / ``Failed to execute: stop`` ((*) nothing running)
pause                           ``Pausing program`` / ``Failed to execute: pause`` ((*) not playing)
programState                    ``STOPPED <name>`` / ``PLAYING <name>`` / ``PAUSED <name>``
                                (``<unnamed>`` when no program is loaded (*))
running                         ``Program running: true`` / ``Program running: false``
get loaded program              ``Loaded program: <path>`` / ``No program loaded``
isProgramSaved                  ``true <name>`` / ``false <name>`` (UR's Client Library pattern;
                                ur-rtde looks for ``True``, so it reads false here)
robotmode                       ``Robotmode: <mode>`` (NO_CONTROLLER ... RUNNING)
safetymode, safetystatus        ``Safetymode: <mode>``, ``Safetystatus: <status>``
power on / power off            ``Powering on`` / ``Powering off`` (the same answer when the arm
                                cannot power on: clients must check ``robotmode``)
brake release                   ``Brake releasing``
unlock protective stop          ``Protective stop releasing`` / ``Cannot unlock protective stop until
                                5s after occurrence. Always inspect cause of protective stop before
                                unlocking``
close safety popup              ``closing safety popup``
popup <text> / close popup      ``showing popup`` / ``closing popup``
addToLog <text>                 ``Added log message`` / ``No log message to add``
restart safety                  ``Restarting safety``
is in remote control            ``true`` / ``false``
get serial number               the serial number (digits, starts with the year: ``2023...``)
get robot model                 ``UR3`` / ``UR5`` / ``UR10`` / ``UR16`` / ``UR20`` / ``UR30``
PolyscopeVersion                ``URSoftware 5.19.0.1210631 (Oct 23 2024)``
version                         ``5.19.0.1210631``
get operational mode            ``MANUAL`` / ``AUTOMATIC`` / ``NONE``
set operational mode <mode>     ``Operational mode '<MODE>' is set`` / (*) ``Failed setting
                                operational mode: <mode>``
clear operational mode          ``No longer controlling the operational mode. Current operational
                                mode: '<MODE>'.``
load installation <file>        ``Loading installation: <path>`` / ``File not found: <file>``
quit                            ``Disconnected`` (then the server closes the connection)
shutdown                        ``Shutting down`` (then the controller goes away)
anything else                   ``could not understand: '<line>'``
==============================  =================================================================

Remote control (e-Series): while the pendant is in Local control, the commands that change the robot
(load, load installation, play, stop, pause, power on/off, brake release, unlock protective stop,
restart safety, shutdown, set/clear operational mode) answer ``Command is not allowed due to safety
reasons, please switch robot to Remote Control mode and reconnect to port 29999``. As UR's driver
maintainers explain, a client connected before a Local/Remote switch must reconnect: this server
refuses those commands on a connection opened before the last switch, as the real one does. Queries
(robotmode, programState, safetystatus, ...) and the popups answer in Local control too.

UR's PolyScope 5 Dashboard Server has no command that lists the programs on the controller (PolyScope
X's Robot API has one): a client learns the catalogue elsewhere; ``URSim.programs()`` gives the tests
the ``*.urp`` files of the programs directory.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

from .lines import LineServer
from .robot import URSim

WELCOME = "Connected: Universal Robots Dashboard Server"
NOT_REMOTE = (
    "Command is not allowed due to safety reasons, please switch robot to Remote Control mode and "
    "reconnect to port 29999"
)
UNLOCK_TOO_EARLY = (
    "Cannot unlock protective stop until 5s after occurrence. Always inspect cause of protective stop before unlocking"
)
OPERATIONAL_MODES = ("MANUAL", "AUTOMATIC")


@dataclass
class Session:
    """One client connection: the remote-control switch count it was opened under."""

    epoch: int
    closing: bool = False


Handler = Callable[[Session, str], str]


@dataclass
class Dashboard:
    """The protocol: one command line in, one reply line out (no sockets; see DashboardServer)."""

    sim: URSim
    received: list[str] = field(default_factory=list)  # every command line, for tests to assert on
    on_shutdown: Callable[[], None] | None = None

    def __post_init__(self) -> None:
        # (command, needs remote control, handler); the longest matching command wins
        self.table: list[tuple[str, bool, Handler]] = sorted(
            [
                ("load installation", True, self._load_installation),
                ("load", True, self._load),
                ("play", True, self._play),
                ("stop", True, self._stop),
                ("pause", True, self._pause),
                ("quit", False, self._quit),
                ("shutdown", True, self._shutdown),
                ("running", False, self._running),
                ("robotmode", False, lambda s, a: f"Robotmode: {self._sim().robot_mode.name}"),
                ("get loaded program", False, self._loaded_program),
                ("popup", False, self._popup),
                ("close popup", False, self._close_popup),
                ("addtolog", False, self._add_to_log),
                ("isprogramsaved", False, self._saved),
                ("programstate", False, self._program_state),
                ("polyscopeversion", False, self._polyscope_version),
                ("version", False, lambda s, a: self.sim.software_version),
                ("set operational mode", True, self._set_operational_mode),
                ("get operational mode", False, lambda s, a: self.sim.operational_mode),
                ("clear operational mode", True, self._clear_operational_mode),
                ("power on", True, self._power_on),
                ("power off", True, self._power_off),
                ("brake release", True, self._brake_release),
                ("safetymode", False, lambda s, a: f"Safetymode: {self._sim().safety.name}"),
                ("safetystatus", False, lambda s, a: f"Safetystatus: {self._sim().safety.name}"),
                ("unlock protective stop", True, self._unlock_protective_stop),
                ("close safety popup", False, self._close_safety_popup),
                ("restart safety", True, self._restart_safety),
                ("is in remote control", False, lambda s, a: "true" if self.sim.remote_control else "false"),
                ("get serial number", False, lambda s, a: self.sim.serial_number),
                ("get robot model", False, lambda s, a: self.sim.robot_model),
            ],
            key=lambda row: -len(row[0]),
        )

    def session(self) -> Session:
        return Session(self.sim.remote_epoch)

    def answer(self, session: Session, line: str) -> str:
        """The reply to one command line (without the newline)."""
        text = line.strip()
        self.received.append(text)
        lowered = text.lower()
        for command, needs_remote, handler in self.table:
            if lowered == command or lowered.startswith(command + " "):
                if needs_remote and not self._remote(session):
                    return NOT_REMOTE
                return handler(session, text[len(command) :].strip())
        return f"could not understand: '{text}'"

    def _sim(self) -> URSim:
        self.sim.advance()
        return self.sim

    def _remote(self, session: Session) -> bool:
        return self.sim.remote_control and session.epoch == self.sim.remote_epoch

    # -- programs --------------------------------------------------------------------------------
    def _load(self, session: Session, name: str) -> str:
        path = self.sim.resolve(name)
        if not name or path.suffix != ".urp" or not path.is_file():
            return f"File not found: {name}"
        self.sim.advance()
        if path.stat().st_size == 0 or self.sim.program_state.value != "STOPPED":
            return f"Error while loading program: {path}"
        self.sim.load(path)
        return f"Loading program: {path}"

    def _load_installation(self, session: Session, name: str) -> str:
        path = self.sim.resolve(name)
        if not name or not path.is_file():
            return f"File not found: {name}"
        return f"Loading installation: {path}"

    def _play(self, session: Session, arg: str) -> str:
        if not self.sim.can_play():
            return "Failed to execute: play"
        self.sim.play()
        return "Starting program"

    def _stop(self, session: Session, arg: str) -> str:
        return "Stopped" if self.sim.stop() else "Failed to execute: stop"

    def _pause(self, session: Session, arg: str) -> str:
        return "Pausing program" if self.sim.pause() else "Failed to execute: pause"

    def _running(self, session: Session, arg: str) -> str:
        playing = self._sim().program_state.value == "PLAYING"
        return f"Program running: {'true' if playing else 'false'}"

    def _loaded_program(self, session: Session, arg: str) -> str:
        loaded = self.sim.loaded
        return f"Loaded program: {loaded}" if loaded is not None else "No program loaded"

    def _saved(self, session: Session, arg: str) -> str:
        return f"{'true' if self.sim.loaded is not None else 'false'} {self.sim.program_name}"

    def _program_state(self, session: Session, arg: str) -> str:
        sim = self._sim()
        return f"{sim.program_state.value} {sim.program_name}"

    # -- power, brakes, safety -------------------------------------------------------------------
    def _power_on(self, session: Session, arg: str) -> str:
        self.sim.power_on()
        return "Powering on"

    def _power_off(self, session: Session, arg: str) -> str:
        self.sim.power_off()
        return "Powering off"

    def _brake_release(self, session: Session, arg: str) -> str:
        self.sim.brake_release()
        return "Brake releasing"

    def _unlock_protective_stop(self, session: Session, arg: str) -> str:
        return "Protective stop releasing" if self.sim.unlock_protective_stop() else UNLOCK_TOO_EARLY

    def _close_safety_popup(self, session: Session, arg: str) -> str:
        self.sim.safety_popup = False
        return "closing safety popup"

    def _restart_safety(self, session: Session, arg: str) -> str:
        self.sim.restart_safety()
        return "Restarting safety"

    # -- popups, log, identity, operational mode --------------------------------------------------
    def _popup(self, session: Session, text: str) -> str:
        self.sim.popup = text
        return "showing popup"

    def _close_popup(self, session: Session, arg: str) -> str:
        self.sim.popup = None
        return "closing popup"

    def _add_to_log(self, session: Session, text: str) -> str:
        if not text:
            return "No log message to add"
        self.sim.log.append(text)
        return "Added log message"

    def _polyscope_version(self, session: Session, arg: str) -> str:
        return f"URSoftware {self.sim.software_version} ({self.sim.software_date})"

    def _set_operational_mode(self, session: Session, mode: str) -> str:
        if mode.upper() not in OPERATIONAL_MODES:
            return f"Failed setting operational mode: {mode}"
        self.sim.operational_mode = mode.upper()
        return f"Operational mode '{mode.upper()}' is set"

    def _clear_operational_mode(self, session: Session, arg: str) -> str:
        mode = self.sim.operational_mode
        return f"No longer controlling the operational mode. Current operational mode: '{mode}'."

    def _quit(self, session: Session, arg: str) -> str:
        session.closing = True
        return "Disconnected"

    def _shutdown(self, session: Session, arg: str) -> str:
        session.closing = True
        if self.on_shutdown is not None:
            self.on_shutdown()
        return "Shutting down"


class DashboardServer(LineServer[Session]):
    """The Dashboard protocol on a TCP port (127.0.0.1 only). ``stop`` drops every connection."""

    def __init__(self, sim: URSim, port: int = 0, host: str = "127.0.0.1") -> None:
        super().__init__(port, host)
        self.dashboard = Dashboard(sim)

    def greeting(self) -> str:
        return WELCOME

    def session(self) -> Session:
        return self.dashboard.session()

    async def reply(self, session: Session, line: str) -> tuple[str, bool]:
        return self.dashboard.answer(session, line), session.closing


if __name__ == "__main__":
    from .server import main

    main()
