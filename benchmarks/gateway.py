"""The gateway section of ``make bench`` (docs/performance.md, "Gateway"): PackML units whose state
machine runs in a PLC (``interop/plc_packtags.js``, node-opcua's server with a TR88 scan-cycle
program, 50 units) served by one uacell process through the ``opcua-packtags`` driver (one PLC
connection, its subscription at 20 ms).

- command round trip: an asyncua client's Reset on U1 until the PLC's StateCurrent left Stopped
  (read by a second client polling the PLC every 2 ms), p50/p99;
- mirror latency: a command taken at the PLC's own panel (its CntrlCmd and CmdChangeRequest written
  straight to the PLC) until uacell's CurrentState reports it to a subscribed client, p50/p99;
  target for both: p99 <= the subscription interval + 20 ms;
- U2 walked through all 17 TR88 states with every command's handshake;
- all 50 units reset at once: every one reaches Idle (nothing lost);
- PackML units in a Modbus-only PLC (the example, ``uacell.gateway.examples.packtags_plc``, 10
  units in the default register layout, the ``modbus-packtags`` driver polling every 20 ms): command
  round trip and mirror latency as above, the PLC read by a second Modbus client every 2 ms; target
  p99 <= the poll + 20 ms;
- the same for 4 PackML units in an S7 PLC (the example ``uacell.gateway.examples.s7_plc``, snap7's
  server, ``s7-packtags`` polling every 20 ms) and in a Logix controller (the example
  ``uacell.gateway.examples.logix_plc``, cpppo's simulator, ``logix-packtags`` polling every 20 ms);
- a robot over Modbus signals (the example controller, ``uacell.gateway.examples.robot_controller``,
  served from the shipped ``modbus-robot`` cell with a 20 ms poll): a Start's round trip until the
  controller's ``running`` bit rose, and the controller's program end (``running`` fell) until the
  TaskControl's CurrentState change (Ready) reaches a subscribed client; both read from the
  controller by a second Modbus client every 2 ms; target p99 <= the poll + 20 ms.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import shutil
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from benchmarks.harness import Peers, Report, free_port, percentile, process, served, text_of, until

ROOT = Path(__file__).resolve().parent.parent
UNITS = 50
INTERVAL = 0.02  # the driver's subscription interval ([the driver's] publishing_interval default)
POLL_INTERVAL = 0.02  # the same PLC polled (mode = "poll")
WALK = [  # (machine, method, the state it ends in)
    ("MachineState", "Reset", "Idle"),
    ("ExecuteState", "Start", "Execute"),
    ("ExecuteState", "Hold", "Held"),
    ("ExecuteState", "Unhold", "Execute"),
    ("ExecuteState", "Suspend", "Suspended"),
    ("ExecuteState", "Unsuspend", "Execute"),
    ("ExecuteState", "ToComplete", "Complete"),
    ("ExecuteState", "Reset", "Idle"),
    ("MachineState", "Stop", "Stopped"),
    ("BaseStateMachine", "Abort", "Aborted"),
    ("BaseStateMachine", "Clear", "Stopped"),
]
PATHS = {
    "BaseStateMachine": "BaseStateMachine",
    "MachineState": "BaseStateMachine.MachineState",
    "ExecuteState": "BaseStateMachine.MachineState.ExecuteState",
}


def gateway_section(report: Report, peers: Peers, args: argparse.Namespace) -> None:

    if shutil.which("node") is None:
        print("== gateway: skipped, node is not installed", flush=True)
        return
    rounds = 10 if args.quick else 40
    print(f"== gateway ({UNITS} PackML units in a node-opcua PLC, {rounds} round trips each way)", flush=True)
    plc_port = free_port()
    units = [f"U{i}" for i in range(1, UNITS + 1)]
    plc_cmd = ["node", str(ROOT / "interop" / "plc_packtags.js"), str(plc_port), ",".join(units), "200"]
    with process(plc_cmd, ROOT / "interop", ready="listening"):
        endpoint = f"opc.tcp://127.0.0.1:{plc_port}/"
        text = "".join(
            f'[[packml_units]]\nname = "{u}"\nequipment = {{ driver = "opcua-packtags", '
            f'endpoint = "{endpoint}", prefix = "ns=1;s={u}.PackTags" }}\n\n'
            for u in units
        )
        with served(peers, "gateway", text) as server:
            raw = asyncio.run(_measure(server.endpoint, endpoint, rounds))
        # the same PLC polled instead: one Read of every watched tag each POLL_INTERVAL
        poll_text = text.replace('PackTags" }', f'PackTags", mode = "poll", interval = {POLL_INTERVAL} }}')
        with served(peers, "gateway-poll", poll_text) as server:
            raw["poll_mirror_ms"] = asyncio.run(_measure_poll_mirror(server.endpoint, endpoint, rounds))
    report.raw["gateway"] = raw
    bare = raw["bare_mirror_ms"]
    print(
        f"  (the floor: a bare asyncua client subscribed to the PLC at {INTERVAL * 1000:.0f} ms sees its change after "
        f"p50 / p99 {percentile(bare, 0.5) or 0:.1f} / {percentile(bare, 0.99) or 0:.1f} ms)",
        flush=True,
    )
    _latency_rows(
        report,
        raw,
        (
            ("command round trip (call -> the PLC sees it)", "command_ms"),
            ("mirror latency (PLC -> client)", "mirror_ms"),
        ),
        f"subscription {INTERVAL * 1000:.0f} ms",
        (INTERVAL + 0.020) * 1000,
        rounds,
    )
    report.add(
        "gateway: TR88 states walked through the PLC (of 17)",
        str(len(raw["states_seen"])),
        ", ".join(sorted(raw["states_seen"])),
        len(raw["states_seen"]) / 17,
        "all 17 (1.0x)",
        lambda x: x >= 1.0,
    )
    report.add(
        f"gateway: {UNITS} units reset at once on one connection, reached Idle",
        str(raw["units_idle"]),
        f"{UNITS} units",
        raw["units_idle"] / UNITS,
        "all (1.0x)",
        lambda x: x >= 1.0,
    )
    for part in POLLED:
        polled_section(report, peers, part, part.rounds(rounds))
    _latency_rows(
        report,
        raw,
        (("mirror latency, the PLC polled (PLC -> client)", "poll_mirror_ms"),),
        f"poll {POLL_INTERVAL * 1000:.0f} ms, {UNITS} units",
        (POLL_INTERVAL + 0.020) * 1000,
        rounds,
    )
    robot_section(report, peers, rounds // 2)


@dataclass(frozen=True)
class PolledPart:
    """One part of the gateway section whose PLC the driver polls: the example PLC to start, the
    cell's units on it, the test's own look into the PLC, and the report rows."""

    name: str  # "Modbus", "S7", "Logix": the rows' prefix, the peer's and the figures' names
    example: str  # the example PLC's module (uacell.gateway.examples.<example>)
    plc_args: Callable[[int], list[str]]  # its arguments besides --port, for this many units
    unit: Callable[[int, int], str]  # (i, PLC port) -> unit Mi's equipment table in the cell file
    probe: Callable[[int], Any]  # PLC port -> the test's own connection to it
    units: int
    rounds: Callable[[int], int]  # the section's rounds -> this part's
    reference: str  # what the latency is measured against
    note: str = ""


POLL = 0.02  # every polled driver's poll interval in its part
_LOGIX_MAP = ", ".join(f'"Command.Parameter[{j}].Value" = "{{u}}_Parameter[{j}]"' for j in range(5))
POLLED = (
    PolledPart(
        "Modbus", "packtags_plc",
        lambda n: ["--units", str(n), "--acting", "0.2"],
        lambda i, port: f'driver = "modbus-packtags", host = "127.0.0.1", port = {port}, base = {100 * i}',
        lambda port: _ModbusProbe(port), 10, lambda r: r // 2, "Modbus poll",
    ),
    PolledPart(
        "S7", "s7_plc",
        lambda n: ["--units", str(n), "--acting", "0.2"],
        lambda i, port: f'driver = "s7-packtags", host = "127.0.0.1", port = {port}, db = 1, start = {200 * i}',
        lambda port: _S7Probe(port), 4, lambda r: r // 2, "S7 poll",
    ),
    PolledPart(
        "Logix", "logix_plc",
        lambda n: ["--units", ",".join(f"M{i}" for i in range(n)), "--acting", "0.2"],
        lambda i, port: (
            f'driver = "logix-packtags", host = "127.0.0.1", port = {port}, prefix = "M{i}", confirm_timeout = 10.0, '
            f"map = {{ {_LOGIX_MAP.format(u=f'M{i}')} }}"
        ),
        lambda port: _LogixProbe(port), 4, lambda r: max(3, r // 4),  # cpppo's simulator: about 40 ms a request
        "EtherNet/IP poll", " (cpppo's simulator)",
    ),
)  # fmt: skip


def polled_section(report: Report, peers: Peers, part: PolledPart, rounds: int) -> None:
    """One polled part (module doc): the example PLC, ``part.units`` units M0.. on it, polled every POLL."""
    import sys

    plc_port = free_port()
    cmd = [sys.executable, "-m", f"uacell.gateway.examples.{part.example}", "--port", str(plc_port)]
    with process([*cmd, *part.plc_args(part.units)], ROOT, ready="listening"):
        text = "".join(
            f'[[packml_units]]\nname = "M{i}"\nequipment = {{ {part.unit(i, plc_port)}, interval = {POLL} }}\n\n'
            for i in range(part.units)
        )
        with served(peers, f"{part.name.lower()}-gateway", text) as server:
            raw = asyncio.run(_measure_polled(server.endpoint, lambda: part.probe(plc_port), rounds))
    report.raw[f"gateway_{part.name.lower()}"] = raw
    _latency_rows(
        report,
        raw,
        (
            (f"{part.name} PackML command round trip (call -> the PLC sees it)", "command_ms"),
            (f"{part.name} PackML mirror latency (PLC -> client)", "mirror_ms"),
        ),
        f"{part.reference} {POLL * 1000:.0f} ms, {part.units} units"
        + (" (cpppo's simulator)" if part.name == "Logix" else ""),
        (POLL + 0.020) * 1000,
        rounds,
    )


ROBOT_POLL = 0.02  # the modbus-signals driver's poll in the robot part
TASK_CONTROL = "Palletizer.Controllers.Cabinet.TaskControls.Main.TaskControlOperation.TaskControlStateMachine"
SYSTEM = "Palletizer.Controllers.Cabinet.SystemOperation.SystemOperationStateMachine"


def robot_section(report: Report, peers: Peers, rounds: int) -> None:
    """The robot part (module doc): the example controller and the shipped cell, nothing else."""
    import sys

    from uacell.core.cell_file import builtin_cell_path

    ctrl_port = free_port()
    ctrl_cmd = [sys.executable, "-m", "uacell.gateway.examples.robot_controller", "--port", str(ctrl_port)]
    with process([*ctrl_cmd, "--cycle", "0.3"], ROOT):
        text = builtin_cell_path("modbus-robot").read_text().replace("port = 5020", f"port = {ctrl_port}")
        with served(peers, "robot-gateway", text.replace("unit = 1 }", f"unit = 1, poll = {ROBOT_POLL} }}")) as server:
            raw = asyncio.run(_measure_robot(server.endpoint, ctrl_port, rounds))
    report.raw["gateway_robot"] = raw
    _latency_rows(
        report,
        raw,
        (
            ("robot Start round trip (call -> running)", "start_ms"),
            ("robot program end -> client (TaskControl Ready)", "end_ms"),
        ),
        f"Modbus poll {ROBOT_POLL * 1000:.0f} ms",
        (ROBOT_POLL + 0.020) * 1000,
        rounds,
    )


def _latency_rows(
    report: Report, raw: dict[str, Any], rows: Iterable[tuple[str, str]], reference: str, target: float, rounds: int
) -> None:
    """One report row per latency (p50/p99 of ``raw[key]``, ms), against ``target`` ms; a row with
    fewer samples than ``rounds`` has no ratio (something did not arrive)."""
    for name, key in rows:
        values = raw[key]
        p99 = percentile(values, 0.99)
        report.add(
            f"gateway: {name}, p50 / p99",
            f"{percentile(values, 0.5) or 0:.1f} / {p99 or 0:.1f} ms ({len(values)} of {rounds})",
            reference,
            None if p99 is None or len(values) < rounds else p99 / target,
            f"p99 <= {target:.0f} ms (<= 1.0x)",
            lambda x: x <= 1.0,
        )


async def _measure_robot(uacell_endpoint: str, ctrl_port: int, rounds: int) -> dict[str, Any]:
    import logging

    from asyncua import Client, ua

    from uacell.gateway.modbus import ModbusConnection
    from uacell.gateway.modbus_robot import ModbusRobotIO, signal_tags

    logging.getLogger("asyncua").setLevel(logging.ERROR)
    raw: dict[str, Any] = {"start_ms": [], "end_ms": []}
    conn = ModbusConnection("127.0.0.1", ctrl_port, timeout=0.5)
    deadline = time.perf_counter() + 15
    while not await conn.connect():
        if time.perf_counter() > deadline:
            raise TimeoutError("the example controller did not listen")
        await asyncio.sleep(0.05)
    io = ModbusRobotIO(conn, 1, signal_tags())

    async def until_running(running: bool, timeout: float = 5.0) -> float:
        """When the controller's running bit is ``running`` (polled every 2 ms)."""
        limit = time.perf_counter() + timeout
        while (await io.status()).running != running:
            if time.perf_counter() > limit:
                raise TimeoutError(f"the controller's running did not become {running}")
            await asyncio.sleep(0.002)
        return time.perf_counter()

    try:
        async with Client(uacell_endpoint, timeout=30) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")

            async def call(obj: str, method: str, *args: ua.Variant) -> Any:
                node = client.get_node(ua.NodeId(obj, ns))
                return await node.call_method(ua.NodeId(f"{obj}.{method}", ns), *args)

            arrived: list[tuple[float, str]] = []

            class Handler:
                def datachange_notification(self, n: Any, val: Any, data: Any) -> None:
                    if isinstance(val, ua.LocalizedText):
                        arrived.append((time.perf_counter(), val.Text or ""))

            assert await call(SYSTEM, "GetReady") == 0
            await until(lambda: text_of(client, ns, SYSTEM), "Ready")
            assert await call(TASK_CONTROL, "LoadByName", ua.Variant("pick_and_place", ua.VariantType.String)) == 0
            sub = await client.create_subscription(0, Handler())
            task_state = client.get_node(ua.NodeId(f"{TASK_CONTROL}.CurrentState", ns))
            await sub.subscribe_data_change(task_state, queuesize=10)
            await asyncio.sleep(0.2)  # the subscription's first notification (the current state) is not a round's
            for _ in range(rounds):
                await until(lambda: text_of(client, ns, TASK_CONTROL), "Ready")
                arrived.clear()
                t0 = time.perf_counter()
                start = asyncio.ensure_future(call(TASK_CONTROL, "Start"))
                raw["start_ms"].append((await until_running(True) - t0) * 1000)
                assert await start == 0
                ended = await until_running(False)
                limit = time.perf_counter() + 5
                while not any(t == "Ready" and at >= t0 for at, t in arrived) and time.perf_counter() < limit:
                    await asyncio.sleep(0.001)
                seen = next((at for at, t in arrived if t == "Ready" and at >= t0), None)
                if seen is not None:
                    raw["end_ms"].append(max(0.0, seen - ended) * 1000)
            await sub.delete()
    finally:
        conn.close()
    return raw


