"""The robots section of ``make bench`` (docs/performance.md, "Robots"): gateway robots served by one
uacell process each, from the cell file alone.

- ``modbus-signals`` against the example controller (``uacell.gateway.examples.robot_controller``, its
  joints in input registers 20..31), the driver polling every 20 ms (50 Hz) with its axes mapped;
- ``opcua-signals`` against the example OPC UA PLC (``uacell.gateway.examples.robot_plc``, its own
  process), the driver subscribed at 20 ms;
- ``ur-dashboard`` against ursim (``tests/ursim``: UR's Dashboard Server and Modbus register map, its
  own process), the driver polling every 20 ms.

Measured: LoadByName's round trip (the controller's program selected and confirmed; two programs
alternately, one call every 100 ms: the signals drivers keep a pulse signal low for ``pulse_gap``,
50 ms, before they set it again) per driver, p50 / p99; Start until the call answers (it answers once
the controller runs the program: the task is then Executing), p50 / p99; the axis positions from the
controller's change (read by a second Modbus client every 2 ms) to a client subscribed to uacell's
ActualPosition, p99 against the poll + 20 ms; the uacell process's CPU while one robot streams its 6
axes at 50 Hz to a subscribed client, as a share of one core (target < 5 %), beside its CPU while it
polls the same robot standing still.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from benchmarks.harness import Peers, Report, cpu_seconds, free_port, percentile, process, served, text_of, until

ROOT = Path(__file__).resolve().parent.parent
POLL = 0.02
PAUSE = 0.1  # seconds between two timed calls (more than the signals drivers' pulse_gap)
CTRL = "Palletizer.Controllers.Cabinet"
TC = f"{CTRL}.TaskControls.Main.TaskControlOperation.TaskControlStateMachine"
SO = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
AXIS = "Palletizer.MotionDevices.Arm1.Axes.Axis{}.ParameterSet.ActualPosition"
MOTION = (
    f'unit = 1, poll = {POLL}, motion = {{ position = ["input", 20, "int16"], speed = ["input", 26, "int16"],'
    " scale = 0.01, speed_scale = 0.01 } }"
)
UR_CELL = """
[[robots]]
name = "Palletizer"
  [[robots.controllers]]
  name = "Cabinet"
  programs = {{ pick_and_place = "pick_and_place.urp", palletize = "palletize.urp" }}
    [robots.controllers.equipment]
    driver = "ur-dashboard"
    host = "127.0.0.1"
    port = {dashboard}
    modbus_port = {modbus}
    poll = {poll}
    [[robots.controllers.task_controls]]
    name = "Main"
  [[robots.motion_devices]]
  name = "Arm1"
  axes = 6
"""


OPCUA_CELL = """
[[robots]]
name = "Palletizer"
  [[robots.controllers]]
  name = "Cabinet"
  programs = {{ pick_and_place = 3, palletize = 7 }}
    [robots.controllers.equipment]
    driver = "opcua-signals"
    endpoint = "opc.tcp://127.0.0.1:{port}/"
    prefix = "ns={ns};s=Robot1"
    interval = {interval}
    [[robots.controllers.task_controls]]
    name = "Main"
  [[robots.motion_devices]]
  name = "Arm1"
  axes = 6
