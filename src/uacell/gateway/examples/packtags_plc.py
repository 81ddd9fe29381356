"""A PLC keeping ISA-TR88 PackTags in Modbus/TCP holding registers: pymodbus's server with the
default layout of the ``modbus-packtags`` driver (``uacell.gateway.packml_modbus.LAYOUT``, unit i
from register 100 * i) and a small scan-cycle program running each unit's TR88 state machine.

    python -m uacell.gateway.examples.packtags_plc --port 5021 --units 2 --acting 0.1

The program, every scan: take a change request (clear it; act on it when TR88 allows the command
in the state), end an acting state after ``--acting`` seconds, produce at MachSpeed packages/min in
Execute. Test switches in each unit's own registers (from base + 80): 80 refuse (requests are taken
and ignored), 81 frozen (no scan), 82 fault (a rising edge aborts with StopReason 42); 84.. the
Command.Parameter values the last Start took (float32 each). Prints "listening" once it serves.
"""

from __future__ import annotations

import argparse
import asyncio
import sys
import time

from pymodbus.server import ModbusTcpServer
from pymodbus.simulator import SimData, SimDevice
from pymodbus.simulator.simutils import DataType

from uacell.gateway.codec import RegisterType
from uacell.gateway.examples import run_plc
from uacell.gateway.packml_modbus import LAYOUT, PARAMETERS_AT, UNIT_REGISTERS

DEVICE = 1
HOLDING = 3
REFUSE, FROZEN, FAULT, TAKEN = 80, 81, 82, 84
PARAMETERS = 5
S = dict(
    Clearing=1, Stopped=2, Starting=3, Idle=4, Suspended=5, Execute=6, Stopping=7, Aborting=8, Aborted=9,
    Holding=10, Held=11, Unholding=12, Suspending=13, Unsuspending=14, Resetting=15, Completing=16, Complete=17,
)  # fmt: skip
ACTING_NEXT = {
    S["Clearing"]: S["Stopped"], S["Starting"]: S["Execute"], S["Stopping"]: S["Stopped"],
    S["Aborting"]: S["Aborted"], S["Holding"]: S["Held"], S["Unholding"]: S["Execute"],
    S["Suspending"]: S["Suspended"], S["Unsuspending"]: S["Execute"], S["Resetting"]: S["Idle"],
    S["Completing"]: S["Complete"],
}  # fmt: skip
STOPPABLE = {S[n] for n in ("Idle", "Starting", "Execute", "Holding", "Held", "Unholding", "Suspending",
                            "Suspended", "Unsuspending", "Completing", "Complete", "Resetting")}  # fmt: skip
ABORTABLE = set(S.values()) - {S["Aborting"], S["Aborted"]}
# CntrlCmd -> (the states it is taken in, the state it leads to)
COMMANDS = {
    1: ({S["Stopped"], S["Complete"]}, S["Resetting"]), 2: ({S["Idle"]}, S["Starting"]), 3: (STOPPABLE, S["Stopping"]),
    4: ({S["Execute"]}, S["Holding"]), 5: ({S["Held"]}, S["Unholding"]), 6: ({S["Execute"]}, S["Suspending"]),
    7: ({S["Suspended"]}, S["Unsuspending"]), 8: (ABORTABLE, S["Aborting"]), 9: ({S["Aborted"]}, S["Clearing"]),
    10: ({S["Execute"]}, S["Completing"]),
}  # fmt: skip
MODE_CHANGE_IN = {S["Stopped"], S["Idle"], S["Aborted"]}


