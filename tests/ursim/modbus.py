"""UR's Modbus TCP server register map (the controller is the Modbus server, port 502), on pymodbus.

Written from UR's public documentation: the "Modbus Server" article (UR support article 16377, valid
for CB3 and PolyScope 5 e-Series, with its "ModBus Server Data" register table) and UR's answer on its
forum about joint angles ("Convert unsigned value of modbus address 270 to 275 to signed value").

Every register is a 16-bit word read with function 3 (holding) or 4 (input registers); both read the
same map. UR's article notes that the server holds unsigned values: a signed quantity is sent as two's
complement ("if val > 32768: val = val - 65535" in its example). Joint angles are not signed: UR's
forum answer explains that 270-275 count up from 0 within one turn (0 .. 6283 mrad) and that the
revolution counters 320-325 tell the turn: 0 for [0, 2 pi), 65535 (-1) for [-2 pi, 0). So a joint at
-0.5 rad reads 5783 at 270+i and 65535 at 320+i: angle = signed(320+i) * 2 pi + (270+i) / 1000.

=========  ==========================================  ==================  ===============================
address    content                                     unit                encoding
=========  ==========================================  ==================  ===============================
128-255    general purpose registers                   -                   uint16, read/write
256        controller version, major ("high number")   -                   uint16
257        controller version, minor ("low number")    -                   uint16
258        robot mode (0 DISCONNECTED ... 7 RUNNING)   enum                UR's RobotMode numbers (-1 as 65535)
260        is power on (robot)                         bool                0/1
261        is protective stopped ("security stopped")  bool                0/1
262        is emergency stopped                        bool                0/1
263        is teach button pressed                     bool                0/1 (always 0 here)
264        is power button pressed                     bool                0/1 (always 0 here)
265        is safety signal such that we should stop   bool                0/1 (safety not NORMAL/REDUCED)
266        safety mode (1 NORMAL ... 13)               enum                uint16 (UR's SafetyMode numbers)
270-275    joint angle, base .. wrist 3                mrad                uint16, 0..6283 within the turn
280-285    joint angular speed, base .. wrist 3        mrad/s              int16 two's complement
290-295    joint current                               mA                  int16 (our model: 0 when off)
300-305    joint temperature                           deg C               uint16 (our model: 30 when on)
310-315    joint mode (253 RUNNING, 255 IDLE,          enum                uint16 (UR's JointMode numbers)
           239 POWER_OFF)
320-325    joint revolution count                      turns               int16 two's complement
400-402    TCP x, y, z in the base frame               0.1 mm              int16 two's complement
403-405    TCP rx, ry, rz (rotation vector), base      mrad                int16 two's complement
410-415    TCP speed                                   mm/s, mrad/s        int16 (not simulated: 0)
420-425    TCP offset (tool frame)                     mm, mrad            int16 (0: the flange is the TCP)
450        robot current                               mA                  uint16 (our model)
451        I/O current                                 mA                  uint16 (0)
=========  ==========================================  ==================  ===============================

UR's map has no "program running" register: the Dashboard Server's ``running`` / ``programState`` tell
that. Writes to 256-451 are refused (exception 2, illegal data address), as UR's article says for
read-only addresses; 128-255 can be written. The TCP pose is the flange of a UR5e (UR's published
DH parameters), computed from the simulated joints.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable
from dataclasses import dataclass

from pymodbus.constants import ExcCodes
from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import DataType, SimData, SimDevice

from .robot import EMERGENCY, RUNNABLE, RobotMode, SafetyStatus, URSim

TWO_PI_MRAD = 2000 * math.pi
POWERED = frozenset({RobotMode.POWER_ON, RobotMode.IDLE, RobotMode.RUNNING, RobotMode.BACKDRIVE})
JOINT_RUNNING, JOINT_IDLE, JOINT_POWER_OFF = 253, 255, 239
FIRST, LAST = 256, 451  # the read-only robot state block

# UR5e, UR's "DH parameters for calculations of kinematics and dynamics" (m, rad)
DH_A = (0.0, -0.425, -0.3922, 0.0, 0.0, 0.0)
DH_D = (0.1625, 0.0, 0.0, 0.1333, 0.0997, 0.0996)
DH_ALPHA = (math.pi / 2, 0.0, 0.0, math.pi / 2, -math.pi / 2, 0.0)


def u16(value: float) -> int:
    """An unsigned register, clamped to 0..65535."""
    return max(0, min(0xFFFF, round(value)))


def s16(value: float) -> int:
    """A signed quantity as UR sends it: two's complement in an unsigned 16-bit register."""
    return max(-0x8000, min(0x7FFF, round(value))) & 0xFFFF


