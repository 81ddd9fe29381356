"""The test's hands on a simulated UR cell: a small line protocol on its own TCP port.

What a person at the cell would do (the pendant's Local/Remote switch, an emergency stop button, a
safeguard, a collision) and what only a test needs (end the program, kill and restart the
controller, read the whole state). One command per line, one reply line: ``ok``, a JSON object
(``state``) or ``error: <why>``.

====================================  ====================================================
remote on | remote off                the pendant's Remote/Local control switch
estop | estop robot | estop release   press the system (or the robot's) e-stop; release it
protective stop                       a protective stop (latched until unlocked)
fault | violation                     a safety FAULT / VIOLATION (latched until restart safety)
safeguard open | safeguard close      a safeguard stop input
finish                                the playing program reaches its end now
operational mode <NONE|MANUAL|AUTOMATIC>  what ``get operational mode`` answers
program seconds <s|none>              how long a program plays before it ends by itself
robot mode <NAME>                     force a robot mode (NO_CONTROLLER, BOOTING, BACKDRIVE...)
safety <NAME>                         force a safety status (REDUCED, RECOVERY, ...), as is
kill | restart                        the controller goes away (Dashboard and Modbus ports
                                      closed, connections dropped) / comes back, rebooted
reset                                 a fresh cell (buttons released, Remote, AUTOMATIC, home
                                      pose), then restart
state                                 the whole state as JSON (robot.URSim.snapshot)
====================================  ====================================================
"""

from __future__ import annotations

import json
from collections.abc import Awaitable, Callable

from .lines import LineServer
from .robot import RobotMode, SafetyStatus, URSim

MODES = ("NONE", "MANUAL", "AUTOMATIC")


class Control:
    """The control commands, on a URSim and the servers that front it."""

    def __init__(self, sim: URSim, kill: Callable[[], Awaitable[None]], restart: Callable[[], Awaitable[None]]) -> None:
        self.sim, self._kill, self._restart = sim, kill, restart
        self.actions: dict[str, Callable[[], None]] = {
            "remote on": lambda: sim.set_remote_control(True),
            "remote off": lambda: sim.set_remote_control(False),
            "estop": sim.emergency_stop,
            "estop robot": lambda: sim.emergency_stop(robot=True),
            "estop release": sim.release_emergency_stop,
            "protective stop": sim.protective_stop,
            "fault": sim.fault,
            "violation": lambda: sim.fault(SafetyStatus.VIOLATION),
            "safeguard open": lambda: sim.safeguard_stop(True),
            "safeguard close": lambda: sim.safeguard_stop(False),
            "finish": sim.finish_program,
        }

    async def answer(self, line: str) -> str:
        command = " ".join(line.split()).lower()
        if command in self.actions:
            self.actions[command]()
            return "ok"
        if command == "state":
            return json.dumps(self.sim.snapshot())
        if command == "kill":
            await self._kill()
            return "ok"
        if command == "restart":
            await self._restart()
            return "ok"
        if command == "reset":
            self.sim.reset()
            await self._restart()
            return "ok"
        if command.startswith("operational mode "):
            mode = command.removeprefix("operational mode ").upper()
            if mode not in MODES:
                return f"error: operational mode must be one of {', '.join(MODES)}"
            self.sim.operational_mode = mode
            return "ok"
        if command.startswith("robot mode "):
            name = command.removeprefix("robot mode ").upper()
            if name not in RobotMode.__members__:
                return f"error: robot mode must be one of {', '.join(RobotMode.__members__)}"
            self.sim.robot_mode = RobotMode[name]
            return "ok"
        if command.startswith("safety "):
            name = command.removeprefix("safety ").upper()
            if name not in SafetyStatus.__members__:
                return f"error: safety status must be one of {', '.join(SafetyStatus.__members__)}"
            self.sim.safety = SafetyStatus[name]
            return "ok"
        if command.startswith("program seconds "):
            value = command.removeprefix("program seconds ")
            try:
                self.sim.program_seconds = None if value == "none" else float(value)
            except ValueError:
                return f"error: not a number of seconds: {value}"
            return "ok"
        return f"error: unknown command: {line.strip()}"


class ControlServer(LineServer[None]):
    """The control protocol on a TCP port (127.0.0.1 only)."""

    def __init__(self, control: Control, port: int = 0, host: str = "127.0.0.1") -> None:
        super().__init__(port, host)
        self.control = control

    def session(self) -> None:
        return None

    async def reply(self, session: None, line: str) -> tuple[str, bool]:
        return await self.control.answer(line), False