"""


@contextlib.contextmanager
def _plc(port: int) -> Iterator[int]:
    """The example OPC UA PLC (``uacell.gateway.examples.robot_plc``) as its own process: its namespace."""
    cmd = [sys.executable, "-m", "uacell.gateway.examples.robot_plc", "--port", str(port)]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert proc.stdout is not None
        ns = next(int(line.split("ns=")[1]) for line in proc.stdout if line.startswith("listening"))
        yield ns
    finally:
        proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(10)
        if proc.poll() is None:
            proc.kill()


def robots_section(report: Report, peers: Peers, args: argparse.Namespace) -> None:
    from uacell.core.cell_file import builtin_cell_path

    rounds = 10 if args.quick else 40
    seconds = 3.0 if args.quick else 10.0
    print(f"== robots (modbus-signals and ur-dashboard, {rounds} round trips each, poll {POLL * 1000:.0f} ms)")
    port = free_port()
    cmd = [sys.executable, "-m", "uacell.gateway.examples.robot_controller", "--port", str(port), "--cycle", "3600"]
    with process(cmd, ROOT):
        text = builtin_cell_path("modbus-robot").read_text().replace("port = 5020", f"port = {port}")
        with served(peers, "robot-modbus", text.replace("unit = 1 }", MOTION)) as server:
            assert server.proc is not None
            raw = asyncio.run(_measure_modbus(server.endpoint, port, rounds, seconds, server.proc.pid))
    report.raw["robots_modbus"] = raw
    _rows(report, "modbus-signals", raw, rounds)
    _axis_rows(report, raw)
    plc_port = free_port()
    with _plc(plc_port) as ns:
        with served(peers, "robot-opcua", OPCUA_CELL.format(port=plc_port, ns=ns, interval=POLL)) as server:
            raw = asyncio.run(_measure_ur(server.endpoint, rounds))
    report.raw["robots_opcua"] = raw
    _rows(report, "opcua-signals", raw, rounds)
    dashboard, modbus, control = free_port(), free_port(), free_port()
    with _ursim(peers.tmp / "ursim-programs", dashboard, modbus, control):
        text = UR_CELL.format(dashboard=dashboard, modbus=modbus, poll=POLL)
        with served(peers, "robot-ur", text) as server:
            raw = asyncio.run(_measure_ur(server.endpoint, rounds))
    report.raw["robots_ur"] = raw
    _rows(report, "ur-dashboard", raw, rounds)


def _rows(report: Report, driver: str, raw: dict[str, Any], rounds: int) -> None:
    for name, key in (("LoadByName round trip", "load_ms"), ("Start until Executing", "start_ms")):
        values = raw[key]
        report.add(
            f"robots {driver}: {name}, p50 / p99",
            f"{percentile(values, 0.5) or 0:.1f} / {percentile(values, 0.99) or 0:.1f} ms ({len(values)} of {rounds})",
            f"poll {POLL * 1000:.0f} ms",
            None,
        )


def _axis_rows(report: Report, raw: dict[str, Any]) -> None:
    target = (POLL + 0.020) * 1000
    values = raw["axis_ms"]
    p99 = percentile(values, 0.99)
    report.add(
        "robots modbus-signals: axis change -> subscribed client, p50 / p99",
        f"{percentile(values, 0.5) or 0:.1f} / {p99 or 0:.1f} ms ({len(values)} changes)",
        f"poll {POLL * 1000:.0f} ms",
        None if p99 is None or not values else p99 / target,
        f"p99 <= {target:.0f} ms (<= 1.0x)",
        lambda x: x <= 1.0,
    )
    share = raw["cpu_core_fraction"]
    report.add(
        "robots: uacell CPU, one robot streaming 6 axes at 50 Hz",
        f"{share * 100:.1f} % of a core ({raw['cpu_seconds']:.1f} s; polling it still: "
        f"{raw['still_core_fraction'] * 100:.1f} %)",
        "5 % of one core",
        share / 0.05,
        "< 5 % (<= 1.0x)",
        lambda x: x <= 1.0,
    )


@contextlib.contextmanager
def _ursim(programs: Path, dashboard: int, modbus: int, control: int) -> Iterator[subprocess.Popen[str]]:
    programs.mkdir(parents=True, exist_ok=True)
    for name in ("pick_and_place", "palletize"):
        (programs / f"{name}.urp").write_text(f"<URProgram name={name!r}/>")
    cmd = [sys.executable, "-m", "tests.ursim", "--port", str(dashboard), "--programs-dir", str(programs)]
    cmd += ["--modbus-port", str(modbus), "--control-port", str(control), "--unlock-delay", "0"]
    proc = subprocess.Popen(cmd, cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    try:
        assert proc.stdout is not None
        for line in proc.stdout:
            if line.startswith("ursim ready"):
                break
        yield proc
    finally:
        proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(10)
        if proc.poll() is None:
            proc.kill()


class _Calls:
    def __init__(self, client: Any, ns: int) -> None:
        self.client, self.ns = client, ns

    async def status(self, obj: str, method: str, *args: Any) -> int:
        from asyncua import ua

        node = self.client.get_node(ua.NodeId(obj, self.ns))
        return int(await node.call_method(ua.NodeId(f"{obj}.{method}", self.ns), *args))

    async def timed(self, obj: str, method: str, *args: Any) -> float:
        t0 = time.perf_counter()
        assert await self.status(obj, method, *args) == 0, method
        return (time.perf_counter() - t0) * 1000


async def _cycle(calls: _Calls, raw: dict[str, Any], rounds: int, ns: int) -> None:
    """GetReady, LoadByName round trips alternating two programs, Start/Stop round trips."""
    from asyncua import ua

    names = [ua.Variant(n, ua.VariantType.String) for n in ("pick_and_place", "palletize")]
    assert await calls.status(SO, "GetReady") == 0
    await until(lambda: text_of(calls.client, ns, SO), "Ready", timeout=60)
    for i in range(rounds):
        await asyncio.sleep(PAUSE)  # the strobe's pulse_gap has passed: the handshake alone is timed
        raw["load_ms"].append(await calls.timed(TC, "LoadByName", names[i % 2]))
    assert await calls.status(TC, "LoadByName", names[0]) == 0
    for _ in range(rounds):
        await asyncio.sleep(PAUSE)
        raw["start_ms"].append(await calls.timed(TC, "Start"))
        assert await calls.status(TC, "Stop", ua.Variant(4, ua.VariantType.Int64)) == 0
        await until(lambda: text_of(calls.client, ns, TC), "Ready")


async def _measure_modbus(endpoint: str, port: int, rounds: int, seconds: float, pid: int) -> dict[str, Any]:
    import logging

    from asyncua import Client, ua

    from uacell.gateway.codec import RegisterType
    from uacell.gateway.modbus import ModbusConnection, ModbusTag

    logging.getLogger("asyncua").setLevel(logging.ERROR)
    raw: dict[str, Any] = {"load_ms": [], "start_ms": [], "axis_ms": []}
    conn = ModbusConnection("127.0.0.1", port, timeout=0.5)
    while not await conn.connect():
        await asyncio.sleep(0.05)
    joint = ModbusTag("input", 25, RegisterType("int16"))  # Axis6's position, hundredths of a degree
    try:
        async with Client(endpoint, timeout=30) as client:
            ns = await client.get_namespace_index("urn:uacell:cell")
            calls = _Calls(client, ns)
            await _cycle(calls, raw, rounds, ns)
            # the axes: the controller moves them while the program runs
            arrived: list[tuple[float, float]] = []

            class Handler:
                def datachange_notification(self, n: Any, val: Any, data: Any) -> None:
                    if n.nodeid.Identifier == AXIS.format(6):
                        arrived.append((time.perf_counter(), float(val)))

            sub = await client.create_subscription(0, Handler())
            await sub.subscribe_data_change(
                [client.get_node(ua.NodeId(AXIS.format(i), ns)) for i in range(1, 7)], sampling_interval=0, queuesize=10
            )
            cpu0, wall0 = cpu_seconds(pid), time.perf_counter()
            await asyncio.sleep(seconds)  # polling a still robot: the status, the joints that do not change
            raw["still_core_fraction"] = (cpu_seconds(pid) - cpu0) / (time.perf_counter() - wall0)
            assert await calls.status(TC, "Start") == 0
            changes: list[tuple[float, int]] = []
            t_end = time.perf_counter() + 3.0
            while time.perf_counter() < t_end:  # the controller's changes, as a second client sees them
                value = int(await conn.read(joint, 1))
                if not changes or changes[-1][1] != value:
                    changes.append((time.perf_counter(), value))
                await asyncio.sleep(0.002)
            first: dict[int, float] = {}
            for at, value in changes:
                first.setdefault(value, at)
            for at, degrees in arrived:
                seen = first.get(round(degrees * 100))
                if seen is not None and at >= seen:
                    raw["axis_ms"].append((at - seen) * 1000)
            cpu0, wall0 = cpu_seconds(pid), time.perf_counter()
            await asyncio.sleep(seconds)  # streaming 6 axes at 50 Hz to the subscription
            raw["cpu_seconds"] = time.perf_counter() - wall0
            raw["cpu_core_fraction"] = (cpu_seconds(pid) - cpu0) / raw["cpu_seconds"]
            raw["notifications"] = len(arrived)
            await sub.delete()
            assert await calls.status(TC, "Stop", ua.Variant(4, ua.VariantType.Int64)) == 0
    finally:
        conn.close()
    return raw


async def _measure_ur(endpoint: str, rounds: int) -> dict[str, Any]:
    """The cycle alone (ur-dashboard, opcua-signals): LoadByName and Start round trips."""
    import logging

    from asyncua import Client

    logging.getLogger("asyncua").setLevel(logging.ERROR)
    raw: dict[str, Any] = {"load_ms": [], "start_ms": []}
    async with Client(endpoint, timeout=30) as client:
        ns = await client.get_namespace_index("urn:uacell:cell")
        await _cycle(_Calls(client, ns), raw, rounds, ns)
    return raw
