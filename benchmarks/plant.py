"""The plant section of ``make bench`` (docs/performance.md, "Plant: PubSub"): ``--cells`` uacell
processes (20; 5 with ``--quick``), each serving the demo cell and publishing to one mosquitto, and
one subscriber taking everything.

Each cell's Filler1 gets a new MachSpeed every second (an asyncua client per cell); the subscriber
times each new value from its SourceTimestamp to its arrival (the same clock: one machine). Reported:
messages per second delivered, that latency's p50/p99 (target: p99 <= publishing interval + 50 ms),
every value set seen and no SequenceNumber skipped (nothing lost while the broker is up), CPU (share
of one core) and RSS per publishing cell, and the broker's CPU per 1,000 messages/s, from which
docs/performance.md projects a 500-cell plant.
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import json
import shutil
import subprocess
import time
from collections import defaultdict
from collections.abc import Callable, Coroutine
from dataclasses import dataclass
from datetime import datetime
from pathlib import Path
from typing import Any

from benchmarks.harness import Peer, Peers, Report, cpu_seconds, free_port, percentile, rss_kib

PUBLISHING_INTERVAL = 0.5  # [pubsub] publishing_interval's default
SET_EVERY = 1.0


class Mosquitto:
    def __init__(self, tmp: Path, port: int) -> None:
        self.port = port
        self.conf = tmp / "mosquitto.conf"
        self.conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\nuser root\n")
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
        self.proc = subprocess.Popen([exe, "-c", str(self.conf)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        import socket

        deadline = time.monotonic() + 15
        while time.monotonic() < deadline:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", self.port), 0.2):
                return
            time.sleep(0.05)
        raise RuntimeError("mosquitto did not listen")

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            self.proc.wait(10)


Measure = Callable[[Mosquitto, str, list["Peer"]], Coroutine[Any, Any, dict[str, Any]]]


def with_broker(peers: Peers, title: str, measure: Measure) -> dict[str, Any] | None:
    """``measure(broker, url, started)`` against a mosquitto of its own; the cells it appends to
    ``started`` and the broker are stopped after it. None (and a line saying so) without mosquitto."""

    name = title.split(" ", 1)[0]
    if not (shutil.which("mosquitto") or Path("/usr/sbin/mosquitto").exists()):
        print(f"== {name}: skipped, mosquitto is not installed (make setup installs it)", flush=True)
        return None
    print(f"== {title}", flush=True)
    broker = Mosquitto(peers.tmp, free_port())
    broker.start()
    started: list[Peer] = []
    try:
        return asyncio.run(measure(broker, f"mqtt://127.0.0.1:{broker.port}", started))
    finally:
        for p in started:
            p.stop()
        broker.stop()


def plant_section(report: Report, peers: Peers, args: argparse.Namespace) -> None:
    cells = args.cells
    seconds = 8.0 if args.quick else 20.0

    async def measure(broker: Mosquitto, url: str, started: list[Peer]) -> dict[str, Any]:
        for i in range(cells):
            started.append(await asyncio.to_thread(peers.uacell(pubsub=url, publisher=f"cell{i + 1:03d}").start))
        return await _measure(broker, started, seconds)

    title = f"plant ({cells} publishing cells, one mosquitto, one subscriber, {seconds:.0f} s)"
    raw = with_broker(peers, title, measure)
    if raw is None:
        return
    report.raw["plant"] = raw
    latency = raw["latency_ms"]
    p99 = percentile(latency, 0.99)
    target = PUBLISHING_INTERVAL * 1000 + 50
    report.add(
        f"plant: state change -> subscriber, {cells} cells, p50 / p99",
        f"{percentile(latency, 0.5) or 0:.0f} / {p99 or 0:.0f} ms",
        f"publishing interval {PUBLISHING_INTERVAL * 1000:.0f} ms",
        None if p99 is None else p99 / target,
        f"p99 <= {target:.0f} ms (<= 1.0x)",
        lambda x: x <= 1.0,
    )
    report.add(
        "plant: messages delivered to one subscriber",
        f"{raw['messages_per_second']:.0f}/s",
        f"{cells} cells",
        None,
        "",
        None,
    )
    lost = raw["values_missing"] + raw["sequence_gaps"]
    report.add(
        "plant: values lost (missing values + skipped SequenceNumbers)",
        f"{lost}",
        f"{raw['values_set']} values set",
        lost / raw["values_set"] if raw["values_set"] else None,
        "none lost (0x)",
        lambda x: x == 0,
    )
    report.add(
        "plant: per publishing cell, CPU / RSS",
        f"{raw['cpu_per_cell'] * 100:.1f} % / {raw['rss_mib_per_cell']:.0f} MiB",
        "of one core",
        None,
        "",
        None,
    )
    report.add(
        "plant: mosquitto CPU per 1,000 messages/s",
        f"{raw['broker_cpu_per_1000_msgs'] * 100:.1f} %",
        "of one core",
        None,
        "",
        None,
    )


@dataclass
class Drive:
    """What ``drive_speeds`` did: the values set per cell (by index), how long, the CPU shares."""

    values: dict[int, list[float]]
    wall: float
    cpu: list[float]  # of each cell's process, share of one core
    broker_cpu: float
    rss: list[float]  # MiB, of each cell's process at the end


async def drive_speeds(cells: list[Peer], broker: Mosquitto, seconds: float, settle: float) -> Drive:
    """Set each cell's Filler1 MachSpeed to a new value every ``SET_EVERY`` s for ``seconds`` (an
    asyncua client per cell), then wait ``settle`` s for the last values' way."""
    from asyncua import Client, ua

    clients = [Client(p.endpoint, timeout=30) for p in cells]
    for c in clients:
        await c.connect()
    ns = await clients[0].get_namespace_index("urn:uacell:cell")
    unit, method = ua.NodeId("Filler1", ns), ua.NodeId("Filler1.SetMachSpeed", ns)
    values: dict[int, list[float]] = defaultdict(list)
    pids = [p.proc.pid for p in cells if p.proc is not None]
    cpu0 = [cpu_seconds(pid) for pid in pids]
    broker0 = cpu_seconds(broker.proc.pid) if broker.proc else 0.0
    t0 = time.monotonic()
    step = 0
    while time.monotonic() - t0 < seconds:
        step += 1
        for i, c in enumerate(clients):
            value = float(step * 10 + i % 10) + 0.5
            await c.get_node(unit).call_method(method, ua.Variant(value, ua.VariantType.Float))
            values[i].append(value)
        await asyncio.sleep(max(0.0, t0 + step * SET_EVERY - time.monotonic()))
    await asyncio.sleep(settle)
    wall = time.monotonic() - t0
    cpu = [(cpu_seconds(pid) - c0) / wall for pid, c0 in zip(pids, cpu0, strict=True)]
    broker_cpu = ((cpu_seconds(broker.proc.pid) if broker.proc else 0.0) - broker0) / wall
    rss = [_rss_mib(pid) for pid in pids]
    for c in clients:
        await c.disconnect()
    return Drive(values, wall, cpu, broker_cpu, rss)


