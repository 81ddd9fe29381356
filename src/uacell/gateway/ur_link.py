"""The two interfaces of a Universal Robots e-Series controller (PolyScope 5) the ``ur-dashboard`` driver
uses: the Dashboard Server (TCP port 29999, one text line per command and per reply) and the robot state
in UR's Modbus TCP server (port 502). docs/equipment.md cites the documents and versions.

Dashboard replies this module relies on (UR's "Dashboard Server e-Series, port 29999" article):
``load <file>`` answers ``Loading program: <path>``, ``File not found: <file>`` or ``Error while loading
program: <path>``; ``play`` ``Starting program`` or ``Failed to execute: play``; ``programState``
``STOPPED|PLAYING|PAUSED <name>``; ``is in remote control`` ``true|false``; a command that changes the
robot while its pendant is in Local control ``Command is not allowed due to safety reasons, ...``
(a client connected before the switch to Remote must connect again).

Modbus registers (UR's "Modbus Server" article, its register table): 258 robot mode, 260 power on,
261 protective stopped, 262 emergency stopped, 266 safety mode; 270-275 joint angle in mrad within the
turn (0..6283, unsigned), 280-285 joint speed in mrad/s (int16, two's complement), 320-325 the turn
(int16: -1 for [-2 pi, 0)), so angle = turn * 2 pi + angle-in-turn.
"""

from __future__ import annotations

import asyncio
import contextlib
import math
from dataclasses import dataclass

from uacell.gateway.errors import DashboardError
from uacell.gateway.modbus import ModbusConnection

WELCOME = "Connected: Universal Robots Dashboard Server"
NOT_REMOTE = "Command is not allowed due to safety reasons"
# UR's RobotMode and SafetyMode numbers (register 258 and 266)
ROBOT_MODES = {
    -1: "NO_CONTROLLER", 0: "DISCONNECTED", 1: "CONFIRM_SAFETY", 2: "BOOTING", 3: "POWER_OFF", 4: "POWER_ON",
    5: "IDLE", 6: "BACKDRIVE", 7: "RUNNING", 8: "UPDATING_FIRMWARE",
}  # fmt: skip
RUNNING_MODE, IDLE_MODE, POWER_OFF_MODE = 7, 5, 3
SAFETY_MODES = {
    1: "NORMAL", 2: "REDUCED", 3: "PROTECTIVE_STOP", 4: "RECOVERY", 5: "SAFEGUARD_STOP", 6: "SYSTEM_EMERGENCY_STOP",
    7: "ROBOT_EMERGENCY_STOP", 8: "VIOLATION", 9: "FAULT", 10: "VALIDATE_JOINT_ID", 11: "UNDEFINED_SAFETY_MODE",
    12: "AUTOMATIC_MODE_SAFEGUARD_STOP", 13: "SYSTEM_THREE_POSITION_ENABLING_STOP",
}  # fmt: skip
SAFE_MODES = frozenset({1, 2})  # NORMAL, REDUCED: the arm may move
EMERGENCY_MODES = frozenset({6, 7})
FAULT_MODES = frozenset({8, 9})
SAFEGUARD_MODES = frozenset({5, 12, 13})
STATE_REGISTERS = (258, 9)  # 258 .. 266
JOINT_REGISTERS = (270, 16)  # 270 .. 285: angles in the turn, then speeds
TURN_REGISTERS = (320, 6)