def signed(register: int) -> int:
    """Back from two's complement (the client's side of s16)."""
    return register - 0x10000 if register >= 0x8000 else register


def joint_registers(angle: float) -> tuple[int, int]:
    """(angle register 270+i, revolution register 320+i) for a joint angle in rad."""
    turns = math.floor(angle / (2 * math.pi))
    within = round((angle - turns * 2 * math.pi) * 1000)
    if within >= round(TWO_PI_MRAD):  # rounding reached a full turn
        within, turns = 0, turns + 1
    return within, turns & 0xFFFF


def joint_angle(angle_register: int, revolution_register: int) -> float:
    """The client's decoding of 270+i and 320+i, in rad (to the mrad)."""
    return signed(revolution_register) * 2 * math.pi + angle_register / 1000


@functools.lru_cache(maxsize=16)
def flange_pose(joints: tuple[float, ...]) -> tuple[float, float, float, float, float, float]:
    """(x, y, z in m, rx, ry, rz rotation vector in rad) of the UR5e flange in the base frame.
    Cached: one read of 400-405 asks six times for the same joints."""
    t = [[1.0 if i == j else 0.0 for j in range(4)] for i in range(4)]
    for q, a, d, alpha in zip(joints, DH_A, DH_D, DH_ALPHA, strict=True):
        cq, sq, ca, sa = math.cos(q), math.sin(q), math.cos(alpha), math.sin(alpha)
        step: list[list[float]] = [
            [cq, -sq * ca, sq * sa, a * cq],
            [sq, cq * ca, -cq * sa, a * sq],
            [0.0, sa, ca, d],
            [0.0, 0.0, 0.0, 1.0],
        ]
        t = [[sum(t[i][k] * step[k][j] for k in range(4)) for j in range(4)] for i in range(4)]
    return (t[0][3], t[1][3], t[2][3], *rotation_vector(t))


def rotation_vector(m: list[list[float]]) -> tuple[float, float, float]:
    cos = max(-1.0, min(1.0, (m[0][0] + m[1][1] + m[2][2] - 1) / 2))
    angle = math.acos(cos)
    if angle < 1e-9:
        return (0.0, 0.0, 0.0)
    if math.pi - angle < 1e-6:  # half turn: the axis from the diagonal
        axis = [math.sqrt(max(0.0, (m[i][i] + 1) / 2)) for i in range(3)]
        axis[1] = math.copysign(axis[1], m[0][1] + m[1][0])
        axis[2] = math.copysign(axis[2], m[0][2] + m[2][0])
        return (axis[0] * angle, axis[1] * angle, axis[2] * angle)
    k = angle / (2 * math.sin(angle))
    return (k * (m[2][1] - m[1][2]), k * (m[0][2] - m[2][0]), k * (m[1][0] - m[0][1]))


@dataclass(frozen=True)
class Register:
    address: int
    name: str
    read: Callable[[URSim], int]


def _joint(i: int, what: str) -> Callable[[URSim], int]:
    def read(sim: URSim) -> int:
        if what == "angle":
            return joint_registers(sim.joints[i])[0]
        if what == "revolutions":
            return joint_registers(sim.joints[i])[1]
        if what == "speed":
            return s16(sim.speeds[i] * 1000)
        if what == "current":
            return s16(300 + 2000 * abs(sim.speeds[i])) if sim.robot_mode is RobotMode.RUNNING else 0
        if what == "temperature":
            return 30 if sim.robot_mode in POWERED else 25
        mode = sim.robot_mode
        return JOINT_RUNNING if mode is RobotMode.RUNNING else JOINT_IDLE if mode in POWERED else JOINT_POWER_OFF

    return read


