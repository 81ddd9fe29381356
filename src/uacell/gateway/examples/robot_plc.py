"""A robot controller's signals in a PLC's OPC UA server: asyncua's server holding the signals of the
``opcua-signals`` driver (docs/equipment.md) under Objects/Robot1 (string NodeIds ``Robot1.<signal>``,
BrowseNames ``<signal>``, in the namespace ``urn:example:plc``) and a scan-cycle program (10 ms) acting on
them: drives follow ``drives_on``, a strobe copies the program number and name to their echoes, a start
runs the selected program (its joints, one array of radians, swing) until a stop, program 99 faults on
start until a reset.

    python -m uacell.gateway.examples.robot_plc --port 4850

prints ``listening ns=<namespace index>`` once clients can connect.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import math
from typing import Any

from asyncua import Server, ua

FAULT_PROGRAM = 99

# the PLC's variables: signal -> (OPC UA type, initial value)
SIGNALS: dict[str, tuple[ua.VariantType, Any]] = {
    **{n: (ua.VariantType.Boolean, False) for n in ("start", "stop", "reset", "drives_on", "program_strobe")},
    "program_number": (ua.VariantType.Int32, 0),
    "program_name": (ua.VariantType.String, ""),
    **{n: (ua.VariantType.Boolean, False) for n in ("drives_are_on", "running", "program_end", "at_start", "fault")},
    "remote_ready": (ua.VariantType.Boolean, True),
    "program_echo": (ua.VariantType.Int32, 0),
    "fault_code": (ua.VariantType.Int32, 0),
    "program_name_echo": (ua.VariantType.String, ""),
    "emergency_stop": (ua.VariantType.Boolean, False),
    "operational_mode": (ua.VariantType.Int32, 4),
    "joints": (ua.VariantType.Double, [0.0] * 6),  # radians, one array
}


class PLC:
    """asyncua's server with the robot's signals and a scan-cycle program (10 ms) acting on them."""

    def __init__(self, port: int) -> None:
        self.port = port
        self.server: Server | None = None
        self.nodes: dict[str, Any] = {}
        self.ns = 0
        self._scan: asyncio.Task[None] | None = None

    async def start(self) -> None:
        server = Server()
        await server.init()
        server.set_endpoint(f"opc.tcp://127.0.0.1:{self.port}/")
        self.ns = await server.register_namespace("urn:example:plc")
        robot = await server.nodes.objects.add_object(ua.NodeId("Robot1", self.ns), ua.QualifiedName("Robot1", self.ns))
        for name, (vtype, value) in SIGNALS.items():
            node = await robot.add_variable(
                ua.NodeId(f"Robot1.{name}", self.ns), ua.QualifiedName(name, self.ns), ua.Variant(value, vtype)
            )
            await node.set_writable()
            self.nodes[name] = node
        await server.start()
        self.server = server
        self._scan = asyncio.get_running_loop().create_task(self._program())

    async def stop(self) -> None:
        if self._scan is not None:
            self._scan.cancel()
            with contextlib.suppress(asyncio.CancelledError):
                await self._scan
        if self.server is not None:
            await self.server.stop()
            self.server = None

    async def get(self, name: str) -> Any:
        return await self.nodes[name].read_value()

    async def set(self, name: str, value: Any) -> None:
        await self.nodes[name].write_value(ua.Variant(value, SIGNALS[name][0]))

    async def _program(self) -> None:
        last: dict[str, bool] = {}
        t = 0.0
        while True:
            await asyncio.sleep(0.01)
            v = {n: await self.get(n) for n in SIGNALS}
            rising = {n for n in ("start", "stop", "reset", "program_strobe") if v[n] and not last.get(n)}
            last = {n: bool(v[n]) for n in ("start", "stop", "reset", "program_strobe")}
            if v["drives_are_on"] != v["drives_on"]:
                await self.set("drives_are_on", v["drives_on"])
            if "program_strobe" in rising:
                await self.set("program_echo", v["program_number"])
                await self.set("program_name_echo", v["program_name"])
            if "reset" in rising and v["fault"]:
                await self.set("fault", False)
                await self.set("fault_code", 0)
            if "start" in rising and v["drives_on"] and not v["fault"] and not v["running"]:
                if v["program_echo"] == FAULT_PROGRAM:
                    await self.set("fault_code", FAULT_PROGRAM)
                    await self.set("fault", True)
                elif v["program_echo"]:
                    await self.set("running", True)
                    await self.set("program_end", False)
            if v["running"] and ("stop" in rising or not v["drives_on"]):
                await self.set("running", False)
            if v["running"]:
                t += 0.01
                await self.set("joints", [0.1 * (i + 1) * math.sin(t) for i in range(6)])


async def main(port: int) -> None:
    plc = PLC(port)
    await plc.start()
    print(f"listening ns={plc.ns}", flush=True)
    try:
        await asyncio.Event().wait()
    finally:
        await plc.stop()


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=(__doc__ or "").splitlines()[0])
    parser.add_argument("--port", type=int, default=4850)
    asyncio.run(main(parser.parse_args().port))
