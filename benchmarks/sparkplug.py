"""The Sparkplug section of ``make bench`` (docs/performance.md, "Plant: Sparkplug B"): ``--cells``
uacell processes (20; 5 with ``--quick``), each serving the demo cell as a Sparkplug B edge node on one
mosquitto, and one host application taking everything (``--only sparkplug``).

The host subscribes before the cells start, so it sees every NBIRTH and DBIRTH. Each cell's Filler1
gets a new MachSpeed every second (an asyncua client per cell); the host times each new value from the
metric's timestamp (the value's SourceTimestamp) to its arrival (one machine, one clock). Reported:
births seen (an NBIRTH and two DBIRTHs per cell, before any DDATA of that node), the latency's p50/p99
(target p99 <= 50 ms: DDATA goes out on change, no publishing interval), every value set seen and no
seq skipped (nothing lost), messages per second, CPU (share of one core) of a cell and the broker's.
"""

from __future__ import annotations

import argparse
import asyncio
import time
from collections import defaultdict
from typing import Any

from benchmarks.harness import Peer, Peers, Report, percentile
from benchmarks.plant import Mosquitto, drive_speeds, with_broker

TARGET_MS = 50.0


def sparkplug_section(report: Report, peers: Peers, args: argparse.Namespace) -> None:
    cells = args.cells
    seconds = 8.0 if args.quick else 20.0

    async def measure(broker: Mosquitto, url: str, started: list[Peer]) -> dict[str, Any]:
        return await _measure(broker, peers, url, cells, started, seconds)

    title = f"sparkplug ({cells} edge nodes, one mosquitto, one host application, {seconds:.0f} s)"
    raw = with_broker(peers, title, measure)
    if raw is None:
        return
    report.raw["sparkplug"] = raw
    latency = raw["latency_ms"]
    p99 = percentile(latency, 0.99)
    report.add(
        f"sparkplug: births, {cells} edge nodes (NBIRTH + 2 DBIRTH each, before data)",
        f"{raw['births_in_order']} of {cells}",
        f"{raw['nbirths']} NBIRTH, {raw['dbirths']} DBIRTH",
        None,
        "every node",
        None,
    )
    report.add(
        f"sparkplug: value change -> host, {cells} cells, p50 / p99",
        f"{percentile(latency, 0.5) or 0:.1f} / {p99 or 0:.1f} ms",
        "on change",
        None if p99 is None else p99 / TARGET_MS,
        f"p99 <= {TARGET_MS:.0f} ms (<= 1.0x)",
        lambda x: x <= 1.0,
    )
    lost = raw["values_missing"] + raw["seq_gaps"] + raw["births_missing"]
    report.add(
        "sparkplug: lost (values missing + seq gaps + births missing)",
        f"{lost}",
        f"{raw['values_set']} values set",
        lost / raw["values_set"] if raw["values_set"] else None,
        "none lost (0x)",
        lambda x: x == 0,
    )
    report.add(
        "sparkplug: messages to the host; per cell CPU; mosquitto CPU",
        f"{raw['messages_per_second']:.0f}/s; {raw['cpu_per_cell'] * 100:.1f} %; {raw['broker_cpu'] * 100:.1f} %",
        "of one core",
        None,
        "",
        None,
    )


async def _measure(
    broker: Mosquitto, peers: Peers, url: str, cells: int, started: list[Peer], seconds: float
) -> dict[str, Any]:
    import logging
    import threading

    import paho.mqtt.client as mqtt
    from paho.mqtt.enums import CallbackAPIVersion

    from uacell.sparkplug.payload import DataType, decode, get_value

    logging.getLogger("asyncua").setLevel(logging.ERROR)
    received: list[tuple[float, str, bytes]] = []
    ready = threading.Event()

    # The host application runs in paho's own network thread: arrival times are not held up by the
    # bench's event loop (its 20 OPC UA clients).
    def connected(client: mqtt.Client, *_: Any) -> None:
        client.subscribe("spBv1.0/bench/#", qos=0)
        ready.set()

    host = mqtt.Client(CallbackAPIVersion.VERSION2)
    host.on_connect = connected
    host.on_message = lambda _c, _u, m: received.append((time.time(), m.topic, bytes(m.payload)))
    host.connect("127.0.0.1", broker.port)
    host.loop_start()
    if not await asyncio.to_thread(ready.wait, 15):
        raise RuntimeError("the host application did not connect")
    for i in range(cells):
        started.append(await asyncio.to_thread(peers.uacell(sparkplug=url, publisher=f"cell{i + 1:03d}").start))
    first = len(received)
    run = await drive_speeds(started, broker, seconds, 0.5)
    values = {f"cell{i + 1:03d}": v for i, v in run.values.items()}
    wall, cpu = run.wall, run.cpu
    host.disconnect()
    host.loop_stop()
    # the host's view: per node the seq chain, per device the aliases from its DBIRTH
    seq: dict[str, int] = {}
    gaps = 0
    aliases: dict[str, dict[int, str]] = {}
    births: dict[str, list[str]] = defaultdict(list)  # node -> message kinds up to its first DDATA
    seen: dict[str, set[float]] = defaultdict(set)
    latency: list[float] = []
    for arrived, topic, data in received:
        _, _, kind, edge, *device = topic.split("/")
        payload = decode(data)
        if kind in ("NBIRTH", "DBIRTH", "DDATA", "DDEATH"):
            expected = 0 if kind == "NBIRTH" else (seq.get(edge, -1) + 1) % 256
            gaps += payload.seq != expected
            seq[edge] = payload.seq
        if kind in ("NBIRTH", "DBIRTH") or (kind == "DDATA" and "DDATA" not in births[edge]):
            births[edge].append(kind)
        if kind == "DBIRTH":
            aliases[topic] = {m.alias: m.name for m in payload.metrics}
        if kind != "DDATA" or device != ["Filler1"]:
            continue
        names = aliases.get(topic.replace("/DDATA/", "/DBIRTH/"), {})
        for m in payload.metrics:
            if names.get(m.alias) == "Status/MachSpeed":
                v = get_value(m, DataType.Float)
                if v in values[edge] and v not in seen[edge]:
                    seen[edge].add(v)
                    latency.append(arrived * 1000 - m.timestamp)
    in_order = sum(1 for kinds in births.values() if kinds[:3] == ["NBIRTH", "DBIRTH", "DBIRTH"])
    set_count = sum(len(v) for v in values.values())
    window = len(received) - first
    return {
        "cells": cells,
        "seconds": wall,
        "messages_per_second": window / wall,
        "latency_ms": latency,
        "nbirths": sum(k.count("NBIRTH") for k in births.values()),
        "dbirths": sum(k.count("DBIRTH") for k in births.values()),
        "births_in_order": in_order,
        "births_missing": cells - in_order,
        "values_set": set_count,
        "values_missing": sum(len(set(values[e]) - seen[e]) for e in values),
        "seq_gaps": gaps,
        "cpu_per_cell": sum(cpu) / len(cpu) if cpu else 0.0,
        "rss_mib_per_cell": sum(run.rss) / len(run.rss) if run.rss else 0.0,
        "broker_cpu": run.broker_cpu,
    }
