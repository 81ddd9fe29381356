"""A robot controller behind Modbus/TCP: pymodbus's server holding the default signal map
(``uacell.gateway.signals.DEFAULT_MAP``) and a small scan-cycle controller program.

    python -m uacell.gateway.examples.robot_controller --port 5020 --cycle 2.0

The program: remote ready is always on; drives follow the drives_on coil; a rising program strobe
copies program_number and program_name (a string of 8 registers) to their echoes; a rising start
with drives on, a program selected and no fault runs the program for ``--cycle`` seconds, then sets
program end and at start; a rising stop ends the run at once (no program end); a program number of
99 faults on start (code 99) until reset.

Its panel, holding registers a test (or you, with any Modbus client) writes: ``REMOTE_OFF`` (holding
20) non-zero takes remote control away (remote_ready off: starts are ignored); ``ESTOP`` (holding
21) non-zero is an emergency stop: the run ends, the drives drop, fault 21 is latched and stays until a
reset pulse with the emergency stop released (its signal ``emergency_stop``, discrete 6, follows the
switch); ``PSTOP`` (holding 22) non-zero is a protective stop (``protective_stop``, discrete 7: the run
ends, no fault); ``MODE`` (holding 23) is the operational mode it reports (``operational_mode``, input 2;
0 in the panel: AUTOMATIC_EXTERNAL 4).

Its six joints move while a program runs (axis i swings by 10 * i degrees): their positions in input
registers 20..25 and speeds in 26..31, int16 in hundredths of a degree (per second).
"""

from __future__ import annotations

import argparse
import asyncio
import math

from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import SimData, SimDevice
from pymodbus.simulator.simutils import DataType

from uacell.gateway.examples import run_plc
from uacell.gateway.signals import DEFAULT_MAP

FC = {"coil": 1, "discrete": 2, "holding": 3, "input": 4}
UNIT = 1
FAULT_PROGRAM = 99
REMOTE_OFF, ESTOP, PSTOP, MODE = 20, 21, 22, 23  # holding registers of the panel
ESTOP_CODE = 21
JOINTS, JOINT_SPEEDS, AXES = 20, 26, 6  # input registers: int16, 0.01 degree (per second)
AUTOMATIC_EXTERNAL = 4