class _ModbusProbe:
    """The test's own look into the example Modbus PLC: a unit's state, a command at its panel."""

    def __init__(self, port: int) -> None:
        from uacell.gateway.modbus import ModbusConnection

        self.conn = ModbusConnection("127.0.0.1", port, timeout=1.0)

    async def open(self) -> None:
        assert await self.conn.connect()

    def _tag(self, unit: int, key: str) -> Any:
        from uacell.gateway.packml_modbus import Point, resolve_modbus

        return Point.parse(resolve_modbus("bench", 1, 100 * unit)[key].address).tag

    async def state(self, unit: int) -> int:
        return int(await self.conn.read(self._tag(unit, "Status.StateCurrent"), 1))

    async def command(self, unit: int, number: int) -> None:
        await self.conn.write(self._tag(unit, "Command.CntrlCmd"), number, 1)
        await self.conn.write(self._tag(unit, "Command.CmdChangeRequest"), True, 1)

    async def close(self) -> None:
        self.conn.close()


class _S7Probe:
    """The same into the example S7 PLC (unit i from byte 200 * i of DB 1)."""

    def __init__(self, port: int) -> None:
        from uacell.gateway.packml_s7 import S7Connection

        self.conn = S7Connection("127.0.0.1", port, 0, 1, 1.0)

    async def open(self) -> None:
        assert await self.conn.connect()

    def _address(self, unit: int, key: str) -> Any:
        from uacell.gateway.packml_s7 import resolve_s7
        from uacell.gateway.s7 import S7Address

        return S7Address.parse(resolve_s7("bench", 1, 200 * unit)[key].address)

    async def state(self, unit: int) -> int:
        a = self._address(unit, "Status.StateCurrent")
        return int(a.decode(await self.conn.read(a.db, a.byte, 4), a.byte))

    async def command(self, unit: int, number: int) -> None:
        cmd, req = self._address(unit, "Command.CntrlCmd"), self._address(unit, "Command.CmdChangeRequest")
        await self.conn.write([(cmd, number), (req, True)])

    async def close(self) -> None:
        await self.conn.close()


