"""What every section of the benchmark suite uses: the peers it starts (``Peer``, ``Peers``), the
node-opcua bench client (``client``), the report (``Report``), helper processes (``process``,
``served``) and small figures (``median``, ``percentile``). The sections import this module and
``__main__`` imports the sections: no section imports ``__main__``.
"""

from __future__ import annotations

import asyncio
import contextlib
import json
import logging
import os
import socket
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
INTEROP = ROOT / "interop"
CLIENT = INTEROP / "bench_client.js"
log = logging.getLogger("benchmarks")
TICKS = os.sysconf("SC_CLK_TCK")

FILLER = "/PackML:PackMLObjects/Cell:Filler1"
TASK_CONTROL = (
    "/DI:DeviceSet/Cell:Robot1/Robotics:Controllers/Cell:Controller1/Robotics:TaskControls"
    "/Cell:TaskControl1/Robotics:TaskControlOperation/Robotics:TaskControlStateMachine"
)
SPEED = {"type": "Float", "value": 120.0}
SET_SPEED = [{"object": FILLER, "method": "/PackML:SetMachSpeed", "args": [SPEED]}]
ECHO = [{"object": "/Bench:Bench", "method": "/Bench:Echo", "args": [SPEED]}]
LOAD_CYCLE = [
    {"object": TASK_CONTROL, "method": "/Robotics:LoadByName", "args": [{"type": "String", "value": "pick_and_place"}]},
    {"object": TASK_CONTROL, "method": "/Robotics:UnloadProgram", "args": []},
]
READ_STATE = [{"read": FILLER + "/PackML:BaseStateMachine/CurrentState"}]
STATE = FILLER + "/PackML:BaseStateMachine/PackML:MachineState/CurrentState"
TC_STATE = TASK_CONTROL + "/CurrentState"