def _tcp(i: int) -> Callable[[URSim], int]:
    def read(sim: URSim) -> int:
        pose = flange_pose(tuple(sim.joints))
        return s16(pose[i] * 10000 if i < 3 else pose[i] * 1000)

    return read


def _version(part: int) -> Callable[[URSim], int]:
    return lambda sim: int(sim.software_version.split(".")[part])


REGISTERS: tuple[Register, ...] = (
    Register(256, "controller version major", _version(0)),
    Register(257, "controller version minor", _version(1)),
    Register(258, "robot mode", lambda sim: s16(sim.robot_mode.value)),
    Register(260, "is power on", lambda sim: int(sim.robot_mode in POWERED)),
    Register(261, "is protective stopped", lambda sim: int(sim.safety is SafetyStatus.PROTECTIVE_STOP)),
    Register(262, "is emergency stopped", lambda sim: int(sim.safety in EMERGENCY)),
    Register(265, "is safety signal such that we should stop", lambda sim: int(sim.safety not in RUNNABLE)),
    Register(266, "safety mode", lambda sim: sim.safety.value),
    *(Register(270 + i, f"joint {i} angle", _joint(i, "angle")) for i in range(6)),
    *(Register(280 + i, f"joint {i} speed", _joint(i, "speed")) for i in range(6)),
    *(Register(290 + i, f"joint {i} current", _joint(i, "current")) for i in range(6)),
    *(Register(300 + i, f"joint {i} temperature", _joint(i, "temperature")) for i in range(6)),
    *(Register(310 + i, f"joint {i} mode", _joint(i, "mode")) for i in range(6)),
    *(Register(320 + i, f"joint {i} revolutions", _joint(i, "revolutions")) for i in range(6)),
    *(Register(400 + i, f"tcp {'x y z rx ry rz'.split()[i]}", _tcp(i)) for i in range(6)),
    Register(450, "robot current", lambda sim: 1200 if sim.robot_mode in POWERED else 0),
)
BY_ADDRESS = {r.address: r for r in REGISTERS}


class URModbusServer:
    """pymodbus's TCP server holding UR's map, read live from a URSim (127.0.0.1 only)."""

    def __init__(self, sim: URSim, port: int, host: str = "127.0.0.1") -> None:
        self.sim, self.host, self.port = sim, host, port
        self.reads = 0  # requests served, for tests
        self._server: ModbusTcpServer | None = None

    async def _action(
        self,
        function_code: int,
        start_address: int,
        address: int,
        count: int,
        registers: list[int],
        set_values: list[int] | list[bool] | None,
    ) -> ExcCodes | None:
        if set_values is not None:
            return None  # pymodbus refuses writes to the read-only block itself
        self.reads += 1
        self.sim.advance()
        for a in range(address, address + count):
            register = BY_ADDRESS.get(a)
            if register is not None:
                registers[a - start_address] = register.read(self.sim)
        return None

    @property
    def listening(self) -> bool:
        return self._server is not None

    async def start(self) -> None:
        """Listen (a new pymodbus server each time: it is built in the running loop)."""
        device = SimDevice(
            id=0,
            simdata=[
                SimData(0, count=FIRST, values=0, datatype=DataType.REGISTERS),
                SimData(FIRST, count=LAST - FIRST + 1, values=0, datatype=DataType.REGISTERS, readonly=True),
            ],
            action=self._action,
        )
        server = ModbusTcpServer(device, address=(self.host, self.port))
        if not await server.listen():
            raise OSError(f"Modbus server could not listen on {self.host}:{self.port}")
        if self.port == 0:  # the port the kernel gave
            self.port = server.transport.sockets[0].getsockname()[1]  # type: ignore[attr-defined]
        self._server = server

    async def stop(self) -> None:
        """Stop listening and drop every client connection."""
        server, self._server = self._server, None
        if server is not None:
            await server.shutdown()