class Dashboard:
    """One connection to the Dashboard Server; commands one at a time, each answered by one line."""

    def __init__(self, host: str, port: int = 29999, timeout: float = 2.0) -> None:
        self.host, self.port, self.timeout = host, port, timeout
        self._reader: asyncio.StreamReader | None = None
        self._writer: asyncio.StreamWriter | None = None
        self._lock = asyncio.Lock()

    @property
    def name(self) -> str:
        return f"{self.host}:{self.port}"

    @property
    def connected(self) -> bool:
        return self._writer is not None

    async def connect(self) -> None:
        """Connect anew and read the welcome line; DashboardError when either fails. A command under way
        is answered on the connection it was sent on first (the two never cross: a connection replaced
        under a waiting command, or two made at once, one of them never closed, did)."""
        async with self._lock:
            await self._connect()

    async def _connect(self) -> None:
        self.close()
        try:
            async with asyncio.timeout(self.timeout):
                reader, writer = await asyncio.open_connection(self.host, self.port)
            self._reader, self._writer = reader, writer
            async with asyncio.timeout(self.timeout):
                welcome = await reader.readline()
        except (OSError, TimeoutError) as e:
            self.close()
            raise DashboardError(f"dashboard {self.name}: {e or type(e).__name__}") from None
        if not welcome.decode(errors="replace").startswith(WELCOME):
            self.close()
            raise DashboardError(f"dashboard {self.name}: not a Dashboard Server ({welcome[:60]!r})")

    async def ask(self, command: str) -> str:
        """Send ``command``, return the reply line (without its line end); DashboardError if the
        connection fails (it is closed then, and connected again by the next ``ask``)."""
        async with self._lock:
            if self._writer is None:
                await self._connect()
            reader, writer = self._reader, self._writer
            assert reader is not None and writer is not None
            try:
                writer.write(command.encode() + b"\n")
                await writer.drain()
                async with asyncio.timeout(self.timeout):
                    line = await reader.readline()
            except (OSError, TimeoutError) as e:
                self.close()
                raise DashboardError(f"dashboard {self.name}: {command}: {e or type(e).__name__}") from None
            if not line:
                self.close()
                raise DashboardError(f"dashboard {self.name}: the connection was closed")
            return line.decode(errors="replace").strip()

    def close(self) -> None:
        if self._writer is not None:
            self._writer.close()
        self._reader = self._writer = None

    async def aclose(self) -> None:
        """``close``, then wait (a moment at most) until the socket is closed: at a shutdown the event
        loop may end right after, and a transport it never got to close is a leaked socket."""
        writer = self._writer
        self.close()
        if writer is not None:
            with contextlib.suppress(OSError, TimeoutError):
                async with asyncio.timeout(self.timeout):
                    await writer.wait_closed()


@dataclass(frozen=True)
class URState:
    """What the Modbus registers say, read once."""

    robot_mode: int
    power_on: bool
    protective_stopped: bool
    emergency_stopped: bool
    safety_mode: int
    positions: tuple[float, ...]  # degrees
    speeds: tuple[float, ...]  # degrees/s

    @property
    def arm_running(self) -> bool:
        """Powered with the brakes released (robot mode RUNNING): ready to move."""
        return self.robot_mode == RUNNING_MODE


def signed(word: int) -> int:
    return word - 0x10000 if word >= 0x8000 else word


def joint_degrees(in_turn_mrad: int, turn: int) -> float:
    """UR's joint angle (270+i: 0..6283 mrad within the turn, 320+i: the turn) in degrees."""
    return math.degrees(signed(turn) * 2 * math.pi + in_turn_mrad / 1000.0)


async def read_state(conn: ModbusConnection, unit: int, axes: int) -> URState:
    """Three reads (258-266, 270-285, 320-325); CommunicationError when one fails."""
    state = [int(w) for w in await conn.read_block("holding", *STATE_REGISTERS, unit)]
    joints = [int(w) for w in await conn.read_block("holding", *JOINT_REGISTERS, unit)]
    turns = [int(w) for w in await conn.read_block("holding", *TURN_REGISTERS, unit)]
    n = min(axes, 6)
    return URState(
        robot_mode=signed(state[0]),
        power_on=bool(state[2]),
        protective_stopped=bool(state[3]),
        emergency_stopped=bool(state[4]),
        safety_mode=state[8],
        positions=tuple(joint_degrees(joints[i], turns[i]) for i in range(n)),
        speeds=tuple(math.degrees(signed(joints[10 + i]) / 1000.0) for i in range(n)),
    )