# --- processes -----------------------------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def cpu_seconds(pid: int) -> float:
    """The CPU time (user and system, all threads) process ``pid`` has used so far; 0.0 once it is gone."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / TICKS  # utime + stime
    except (OSError, IndexError, ValueError):
        return 0.0


def rss_kib(pid: int) -> int:
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1])
    except OSError:
        pass
    return 0


@dataclass
class Peer:
    """A server process that prints ``listening`` once clients can connect."""

    name: str
    cmd: list[str]
    cwd: Path = ROOT
    port: int = 0
    proc: subprocess.Popen[str] | None = None
    startup: float = 0.0  # seconds from spawn to the listening line

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://127.0.0.1:{self.port}/"

    def start(self, timeout: float = 300.0) -> Peer:
        t0 = time.perf_counter()
        self.proc = subprocess.Popen(
            self.cmd, cwd=self.cwd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True
        )
        timer = threading.Timer(timeout, self.proc.kill)
        timer.start()
        try:
            assert self.proc.stdout is not None
            for line in self.proc.stdout:
                if line.strip().endswith("listening"):
                    break
            else:
                raise RuntimeError(f"{self.name} did not start (exit {self.proc.poll()})")
        finally:
            timer.cancel()
        self.startup = time.perf_counter() - t0
        return self

    def rss_kib(self) -> int:
        return rss_kib(self.proc.pid) if self.proc else 0

    def stop(self) -> None:
        # Graceful shutdown is not measured: SIGTERM, then SIGKILL after a short grace.
        if self.proc is None:
            return
        self.proc.terminate()
        try:
            self.proc.wait(10)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            self.proc.wait(10)
        self.proc = None


class Peers:
    """Builds the peers' commands: uacell peers restart with their cell's data directory, or start afresh."""

    def __init__(self, tmp: Path) -> None:
        self.tmp = tmp
        self.count = 0
        self.prepared: set[str] = set()  # cells whose snapshot is in the shared cache directory
        from uacell.catalog import companions
        from uacell.core.companion import models_of
        from uacell.models.source import locate_models, official_models

        models = official_models(models_of(companions()))
        paths = locate_models(models)
        self.nodeset_files = [str(paths[m.key]) for m in models]

    def uacell(
        self,
        cell: str = "demo",
        snapshot: bool = True,
        history: bool = True,
        pubsub: str = "",
        publisher: str = "",
        sparkplug: str = "",
        history_events: int = 0,
    ) -> Peer:
        """A uacell peer; ``snapshot``: a restart, with the cell's data directory and the shared cache
        directory of address-space snapshots (the first peer of each cell writes its snapshot,
        untimed, here); else a first start, with empty directories of its own."""
        if snapshot and cell not in self.prepared:
            self.prepared.add(cell)
            self._prepare_snapshot(cell)
        self.count += 1
        port = free_port()
        # A restart keeps its data directory (its certificate: no new key to generate); a first
        # start has an empty one. Peers of one cell never run at the same time.
        data = self.tmp / (f"uacell-{cell}" if snapshot else f"uacell-{cell}-{self.count}")
        if not history:  # it runs beside a peer of the same cell with history on
            data = data.with_name(data.name + "-no-history")
        if publisher:  # one of many cells publishing side by side
            data = data.with_name(f"{data.name}-{publisher}")
        if history_events:  # its stored events are its own (the other peers' history stays as it was)
            data = data.with_name(f"{data.name}-{history_events}-events")
        cache = self.cache if snapshot else data / "cache"
        cmd = [sys.executable, "-m", "benchmarks.peers", "uacell", "--port", str(port), "--cell", cell]
        cmd += [] if history else ["--no-history"]
        cmd += ["--pubsub", pubsub] if pubsub else []
        cmd += ["--sparkplug", sparkplug] if sparkplug else []
        cmd += ["--publisher-id", publisher] if publisher else []
        cmd += ["--history-events", str(history_events)] if history_events else []
        name = f"uacell {cell} cell" + ("" if history else " (history off)") + (f" {publisher}" if publisher else "")
        return Peer(name, [*cmd, "--data-dir", str(data), "--cache-dir", str(cache)], port=port)

    @property
    def cache(self) -> Path:
        return self.tmp / "cache"

    def _prepare_snapshot(self, cell: str) -> None:
        """Run a peer of ``cell`` until it has written its snapshot into the shared cache directory."""
        before = set(self.cache.glob("address-space-*.snapshot"))
        with running(self.uacell(cell)):
            deadline = time.monotonic() + 600
            while time.monotonic() < deadline:
                if set(self.cache.glob("address-space-*.snapshot")) - before:
                    return
                time.sleep(0.2)
        raise RuntimeError(f"the uacell peer ({cell} cell) wrote no address-space snapshot")

    def asyncua(self, nodesets: bool = False) -> Peer:
        port = free_port()
        cmd = [sys.executable, "-m", "benchmarks.peers", "asyncua", "--port", str(port)]
        name = "asyncua echo" + (" + NodeSets" if nodesets else "")
        return Peer(name, cmd + (["--nodesets"] if nodesets else []), port=port)

    def node(self, nodesets: bool = False) -> Peer:
        port = free_port()
        cmd = ["node", str(INTEROP / "bench_server.js"), str(port), *(self.nodeset_files if nodesets else [])]
        return Peer("node-opcua echo" + (" + NodeSets" if nodesets else ""), cmd, cwd=INTEROP, port=port)


@contextlib.contextmanager
def running(*peers: Peer) -> Iterator[tuple[Peer, ...]]:
    try:
        for p in peers:
            p.start()
        yield peers
    finally:
        for p in peers:
            p.stop()


def client(endpoint: str, spec: dict[str, Any], timeout: float = 300.0) -> dict[str, Any]:
    proc = subprocess.run(
        ["node", str(CLIENT), endpoint, json.dumps(spec)],
        cwd=INTEROP,
        capture_output=True,
        text=True,
        timeout=timeout,
        check=False,
    )
    lines = [ln for ln in proc.stdout.splitlines() if ln.strip()]
    if proc.returncode != 0 or not lines:
        tail = proc.stderr.strip().splitlines()[-3:]
        raise RuntimeError(f"bench client {spec['mode']} failed: {' / '.join(tail)}")
    result: dict[str, Any] = json.loads(lines[-1])
    return result


def loaded(peer: Peer, spec: dict[str, Any]) -> dict[str, Any]:
    """``client`` against ``peer``, with the peer's CPU time per call (the whole process, every thread)
    as ``cpu_us_per_call``: much steadier from round to round than the rate on a shared machine."""
    assert peer.proc is not None
    before = cpu_seconds(peer.proc.pid)
    result = client(peer.endpoint, spec)
    result["cpu_us_per_call"] = 1e6 * (cpu_seconds(peer.proc.pid) - before) / max(1, result["calls"])
    return result


def rotated(items: list[Any], round_no: int) -> list[Any]:
    k = round_no % len(items)
    return items[k:] + items[:k]


def median(values: list[float]) -> float | None:
    values = [v for v in values if v is not None]
    return statistics.median(values) if values else None


# --- the report ------------------------------------------------------------------------------------
@dataclass
class Row:
    measure: str
    value: str
    reference: str
    ratio: float | None
    target: str = ""
    passed: bool | None = None


@dataclass
class Report:
    rows: list[Row] = field(default_factory=list)
    raw: dict[str, Any] = field(default_factory=dict)

    def add(
        self,
        measure: str,
        value: str,
        reference: str,
        ratio: float | None,
        target: str = "",
        ok: Callable[[float], object] | None = None,
    ) -> None:
        passed = None if ok is None or ratio is None else bool(ok(ratio))
        self.rows.append(Row(measure, value, reference, ratio, target, passed))
        verdict = {True: "PASS", False: "FAIL", None: ""}[passed]
        print(f"  {measure}: {value} vs {reference} -> {fmt(ratio)} {target} {verdict}", flush=True)

    def add_rates(
        self, measure: str, ours: list[dict[str, Any]], theirs: list[dict[str, Any]], reference: str, floor: float
    ) -> None:
        """A row of calls/s: the median rates of ``ours`` and of ``theirs`` (load runs of the same
        rounds), the median of the per-round ratios, and the target ``>= floor``."""
        self.add(
            measure,
            f"{median([x['rate'] for x in ours]):.0f}/s",
            f"{reference} {median([x['rate'] for x in theirs]):.0f}/s",
            median([a["rate"] / b["rate"] for a, b in zip(ours, theirs, strict=True)]),
            f">= {floor}x",
            lambda x: x >= floor,
        )

    def add_cpu(self, measure: str, ours: list[dict[str, Any]], theirs: list[dict[str, Any]], reference: str) -> None:
        """A row of CPU per call (``loaded`` runs), no target: the median of each and of the per-round
        ratios ours/theirs (below 1: ours costs less)."""
        self.add(
            measure,
            f"{median([x['cpu_us_per_call'] for x in ours]):.0f} us",
            f"{reference} {median([x['cpu_us_per_call'] for x in theirs]):.0f} us",
            median([a["cpu_us_per_call"] / b["cpu_us_per_call"] for a, b in zip(ours, theirs, strict=True)]),
        )

    def print(self) -> None:
        head = ("measure", "uacell", "reference", "ratio", "target", "")
        table = [head] + [
            (r.measure, r.value, r.reference, fmt(r.ratio), r.target, {True: "PASS", False: "FAIL", None: ""}[r.passed])
            for r in self.rows
        ]
        widths = [max(len(str(row[i])) for row in table) for i in range(len(head))]
        print()
        for i, row in enumerate(table):
            print("  ".join(str(c).ljust(w) for c, w in zip(row, widths, strict=True)).rstrip())
            if i == 0:
                print("  ".join("-" * w for w in widths))
        targets = [r for r in self.rows if r.passed is not None]
        print(f"\n{sum(1 for r in targets if r.passed)}/{len(targets)} targets met", flush=True)


def fmt(x: float | None, unit: str = "x") -> str:
    return "n/a" if x is None else f"{x:.2f}{unit}"


# --- helper processes and waits ------------------------------------------------------------------
def percentile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


@contextlib.contextmanager
def process(cmd: list[str], cwd: Path, ready: str = "") -> Iterator[subprocess.Popen[str]]:
    """A helper process (a PLC, a controller), stopped on the way out; ``ready``: the line it prints
    once it serves."""
    proc = subprocess.Popen(
        cmd, cwd=cwd, stdout=subprocess.PIPE if ready else subprocess.DEVNULL, stderr=subprocess.DEVNULL, text=True
    )
    try:
        if ready:
            assert proc.stdout is not None
            for line in proc.stdout:
                if line.strip() == ready:
                    break
        yield proc
    finally:
        proc.terminate()
        with contextlib.suppress(subprocess.TimeoutExpired):
            proc.wait(10)
        if proc.poll() is None:
            proc.kill()


@contextlib.contextmanager
def served(peers: Peers, name: str, cell_text: str) -> Iterator[Peer]:
    """A uacell peer serving ``cell_text`` (a cell file's content), stopped on the way out."""
    cell = peers.tmp / f"{name}.toml"
    cell.write_text(cell_text)
    port = free_port()
    cmd = [sys.executable, "-m", "benchmarks.peers", "uacell", "--port", str(port), "--cell", str(cell)]
    cmd += ["--data-dir", str(peers.tmp / f"{name}-data"), "--cache-dir", str(peers.tmp / f"{name}-cache")]
    server = Peer(f"uacell {name} cell", cmd, port=port).start()
    try:
        # a first start writes its address-space snapshot beside the loop (a forked child): measure after it
        from uacell.ua.snapshot import PREFIX, SUFFIX

        deadline = time.monotonic() + 60
        while not any((peers.tmp / f"{name}-cache").glob(f"{PREFIX}*{SUFFIX}")) and time.monotonic() < deadline:
            time.sleep(0.05)
        yield server
    finally:
        server.stop()


async def text_of(client: Any, ns: int, machine: str) -> str:
    from asyncua import ua

    value = await client.get_node(ua.NodeId(f"{machine}.CurrentState", ns)).read_value()
    return str(value.Text)


async def until(read: Any, wanted: str, timeout: float = 10.0) -> None:
    limit = time.perf_counter() + timeout
    while await read() != wanted:
        if time.perf_counter() > limit:
            raise TimeoutError(f"waited for {wanted}")
        await asyncio.sleep(0.005)