class _LogixProbe:
    """The same into the example Logix controller (units named M<i>)."""

    def __init__(self, port: int) -> None:
        from uacell.gateway.packml_logix import LogixConnection

        self.conn = LogixConnection("127.0.0.1", port, 0, 1.0)

    async def open(self) -> None:
        assert await self.conn.connect()

    async def state(self, unit: int) -> int:
        (value,) = await self.conn.read([f"M{unit}.Status.StateCurrent"])
        return int(value)

    async def command(self, unit: int, number: int) -> None:
        await self.conn.write([(f"M{unit}.Command.CntrlCmd", number), (f"M{unit}.Command.CmdChangeRequest", True)])

    async def close(self) -> None:
        await asyncio.to_thread(self.conn.close)


async def _measure_polled(uacell_endpoint: str, probe: Callable[[], Any], rounds: int) -> dict[str, Any]:
    """Command round trip on M1 and mirror latency on M3 (its command written straight to the PLC),
    the PLC read by the test's own connection (``probe()``, made on the loop) every 2 ms."""
    import logging

    from asyncua import Client, ua

    logging.getLogger("asyncua").setLevel(logging.ERROR)
    raw: dict[str, Any] = {"command_ms": [], "mirror_ms": []}
    plc = probe()  # pymodbus's client wants the running loop
    await plc.open()

    async def until_plc(unit: int, state: int, leaves: bool = False, timeout: float = 10.0) -> float:
        """When the PLC's state is ``state`` (``leaves``: no longer), read every 2 ms."""
        limit = time.perf_counter() + timeout
        while ((await plc.state(unit)) == state) == leaves:
            if time.perf_counter() > limit:
                raise TimeoutError(f"M{unit}: the PLC did not reach {state}")
            await asyncio.sleep(0.002)
        return time.perf_counter()

    def machine(unit: int, name: str) -> str:
        return f"M{unit}.{PATHS[name]}"

    try:
        async with Client(uacell_endpoint, timeout=30) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")

            async def call(unit: int, name: str, method: str) -> ua.StatusCode:
                obj = machine(unit, name)
                req = ua.CallMethodRequest(ObjectId=ua.NodeId(obj, ns), MethodId=ua.NodeId(f"{obj}.{method}", ns))
                (res,) = await client.uaclient.call([req])
                return res.StatusCode

            for _ in range(rounds):
                t0 = time.perf_counter()
                assert (await call(1, "MachineState", "Reset")).is_good()
                raw["command_ms"].append((await until_plc(1, 2, leaves=True) - t0) * 1000)
                await until(lambda: text_of(client, ns, machine(1, "ExecuteState")), "Idle")
                assert (await call(1, "MachineState", "Stop")).is_good()
                await until(lambda: text_of(client, ns, machine(1, "MachineState")), "Stopped")

            arrived: list[tuple[float, str]] = []

            class Handler:
                def datachange_notification(self, n: Any, val: Any, data: Any) -> None:
                    if isinstance(val, ua.LocalizedText):
                        arrived.append((time.perf_counter(), val.Text or ""))

            sub = await client.create_subscription(0, Handler())
            state = client.get_node(ua.NodeId(f"{machine(3, 'ExecuteState')}.CurrentState", ns))
            await sub.subscribe_data_change(state, queuesize=10)
            for _ in range(rounds):
                arrived.clear()
                await plc.command(3, 1)  # the PLC's own panel: Reset
                changed = await until_plc(3, 15)
                limit = time.perf_counter() + 5
                while not any(t == "Resetting" for _, t in arrived) and time.perf_counter() < limit:
                    await asyncio.sleep(0.001)
                seen = next((at for at, t in arrived if t == "Resetting"), None)
                if seen is not None:
                    raw["mirror_ms"].append(max(0.0, seen - changed) * 1000)
                await until(lambda: text_of(client, ns, machine(3, "ExecuteState")), "Idle")
                assert (await call(3, "MachineState", "Stop")).is_good()
                await until(lambda: text_of(client, ns, machine(3, "MachineState")), "Stopped")
            await sub.delete()
    finally:
        await plc.close()
    return raw