class Controller:
    """The controller program; reads and writes the server's own data store each scan."""

    def __init__(self, server: ModbusTcpServer, cycle: float) -> None:
        self.store, self.cycle = server.context, cycle
        self.values: dict[str, int] = {}
        self.last: dict[str, bool] = {}
        self.run_until = self.run_started = 0.0
        self.joints = [0.0] * AXES
        self.joint_words: list[int] = []

    async def get(self, signal: str) -> int | tuple[int, ...]:
        table, address, kind = DEFAULT_MAP[signal]
        count = int(kind.partition(":")[2] or 1)  # a string's registers, as they are
        got = await self.store.async_getValues(UNIT, FC[table], address, count)
        assert isinstance(got, list), got
        return tuple(int(x) for x in got) if count > 1 else int(got[0])

    async def set(self, signal: str, value: int | tuple[int, ...]) -> None:
        table, address, _ = DEFAULT_MAP[signal]
        if isinstance(value, tuple):
            values: list[int] | list[bool] = list(value)
        else:
            values = [bool(value)] if table in ("coil", "discrete") else [value]
        await self.store.async_setValues(UNIT, FC[table], address, values)

    async def panel(self) -> tuple[bool, bool, bool, int]:
        got = await self.store.async_getValues(UNIT, FC["holding"], REMOTE_OFF, 4)
        assert isinstance(got, list), got
        return bool(got[0]), bool(got[1]), bool(got[2]), int(got[3]) or AUTOMATIC_EXTERNAL

    async def move_joints(self, now: float, running: bool) -> None:
        """While running, axis i swings by 10 * i degrees; still otherwise (where it stopped)."""
        if running:
            phase = 2 * math.pi * (now - self.run_started) / max(self.cycle, 0.1)
            amplitude = [10.0 * (i + 1) for i in range(AXES)]
            self.joints = [a * math.sin(phase) for a in amplitude]
            omega = 2 * math.pi / max(self.cycle, 0.1)
            speeds = [a * omega * math.cos(phase) for a in amplitude]
        else:
            speeds = [0.0] * AXES
        words = [round(v * 100) & 0xFFFF for v in (*self.joints, *speeds)]
        if words != self.joint_words:
            self.joint_words = words
            await self.store.async_setValues(UNIT, FC["input"], JOINTS, words)

    async def scan(self, now: float) -> None:
        read = {name: await self.get(name) for name in DEFAULT_MAP}
        remote_off, estop, pstop, mode = await self.panel()
        v = dict(read)  # updated as the program decides, so later rules see this scan's outputs
        rising = {n for n in ("program_strobe", "reset", "start", "stop") if v[n] and not self.last.get(n)}
        self.last = {n: bool(v[n]) for n in ("program_strobe", "reset", "start", "stop")}
        if estop and not (v["fault"] and v["fault_code"] == ESTOP_CODE):
            v["fault"], v["fault_code"] = 1, ESTOP_CODE
        estop_latched = bool(v["fault"]) and v["fault_code"] == ESTOP_CODE
        if estop_latched and "reset" in rising and estop:
            rising.discard("reset")  # still pressed: the reset does nothing
        v["remote_ready"] = 0 if remote_off else 1
        if remote_off:
            rising.discard("start")
        out: dict[str, int | tuple[int, ...]] = {
            "emergency_stop": int(estop),
            "protective_stop": int(pstop),
            "operational_mode": mode,
            "remote_ready": v["remote_ready"],
            "drives_are_on": v["drives_on"] and not estop_latched,
            "fault": v["fault"],
            "fault_code": v["fault_code"],
        }
        if estop_latched:
            v["drives_on"] = 0
        if "program_strobe" in rising:
            # read again now: a client's writes may land between this scan's reads, and the number or
            # name written before the strobe must not be the one read before it
            selected_number, selected_name = await self.get("program_number"), await self.get("program_name")
            out["program_echo"] = v["program_echo"] = selected_number
            out["program_name_echo"] = v["program_name_echo"] = selected_name
        if "reset" in rising:
            out["fault"] = v["fault"] = 0
            out["fault_code"] = v["fault_code"] = 0
            out["drives_are_on"] = 0 if estop_latched else v["drives_on"]
        selected = v["program_echo"] or any(v["program_name_echo"])  # type: ignore[arg-type]
        if "start" in rising and v["drives_on"] and selected and not v["fault"] and not v["running"]:
            if v["program_echo"] == FAULT_PROGRAM:
                out["fault"] = 1
                out["fault_code"] = FAULT_PROGRAM
            else:
                out.update(running=1, program_end=0, at_start=0)
                v["running"] = 1
                self.run_until, self.run_started = now + self.cycle, now
        if v["running"] and ("stop" in rising or not v["drives_on"] or pstop):
            out["running"] = v["running"] = 0
        if v["running"] and now >= self.run_until:
            out.update(running=0, program_end=1, at_start=1)
            v["running"] = 0
        await self.move_joints(now, bool(v["running"]))
        for name, value in out.items():
            if read[name] != value:
                await self.set(name, value)


def device() -> SimDevice:
    """Four distinct blocks of 32 entries from address 0 (coils, discrete inputs, holding, input)."""

    def block(bits: bool) -> list[SimData]:
        kind = DataType.BITS if bits else DataType.REGISTERS
        return [SimData(0, values=([False] if bits else [0]) * 32, datatype=kind)]

    return SimDevice(id=UNIT, simdata=(block(True), block(True), block(False), block(False)))


async def main(port: int, cycle: float, scan: float) -> None:
    server = ModbusTcpServer(device(), address=("127.0.0.1", port))
    controller = Controller(server, cycle)

    await run_plc(server, controller.scan, scan)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--port", type=int, default=5020)
    parser.add_argument("--cycle", type=float, default=2.0, help="seconds a program runs")
    parser.add_argument("--scan", type=float, default=0.005, help="scan cycle in seconds")
    args = parser.parse_args()
    asyncio.run(main(args.port, args.cycle, args.scan))