async def _measure(broker: Mosquitto, cells: list[Peer], seconds: float) -> dict[str, Any]:
    import logging

    import aiomqtt

    logging.getLogger("asyncua").setLevel(logging.ERROR)

    received: list[tuple[float, str, dict[str, Any]]] = []
    ready = asyncio.Event()

    async def subscribe() -> None:
        async with aiomqtt.Client("127.0.0.1", broker.port, max_queued_incoming_messages=0) as c:
            await c.subscribe("opcua/json/data/#", qos=1)
            ready.set()
            async for m in c.messages:
                received.append((time.time(), str(m.topic), json.loads(m.payload)))

    sub = asyncio.ensure_future(subscribe())
    await asyncio.wait_for(ready.wait(), 15)
    first = len(received)
    run = await drive_speeds(cells, broker, seconds, PUBLISHING_INTERVAL * 2 + 0.2)
    values, wall, cpu, broker_cpu, rss = run.values, run.wall, run.cpu, run.broker_cpu, run.rss
    sub.cancel()
    with contextlib.suppress(asyncio.CancelledError, aiomqtt.MqttError):
        await sub
    window = received[first:]
    latency: list[float] = []
    seen: dict[int, set[float]] = defaultdict(set)
    sequences: dict[str, list[int]] = defaultdict(list)
    for arrived, topic, body in received:
        for m in body.get("Messages", []):
            if m.get("MessageType") != "ua-keepalive":
                sequences[topic].append(m["SequenceNumber"])
            field = m.get("Payload", {}).get("Status/MachSpeed")
            if not field or not topic.endswith("/Filler1"):
                continue
            cell = int(topic.split("/")[3].removeprefix("cell")) - 1
            value = field["Value"]
            if value in values[cell] and value not in seen[cell]:
                seen[cell].add(value)
                changed = datetime.fromisoformat(field["SourceTimestamp"].replace("Z", "+00:00")).timestamp()
                latency.append((arrived - changed) * 1000)
    gaps = sum(sum(1 for a, b in itertools.pairwise(nums) if b != a + 1) for nums in sequences.values())
    set_count = sum(len(v) for v in values.values())
    missing = sum(len(set(values[i]) - seen[i]) for i in values)
    msgs_per_s = len(window) / wall
    return {
        "cells": len(cells),
        "seconds": wall,
        "messages": len(window),
        "messages_per_second": msgs_per_s,
        "latency_ms": latency,
        "values_set": set_count,
        "values_missing": missing,
        "sequence_gaps": gaps,
        "cpu_per_cell": sum(cpu) / len(cpu),
        "rss_mib_per_cell": sum(rss) / len(rss),
        "broker_cpu": broker_cpu,
        "broker_cpu_per_1000_msgs": broker_cpu / max(msgs_per_s / 1000, 1e-9),
    }


def _rss_mib(pid: int) -> float:

    return rss_kib(pid) / 1024