class _Rig:
    """An asyncua client of uacell and one of the PLC, with what the measurements do with them."""

    def __init__(self, ua_client: Any, plc_client: Any, ns: int) -> None:
        self.ua_client, self.plc_client, self.ns = ua_client, plc_client, ns

    def node(self, unit: str, machine: str) -> Any:
        from asyncua import ua

        return self.ua_client.get_node(ua.NodeId(f"{unit}.{PATHS[machine]}", self.ns))

    async def call(self, unit: str, machine: str, method: str, *args: Any) -> Any:
        from asyncua import ua

        req = ua.CallMethodRequest(
            ObjectId=ua.NodeId(f"{unit}.{PATHS[machine]}", self.ns),
            MethodId=ua.NodeId(f"{unit}.{PATHS[machine]}.{method}", self.ns),
            InputArguments=list(args),
        )
        (res,) = await self.ua_client.uaclient.call([req])
        return res.StatusCode

    def tag(self, unit: str, path: str) -> Any:
        from asyncua import ua

        return self.plc_client.get_node(ua.NodeId(f"{unit}.PackTags.{path}", 1))

    async def until_plc(self, unit: str, state: int, timeout: float = 10.0, leaves: bool = False) -> float:
        """When the PLC's state is ``state`` (``leaves``: is no longer ``state``), read every 2 ms."""
        deadline = time.perf_counter() + timeout
        while (int(await self.tag(unit, "Status.StateCurrent").read_value()) == state) == leaves:
            if time.perf_counter() > deadline:
                raise TimeoutError(f"{unit}: the PLC did not reach {state}")
            await asyncio.sleep(0.002)
        return time.perf_counter()

    async def text(self, unit: str, machine: str) -> str | None:
        dv = await self.node(unit, machine).get_child("0:CurrentState")
        value = await dv.read_data_value(raise_on_bad_status=False)
        return value.Value.Value.Text if value.StatusCode.is_good() else None

    async def until_text(self, unit: str, machine: str, wanted: str, timeout: float = 10.0) -> None:
        deadline = time.perf_counter() + timeout
        while await self.text(unit, machine) != wanted:
            if time.perf_counter() > deadline:
                raise TimeoutError(f"{unit}.{machine} did not reach {wanted}")
            await asyncio.sleep(0.005)

    async def mirror(self, unit: str, rounds: int, bare_interval: float = 0.0) -> tuple[list[float], list[float]]:
        """The PLC's own panel resets ``unit``: ms until uacell's client sees Resetting, and (with
        ``bare_interval``) until a bare asyncua client subscribed to the PLC's StateCurrent sees it."""
        from asyncua import ua

        seen_ms: list[float] = []
        bare_ms: list[float] = []
        arrived: list[tuple[float, str]] = []
        bare: list[tuple[float, int]] = []

        class Handler:
            def datachange_notification(self, n: Any, val: Any, data: Any) -> None:
                if isinstance(val, ua.LocalizedText):
                    arrived.append((time.perf_counter(), val.Text or ""))

        class Bare:
            def datachange_notification(self, n: Any, val: Any, data: Any) -> None:
                bare.append((time.perf_counter(), int(val)))

        sub = await self.ua_client.create_subscription(0, Handler())
        await sub.subscribe_data_change(await self.node(unit, "ExecuteState").get_child("0:CurrentState"), queuesize=10)
        bare_sub = None
        if bare_interval:
            bare_sub = await self.plc_client.create_subscription(bare_interval * 1000, Bare())
            # sampled as uacell's link samples the PLC's tags (asyncua's default would be 50 ms)
            await bare_sub.subscribe_data_change(self.tag(unit, "Status.StateCurrent"), sampling_interval=0.0)
        for _ in range(rounds):
            arrived.clear()
            bare.clear()
            await self.tag(unit, "Command.CntrlCmd").write_value(ua.Variant(1, ua.VariantType.Int32))
            await self.tag(unit, "Command.CmdChangeRequest").write_value(ua.Variant(True, ua.VariantType.Boolean))
            changed = await self.until_plc(unit, 15)
            deadline = time.perf_counter() + 5
            while not any(t == "Resetting" for _, t in arrived) and time.perf_counter() < deadline:
                await asyncio.sleep(0.001)
            seen = next((at for at, t in arrived if t == "Resetting"), None)
            if seen is not None:
                seen_ms.append(max(0.0, seen - changed) * 1000)
            floor = next((at for at, v in bare if v == 15), None)
            if floor is not None:
                bare_ms.append(max(0.0, floor - changed) * 1000)
            await self.until_text(unit, "ExecuteState", "Idle")
            assert (await self.call(unit, "MachineState", "Stop")).is_good()
            await self.until_text(unit, "MachineState", "Stopped")
        await sub.delete()
        if bare_sub is not None:
            await bare_sub.delete()
        return seen_ms, bare_ms