class Unit:
    """One unit's PackTags in the server's registers, and its program."""

    def __init__(self, store: object, base: int, acting: float) -> None:
        self.store, self.base, self.acting = store, base, acting
        self.entered = time.monotonic()
        self.produced = 0.0
        self.last_scan = time.monotonic()
        self.last_fault = False

    async def regs(self, offset: int, count: int) -> list[int]:
        got = await self.store.async_getValues(DEVICE, HOLDING, self.base + offset, count)  # type: ignore[attr-defined]
        return [int(x) for x in got]

    async def get(self, tag: str) -> int | float | bool:
        _, offset, kind = LAYOUT[tag]
        rtype = RegisterType(kind)
        value = rtype.decode(await self.regs(offset, rtype.count))
        assert not isinstance(value, str)
        return value

    async def put(self, offset: int, kind: str, value: object) -> None:
        await self.store.async_setValues(DEVICE, HOLDING, self.base + offset, RegisterType(kind).encode(value))  # type: ignore[attr-defined]

    async def set(self, tag: str, value: object) -> None:
        _, offset, kind = LAYOUT[tag]
        await self.put(offset, kind, value)

    async def initialise(self) -> None:
        await self.set("Status.StateCurrent", S["Stopped"])
        await self.set("Status.UnitModeCurrent", 1)
        await self.set("Command.UnitMode", 1)
        await self.set("Command.MachSpeed", 60.0)
        await self.set("Status.MachSpeed", 60.0)

    async def enter(self, state: int, now: float) -> None:
        await self.set("Status.StateCurrent", state)
        self.entered = now

    async def scan(self, now: float) -> None:
        refuse, frozen, fault = (bool(r) for r in await self.regs(REFUSE, 3))
        if frozen:
            return
        state = int(await self.get("Status.StateCurrent"))
        if fault and not self.last_fault and state in ABORTABLE:
            await self.set("Admin.StopReason", 42)
            await self.enter(state := S["Aborting"], now)
        self.last_fault = fault
        if await self.get("Command.CmdChangeRequest"):
            await self.set("Command.CmdChangeRequest", False)
            rule = COMMANDS.get(int(await self.get("Command.CntrlCmd")))
            if not refuse and rule is not None and state in rule[0]:
                if rule[1] == S["Starting"]:
                    taken = await self.regs(PARAMETERS_AT, 2 * PARAMETERS)
                    await self.store.async_setValues(DEVICE, HOLDING, self.base + TAKEN, taken)  # type: ignore[attr-defined]
                await self.enter(state := rule[1], now)
        if await self.get("Command.UnitModeChangeRequest"):
            await self.set("Command.UnitModeChangeRequest", False)
            if not refuse and state in MODE_CHANGE_IN:
                await self.set("Status.UnitModeCurrent", await self.get("Command.UnitMode"))
        speed = float(await self.get("Command.MachSpeed"))
        if speed > 0:
            await self.set("Status.MachSpeed", speed)
        if state in ACTING_NEXT and now - self.entered >= self.acting:
            await self.enter(state := ACTING_NEXT[state], now)
        if state == S["Execute"]:
            await self.set("Status.CurMachSpeed", speed)
            self.produced += speed / 60.0 * (now - self.last_scan)
            whole = int(self.produced)
            if whole:
                self.produced -= whole
                await self.set("Admin.ProdProcessedCount", int(await self.get("Admin.ProdProcessedCount")) + whole)
        else:
            await self.set("Status.CurMachSpeed", 0.0)
        self.last_scan = now


def device(units: int) -> SimDevice:
    """Holding registers for ``units`` units (and one coil, discrete input and input register)."""
    registers = [SimData(0, values=[0] * (UNIT_REGISTERS * units), datatype=DataType.REGISTERS)]
    bits = [SimData(0, values=[False], datatype=DataType.BITS)]
    return SimDevice(id=DEVICE, simdata=(bits, bits, registers, [SimData(0, values=[0], datatype=DataType.REGISTERS)]))


async def main(port: int, units: int, acting: float, period: float) -> None:
    server = ModbusTcpServer(device(units), address=("127.0.0.1", port))
    program = [Unit(server.context, UNIT_REGISTERS * i, acting) for i in range(units)]
    for unit in program:
        await unit.initialise()

    async def scan(now: float) -> None:
        for unit in program:
            await unit.scan(now)

    await run_plc(server, scan, period)


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--port", type=int, default=5021)
    parser.add_argument("--units", type=int, default=1, help="units, unit i from register 100 * i")
    parser.add_argument("--acting", type=float, default=0.1, help="seconds an acting state takes")
    parser.add_argument("--scan", type=float, default=0.005, help="scan cycle in seconds")
    args = parser.parse_args()
    try:
        asyncio.run(main(args.port, args.units, args.acting, args.scan))
    except KeyboardInterrupt:
        sys.exit(0)
