"""`make soak`: many sessions with subscriptions on a cycling cell for a long time.

Starts `uacell serve` (a separate process, so that its memory is its own), drives the cell (Filler1
producing, the robot running pick_and_place continuously), connects ``--sessions`` clients that each
subscribe to Filler1's ProdProcessedCount and the robot's program pointer, and after ``--minutes``
reports the server's RSS growth and the notifications lost (gaps in the sequence numbers of the
notification messages each session received). Exits 1 if a notification was lost, 0 otherwise. Not
part of `make test`.

    python tools/soak.py [--sessions 200] [--minutes 10]
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import itertools
import logging
import os
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from asyncua import Client, ua

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # the repository: its benchmarks package
from benchmarks.soak import start_filler, start_robot  # the cell driving, shared with `make bench`

CELL = "urn:uacell:cell"
F = "Filler1"
TASK = "Robot1.Controllers.Controller1.TaskControls.TaskControl1"


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


class Counts:
    """What one session saw: ProdProcessedCount[0].Count values and the sequence numbers of the
    notification messages that carried data (a gap is a message the server never delivered)."""

    def __init__(self) -> None:
        self.seen: list[int] = []
        self.sequence: list[int] = []
        self.notifications = 0
        self.status_changes = 0

    def datachange_notification(self, node: object, value: object, data: object) -> None:
        self.notifications += 1
        if isinstance(value, list) and value and hasattr(value[0], "Count"):
            self.seen.append(int(value[0].Count))

    def status_change_notification(self, status: object) -> None:
        self.status_changes += 1

    def lost(self) -> int:
        numbers = sorted(set(self.sequence))
        return sum(b - a - 1 for a, b in itertools.pairwise(numbers) if b > a + 1)


async def drive(endpoint: str) -> Client:
    """Set the cell cycling; the returned client stays connected."""
    client = Client(endpoint, timeout=60)
    await client.connect()
    await client.load_data_type_definitions()  # registers the PackML structures for every client here
    ns = await client.get_namespace_index(CELL)
    await start_filler(client, ns, F, 120.0)  # 2 packages/s
    await start_robot(client, ns, "Robot1")
    return client


async def session(endpoint: str, ns: int, counts: Counts) -> Client:
    # 200 clients share this process's one event loop: a lenient keep-alive probe keeps a busy moment
    # here from passing for a lost server.
    client = Client(endpoint, timeout=60, watchdog_intervall=30.0)
    await client.connect()
    sub = await client.create_subscription(500, counts)
    callbacks = client.uaclient._subscription_callbacks
    deliver = callbacks[sub.subscription_id]

    def record(result: ua.PublishResult) -> object:
        if result.NotificationMessage.NotificationData:
            counts.sequence.append(result.NotificationMessage.SequenceNumber)
        return deliver(result)

    callbacks[sub.subscription_id] = record
    nodes = [client.get_node(ua.NodeId(f"{F}.Admin.ProdProcessedCount", ns))]
    nodes.append(client.get_node(ua.NodeId(f"{TASK}.ParameterSet.ProgramPointer", ns)))
    await sub.subscribe_data_change(nodes, queuesize=100)
    return client


async def soak(endpoint: str, pid: int, sessions: int, minutes: float) -> int:
    driver = await drive(endpoint)
    ns = await driver.get_namespace_index(CELL)
    counts = [Counts() for _ in range(sessions)]
    clients: list[Client] = []
    for i in range(0, sessions, 20):  # connect in groups: 200 handshakes at once only measure the handshake
        clients += await asyncio.gather(*(session(endpoint, ns, c) for c in counts[i : i + 20]))
    await asyncio.sleep(5)
    start_rss, start = rss_mb(pid), time.monotonic()
    print(f"{sessions} sessions subscribed; RSS {start_rss:.1f} MB; soaking for {minutes:g} min", flush=True)
    samples = [(0.0, start_rss)]
    while (elapsed := time.monotonic() - start) < minutes * 60:
        await asyncio.sleep(min(30.0, minutes * 60 - elapsed))
        samples.append((time.monotonic() - start, rss_mb(pid)))
        print(f"  {samples[-1][0] / 60:5.1f} min: RSS {samples[-1][1]:.1f} MB", flush=True)
    await asyncio.sleep(2)  # the last notifications arrive
    for client in [driver, *clients]:
        with contextlib.suppress(Exception):
            await client.disconnect()
    end_rss = samples[-1][1]
    lost = sum(c.lost() for c in counts)
    silent = sum(1 for c in counts if len(set(c.seen)) < 2)
    produced = max((max(c.seen) - min(c.seen) for c in counts if c.seen), default=0)
    messages = sum(len(set(c.sequence)) for c in counts)
    slope = (end_rss - start_rss) / max(samples[-1][0] / 60, 1e-9)
    print(f"RSS: {start_rss:.1f} MB -> {end_rss:.1f} MB ({end_rss - start_rss:+.1f} MB, {slope:+.2f} MB/min)")
    print(f"notifications: {sum(c.notifications for c in counts)} in {messages} messages; packages: {produced}")
    print(f"lost notification messages (sequence gaps): {lost}; sessions that saw no change: {silent}")
    print(f"subscription status changes (e.g. timeouts): {sum(c.status_changes for c in counts)}")
    return 1 if lost or silent else 0


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sessions", type=int, default=200)
    parser.add_argument("--minutes", type=float, default=10.0)
    args = parser.parse_args()
    logging.basicConfig(level=logging.ERROR)  # 200 clients' notes on their session timeout are noise
    with tempfile.TemporaryDirectory(prefix="uacell-soak-") as tmp:
        port = free_port()
        config = Path(tmp) / "uacell.toml"
        config.write_text(
            f"[robot]\ntime_scale = 5.0\n[packml]\nacting_time = 0.2\n[limits]\nsessions = {args.sessions + 10}\n"
            f"connections = {args.sessions + 20}\n"
        )
        cmd = [
            sys.executable,
            "-m",
            "uacell",
            "--log-level",
            os.environ.get("SOAK_LOG", "WARNING"),
            "serve",
            "--config",
            str(config),
        ]
        cmd += ["--port", str(port), "--data-dir", str(Path(tmp) / "data"), "--no-web"]
        server = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        try:
            assert server.stdout is not None
            for line in server.stdout:
                print(f"server: {line.rstrip()}", flush=True)
                if line.startswith("uacell listening on "):
                    break
            else:
                return 2
            return asyncio.run(soak(f"opc.tcp://127.0.0.1:{port}/", server.pid, args.sessions, args.minutes))
        finally:
            server.terminate()
            try:
                server.wait(10)
            except subprocess.TimeoutExpired:
                server.kill()
            if server.stdout is not None:
                rest = server.stdout.read()
                if rest.strip():
                    print("server: " + rest.rstrip().replace(os.linesep, os.linesep + "server: "))


if __name__ == "__main__":
    sys.exit(main())