async def _measure_poll_mirror(uacell_endpoint: str, plc_endpoint: str, rounds: int) -> list[float]:
    import logging

    from asyncua import Client

    logging.getLogger("asyncua").setLevel(logging.ERROR)
    async with Client(uacell_endpoint, timeout=30) as ua_client, Client(plc_endpoint, timeout=30) as plc_client:
        rig = _Rig(ua_client, plc_client, await ua_client.get_namespace_index("urn:uacell:cell"))
        await rig.until_text("U3", "ExecuteState", "Idle")  # where the first uacell left every unit
        assert (await rig.call("U3", "MachineState", "Stop")).is_good()
        await rig.until_text("U3", "MachineState", "Stopped")
        seen, _ = await rig.mirror("U3", rounds)
    return seen


async def _measure(uacell_endpoint: str, plc_endpoint: str, rounds: int) -> dict[str, Any]:
    import logging

    from asyncua import Client, ua

    logging.getLogger("asyncua").setLevel(logging.ERROR)
    raw: dict[str, Any] = {"command_ms": [], "mirror_ms": [], "bare_mirror_ms": [], "states_seen": [], "units_idle": 0}
    async with Client(uacell_endpoint, timeout=30) as ua_client, Client(plc_endpoint, timeout=30) as plc_client:
        rig = _Rig(ua_client, plc_client, await ua_client.get_namespace_index("urn:uacell:cell"))
        node, call, until_plc, until_text = rig.node, rig.call, rig.until_plc, rig.until_text

        # command round trip: Reset on U1 until the PLC left Stopped (the call answers once it has), then Stop back
        for _ in range(rounds):
            t0 = time.perf_counter()
            assert (await call("U1", "MachineState", "Reset")).is_good()
            raw["command_ms"].append((await until_plc("U1", 2, leaves=True) - t0) * 1000)
            await until_text("U1", "ExecuteState", "Idle")
            assert (await call("U1", "MachineState", "Stop")).is_good()
            await until_text("U1", "MachineState", "Stopped")

        # mirror latency: the PLC's own panel resets U3; uacell's client sees Resetting; beside it, the
        # floor: a bare asyncua client subscribed to the PLC's StateCurrent as uacell is
        raw["mirror_ms"], raw["bare_mirror_ms"] = await rig.mirror("U3", rounds, bare_interval=INTERVAL)

        # every TR88 state, every command, on U2
        states: set[str] = set()
        seen_states: list[str] = []

        class Walk:
            def datachange_notification(self, n: Any, val: Any, data: Any) -> None:
                if isinstance(val, ua.LocalizedText) and val.Text:
                    seen_states.append(val.Text)

        walk = await ua_client.create_subscription(0, Walk())
        for machine in PATHS:
            # every state it passes (a queue of one would keep the last of a turn's changes, decision 83)
            await walk.subscribe_data_change(await node("U2", machine).get_child("0:CurrentState"), queuesize=10)
        for machine, method, end in WALK:
            args = [ua.Variant([], ua.VariantType.ExtensionObject, is_array=True)] if method == "Start" else []
            code = await call("U2", machine, method, *args)
            assert code.is_good(), (method, code)
            target = "ExecuteState" if end in ("Idle", "Execute", "Held", "Suspended", "Complete") else "MachineState"
            if end == "Aborted":
                target = "BaseStateMachine"
            await until_text("U2", target, end)
        await asyncio.sleep(0.2)
        states.update(seen_states)
        await walk.delete()
        tr88 = {
            "Clearing", "Stopped", "Starting", "Idle", "Suspended", "Execute", "Stopping", "Aborting", "Aborted",
            "Holding", "Held", "Unholding", "Suspending", "Unsuspending", "Resetting", "Completing", "Complete",
        }  # fmt: skip
        raw["states_seen"] = sorted(states & tr88)

        # all units at once
        units = [f"U{i}" for i in range(4, UNITS + 1)] + ["U1", "U2", "U3"]
        await asyncio.gather(*(call(u, "MachineState", "Reset") for u in units))
        idle = 0
        for u in units:
            with contextlib.suppress(TimeoutError):
                await until_text(u, "ExecuteState", "Idle", timeout=15)
                idle += 1
        raw["units_idle"] = idle
    return raw
