"""The soak (``make bench ARGS="--only soak"``; ``--minutes``, 20 by default): a cell of 4 fillers and
4 robots under mixed load for a long time, and whether the server stays flat.

It starts ``uacell serve`` (its own process, log file at INFO, the HMI on, PubSub to a mosquitto it
starts, history on) and, from this process: the fillers produce and are stopped, reset and restarted
in turn, each robot runs pick_and_place continuously; 8 sessions hold subscriptions; a session comes
and goes every 2 s (session churn); one client reads CurrentTime every 0.2 s and calls SetMachSpeed
every second (the latencies); every 10 s a HistoryRead of the Server's events and of a value; an HMI
page (an HTTP client doing what the page does: its session, the event stream held open, the history
every 15 s); an MQTT subscriber counts what PubSub delivers.

The run is cut into 10 windows. Per window it reports the server's RSS, open fds, threads, CPU and the
latencies (p50/p99), then the slopes, with targets (PASS/FAIL): RSS growth < 10 MB over the second
half; fds and threads flat over the second half; the last window's p99 within 1.5x the first's (Read
and call); no ERROR line and no traceback in the server's log. ``tools/soak.py`` (``make soak``)
shares the cell driving (``call``, ``robot_method``, ``start_filler``, ``start_robot``).
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import http.cookiejar
import json
import logging
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
from collections.abc import Awaitable, Callable, Iterator
from dataclasses import dataclass, field
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from asyncua import Client, ua

from benchmarks.harness import cpu_seconds

CELL = "urn:uacell:cell"
FILLERS, ROBOTS = 4, 4
SESSIONS = 8
WINDOWS = 10
# targets
RSS_GROWTH_MB = 10.0  # over the second half
FLAT = {"fds": 4, "threads": 2}  # the most the second half may add (a churning session may be open)
P99_GROWTH = 1.5  # the last window's p99 over the first's


# --- driving the cell (shared with tools/soak.py) -------------------------------------------------
async def call(client: Client, ns: int, obj: str, method: str, *args: ua.Variant) -> ua.CallMethodResult:
    """Call ``obj``'s ``method`` (NodeIds as the cell names them); a RuntimeError if it is not Good."""
    req = ua.CallMethodRequest(ObjectId=ua.NodeId(obj, ns), MethodId=ua.NodeId(f"{obj}.{method}", ns))
    req.InputArguments = list(args)
    (res,) = await client.uaclient.call([req])
    if not res.StatusCode.is_good():
        raise RuntimeError(f"{obj}.{method}: {res.StatusCode}")
    return res


async def robot_method(client: Client, ns: int, obj: str, method: str, *args: ua.Variant) -> None:
    """A Robotics method, which answers its outcome in the Int32 Status output."""
    status = (await call(client, ns, obj, method, *args)).OutputArguments[0].Value
    if status != 0:
        raise RuntimeError(f"{method}: Status {status}")


def machine(filler: str) -> str:
    return f"{filler}.BaseStateMachine.MachineState"


async def start_filler(client: Client, ns: int, filler: str, speed: float = 120.0) -> None:
    """Reset, set the speed (packages a minute), Start: the filler produces."""
    await call(client, ns, machine(filler), "Reset")
    state = client.get_node(ua.NodeId(f"{machine(filler)}.ExecuteState.CurrentState", ns))
    for _ in range(200):
        if (await state.read_value()).Text == "Idle":
            break
        await asyncio.sleep(0.05)
    await call(client, ns, filler, "SetMachSpeed", ua.Variant(speed, ua.VariantType.Float))
    no_parameters = ua.Variant([], ua.VariantType.ExtensionObject, is_array=True)
    await call(client, ns, f"{machine(filler)}.ExecuteState", "Start", no_parameters)


async def start_robot(client: Client, ns: int, robot: str) -> None:
    """GetReady, then pick_and_place continuously on TaskControl1."""
    ctrl = f"{robot}.Controllers.Controller1"
    so = f"{ctrl}.SystemOperation.SystemOperationStateMachine"
    task = f"{ctrl}.TaskControls.TaskControl1"
    tc = f"{task}.TaskControlOperation.TaskControlStateMachine"
    await robot_method(client, ns, so, "GetReady")
    for _ in range(200):
        if (await client.get_node(ua.NodeId(f"{so}.CurrentState", ns)).read_value()).Text == "Ready":
            break
        await asyncio.sleep(0.1)
    mode = client.get_node(ua.NodeId(f"{task}.ParameterSet.ExecutionMode", ns))
    await mode.write_value(ua.Variant(1, ua.VariantType.Int32))  # CONTINUOUS
    for program in ("gripper", "pick_and_place"):
        await robot_method(client, ns, tc, "LoadByName", ua.Variant(program, ua.VariantType.String))
    await robot_method(client, ns, tc, "Start")


# --- the server and its counterparts ---------------------------------------------------------------
def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def cell_file(fillers: int, robots: int) -> str:
    lines = []
    for i in range(1, robots + 1):
        lines += [
            "[[robots]]", f'name = "Robot{i}"',
            "  [[robots.controllers]]", '  name = "Controller1"',
            "    [[robots.controllers.task_controls]]", '    name = "TaskControl1"',
            "  [[robots.motion_devices]]", '  name = "Arm1"', "  axes = 6",
        ]  # fmt: skip
    for i in range(1, fillers + 1):
        lines += ["[[packml_units]]", f'name = "Filler{i}"']
    return "\n".join(lines) + "\n"


@dataclass
class Server:
    """``uacell serve`` of the soak cell: its log file, endpoint and HMI URL."""

    tmp: Path
    broker: str
    port: int = field(default_factory=free_port)
    web_port: int = field(default_factory=free_port)
    proc: subprocess.Popen[str] | None = None
    url: str = ""

    @property
    def log(self) -> Path:
        return self.tmp / "server.log"

    @property
    def endpoint(self) -> str:
        return f"opc.tcp://127.0.0.1:{self.port}/"

    def start(self) -> None:
        config = self.tmp / "uacell.toml"
        config.write_text(
            "[robot]\ntime_scale = 5.0\n[packml]\nacting_time = 0.2\n"
            f'[pubsub]\nenabled = true\nbroker = "{self.broker}"\n' + cell_file(FILLERS, ROBOTS)
        )
        cmd = [sys.executable, "-m", "uacell", "--config", str(config), "--log-file", str(self.log)]
        cmd += ["--log-level", "INFO", "serve", "--port", str(self.port), "--web-port", str(self.web_port)]
        cmd += ["--data-dir", str(self.tmp / "data")]
        self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
        timer = threading.Timer(300.0, self.proc.kill)
        timer.start()
        try:
            assert self.proc.stdout is not None
            for line in self.proc.stdout:
                if line.startswith("uacell web on "):
                    self.url = line.split(" on ", 1)[1].strip().rstrip("/")
                    break
        finally:
            timer.cancel()
        if not self.url:
            raise RuntimeError(f"uacell serve did not start (exit {self.proc.poll()}); see {self.log}")
        threading.Thread(target=self.proc.stdout.read, daemon=True).start()  # never blocks on a full pipe

    def stop(self) -> None:
        if self.proc is not None:
            self.proc.terminate()
            try:
                self.proc.wait(15)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait(10)

    def sample(self) -> dict[str, float]:
        """RSS (MB), open fds, threads and CPU seconds of the server process now."""
        assert self.proc is not None
        pid = self.proc.pid
        status = dict(
            line.split(":", 1) for line in Path(f"/proc/{pid}/status").read_text().splitlines() if ":" in line
        )
        return {
            "rss_mb": int(status["VmRSS"].split()[0]) / 1024,
            "threads": int(status["Threads"]),
            "fds": len(os.listdir(f"/proc/{pid}/fd")),
            "cpu_s": cpu_seconds(pid),
        }

    def errors(self) -> list[str]:
        """The log's ERROR and CRITICAL lines, and every traceback's first line."""
        text = self.log.read_text(errors="replace") if self.log.exists() else ""
        return [ln for ln in text.splitlines() if " ERROR " in ln or " CRITICAL " in ln or ln.startswith("Traceback")]


@contextlib.contextmanager
def mosquitto(tmp: Path) -> Iterator[str]:
    """Debian's mosquitto on a free loopback port, anonymous: its URL."""
    exe = shutil.which("mosquitto") or "/usr/sbin/mosquitto"
    port = free_port()
    conf = tmp / "mosquitto.conf"
    conf.write_text(f"listener {port} 127.0.0.1\nallow_anonymous true\npersistence false\nuser root\n")
    proc = subprocess.Popen([exe, "-c", str(conf)], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    try:
        deadline = time.monotonic() + 15
        while True:
            with contextlib.suppress(OSError), socket.create_connection(("127.0.0.1", port), 0.2):
                break
            if time.monotonic() > deadline:
                raise RuntimeError("mosquitto did not listen")
            time.sleep(0.05)
        yield f"mqtt://127.0.0.1:{port}"
    finally:
        proc.terminate()
        proc.wait(10)


# --- the load --------------------------------------------------------------------------------------
@dataclass
class Window:
    """What happened in one window: latencies (ms) per kind, counts, failures."""

    latencies: dict[str, list[float]] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    failures: dict[str, str] = field(default_factory=dict)

    def took(self, kind: str, ms: float) -> None:
        self.latencies.setdefault(kind, []).append(ms)

    def count(self, kind: str, n: int = 1) -> None:
        self.counts[kind] = self.counts.get(kind, 0) + n

    def failed(self, kind: str, exc: BaseException) -> None:
        self.count(f"{kind} failed")
        self.failures.setdefault(kind, f"{type(exc).__name__}: {exc}")


class Load:
    """The soak's clients, all in this process's event loop; ``window`` is where they record."""

    def __init__(self, server: Server, broker: str) -> None:
        self.server, self.broker = server, broker
        self.window = Window()
        self.stopping = asyncio.Event()
        self.ns = 0
        self.turn = 0  # the filler cycled last (1..FILLERS - 1 stand for Filler2..)
        self._hmi: urllib.request.OpenerDirector | None = None
        self._hmi_end: float | None = None  # the ``end`` of the HMI's last history answer

    async def timed(self, kind: str, work: Awaitable[Any]) -> Any:
        t0 = time.perf_counter()
        try:
            result = await work
        except Exception as exc:
            self.window.failed(kind, exc)
            return None
        self.window.took(kind, (time.perf_counter() - t0) * 1000)
        return result

    async def every(self, seconds: float, step: Callable[[], Awaitable[None]]) -> None:
        while not self.stopping.is_set():
            started = time.monotonic()
            await step()
            with contextlib.suppress(TimeoutError):
                await asyncio.wait_for(self.stopping.wait(), max(0.0, seconds - (time.monotonic() - started)))

    async def client(self) -> Client:
        client = Client(self.server.endpoint, timeout=60, watchdog_intervall=30.0)
        await client.connect()
        return client

    async def run(self, seconds: float, begin: Callable[[], None], sample: Callable[[], None]) -> None:
        """Set the cell going, ``begin()``, then everything at once for ``seconds``; ``sample()`` at
        each window's end."""
        driver = await self.client()
        await driver.load_data_type_definitions()
        self.ns = await driver.get_namespace_index(CELL)
        for i in range(1, FILLERS + 1):
            await start_filler(driver, self.ns, f"Filler{i}", 60.0 + 20 * i)
        for i in range(1, ROBOTS + 1):
            await start_robot(driver, self.ns, f"Robot{i}")
        holders = [await self._subscribed() for _ in range(SESSIONS)]
        probe = await self.client()
        await asyncio.to_thread(self._open_hmi)  # the page's browser session, before its requests
        begin()
        self.window = Window()  # the set-up is not the soak
        tasks = [
            asyncio.create_task(self.every(0.2, lambda: self._read(probe))),
            asyncio.create_task(self.every(1.0, lambda: self._set_speed(probe))),
            asyncio.create_task(self.every(12.0, lambda: self._cycle_filler(driver))),
            asyncio.create_task(self.every(2.0, self._churn)),
            asyncio.create_task(self.every(10.0, lambda: self._history(probe))),
            asyncio.create_task(self.every(15.0, self._hmi_history)),
            asyncio.create_task(self._mqtt()),
            asyncio.create_task(asyncio.to_thread(self._hmi_events)),
        ]
        try:
            for _ in range(WINDOWS):
                with contextlib.suppress(TimeoutError):
                    await asyncio.wait_for(self.stopping.wait(), seconds / WINDOWS)
                sample()
        finally:
            self.stopping.set()
            await asyncio.wait(tasks[:-1], timeout=60)  # the HMI stream thread ends with the server
            for client in [probe, driver, *holders]:
                with contextlib.suppress(Exception):
                    await client.disconnect()

    async def _subscribed(self) -> Client:
        window = self

        class Counter:
            def datachange_notification(self, node: Any, value: Any, data: Any) -> None:
                window.window.count("notifications")

            def event_notification(self, event: Any) -> None:
                window.window.count("events")

        client = await self.client()
        sub = await client.create_subscription(500, Counter())
        nodes = [
            client.get_node(ua.NodeId(f"Filler{i}.Admin.ProdProcessedCount", self.ns)) for i in range(1, FILLERS + 1)
        ]
        pointer = "Controllers.Controller1.TaskControls.TaskControl1.ParameterSet.ProgramPointer"
        nodes += [client.get_node(ua.NodeId(f"Robot{i}.{pointer}", self.ns)) for i in range(1, ROBOTS + 1)]
        await sub.subscribe_data_change(nodes, queuesize=10)
        await sub.subscribe_events(client.nodes.server)
        return client

    async def _read(self, client: Client) -> None:
        node = client.get_node(ua.ObjectIds.Server_ServerStatus_CurrentTime)
        await self.timed("Read", node.read_value())

    async def _set_speed(self, client: Client) -> None:
        speed = ua.Variant(90.0 + (time.monotonic() % 60), ua.VariantType.Float)
        await self.timed("call", call(client, self.ns, "Filler1", "SetMachSpeed", speed))

    async def _cycle_filler(self, client: Client) -> None:
        """One filler in turn (2..4: Filler1 keeps producing for the call probe) is stopped and started again."""
        self.turn = self.turn % (FILLERS - 1) + 1
        filler = f"Filler{self.turn + 1}"

        async def cycle() -> None:
            await call(client, self.ns, machine(filler), "Stop")
            await asyncio.sleep(1.0)
            await start_filler(client, self.ns, filler, 100.0)

        await self.timed("filler cycle", cycle())

    async def _churn(self) -> None:
        async def come_and_go() -> None:
            client = await self.client()
            try:
                sub = await client.create_subscription(200, None)
                await sub.subscribe_data_change([client.get_node(ua.ObjectIds.Server_ServerStatus_CurrentTime)])
                await client.get_node(ua.NodeId("Filler1.Status.MachSpeed", self.ns)).read_value()
            finally:
                await client.disconnect()

        await self.timed("session churn", come_and_go())

    async def _history(self, client: Client) -> None:
        end = datetime.now(UTC)
        server = client.nodes.server
        await self.timed("HistoryRead events", server.read_event_history(end - timedelta(minutes=5), end, 1000))
        node = client.get_node(ua.NodeId("Filler1.Status.MachSpeed", self.ns))
        await self.timed("HistoryRead values", node.read_raw_history(end - timedelta(minutes=5), end, 1000))

    # the HMI page: a browser session, its event stream held open, the history every 15 s
    def _open_hmi(self) -> None:
        self._hmi = urllib.request.build_opener(urllib.request.HTTPCookieProcessor(http.cookiejar.CookieJar()))
        with self._hmi.open(self.server.url + "/api/session", timeout=60) as res:
            token = json.loads(res.read())["csrf"]
        # the session's token beside its cookie on every request, as the page sends it (docs/web.md)
        self._hmi.addheaders = [*self._hmi.addheaders, ("X-CSRF-Token", token)]

    @property
    def hmi(self) -> urllib.request.OpenerDirector:
        assert self._hmi is not None, "the HMI session is opened before the load starts"
        return self._hmi

    def _hmi_events(self) -> None:
        try:
            with self.hmi.open(self.server.url + "/api/events", timeout=120) as stream:
                for line in stream:
                    if line.startswith(b"data: "):
                        self.window.count("HMI events")
                    if self.stopping.is_set():
                        return
        except Exception as exc:
            if not self.stopping.is_set():
                self.window.failed("HMI events", exc)

    async def _hmi_history(self) -> None:
        def fetch() -> int:
            # as the page polls: the whole view once, then only what is new since the last answer's end
            since = "" if self._hmi_end is None else f"&since={self._hmi_end}"
            with self.hmi.open(self.server.url + "/api/history?hours=8" + since, timeout=120) as res:
                body = res.read()
            self._hmi_end = json.loads(body).get("end", self._hmi_end)
            return len(body)

        size = await self.timed("HMI history", asyncio.to_thread(fetch))
        if size:
            self.window.count("HMI history bytes", size)

    async def _mqtt(self) -> None:
        import aiomqtt

        host, port = self.broker.removeprefix("mqtt://").split(":")
        try:
            async with aiomqtt.Client(host, int(port), identifier="uacell-soak") as mqtt:
                await mqtt.subscribe("#")
                async for _ in mqtt.messages:
                    self.window.count("PubSub messages")
                    if self.stopping.is_set():
                        return
        except Exception as exc:
            if not self.stopping.is_set():
                self.window.failed("PubSub", exc)


# --- the report ------------------------------------------------------------------------------------
def percentile(values: list[float], q: float) -> float | None:
    if not values:
        return None
    ordered = sorted(values)
    return ordered[min(len(ordered) - 1, int(q * len(ordered)))]


def slope(points: list[tuple[float, float]]) -> float:
    """The least-squares slope of (x, y) points (0 for fewer than two)."""
    if len(points) < 2:
        return 0.0
    mx = sum(x for x, _ in points) / len(points)
    my = sum(y for _, y in points) / len(points)
    den = sum((x - mx) ** 2 for x, _ in points)
    return sum((x - mx) * (y - my) for x, y in points) / den if den else 0.0


def soak(minutes: float, tmp: Path) -> dict[str, Any]:
    """Run the soak; every figure per window, and the server's ERROR lines."""
    windows: list[dict[str, Any]] = []
    logging.getLogger("asyncua").setLevel(logging.ERROR)  # its clients' notes (revised timeouts) are noise here
    with mosquitto(tmp) as broker:
        server = Server(tmp, broker)
        try:
            server.start()
            load = Load(server, broker)
            t0, last = time.monotonic(), server.sample()

            def begin() -> None:
                nonlocal t0, last
                t0, last = time.monotonic(), server.sample()

            def sample() -> None:
                nonlocal last
                now, w = server.sample(), load.window
                load.window = Window()
                elapsed = time.monotonic() - t0
                span = elapsed - (windows[-1]["minute"] * 60 if windows else 0.0)
                row: dict[str, Any] = {
                    "minute": elapsed / 60,
                    "rss_mb": now["rss_mb"],
                    "fds": now["fds"],
                    "threads": now["threads"],
                    "cpu_pct": 100 * (now["cpu_s"] - last["cpu_s"]) / span if span else 0.0,
                    "counts": w.counts,
                    "failures": w.failures,
                }
                for kind, values in w.latencies.items():
                    row[kind] = {
                        "n": len(values),
                        "p50_ms": percentile(values, 0.5),
                        "p99_ms": percentile(values, 0.99),
                    }
                last = now
                windows.append(row)
                print(f"  {line(row)}", flush=True)

            asyncio.run(load.run(minutes * 60, begin, sample))
        finally:
            server.stop()
        errors = server.errors()
    return {"minutes": minutes, "windows": windows, "errors": errors}


def line(row: dict[str, Any]) -> str:
    def p(kind: str) -> str:
        x = row.get(kind)
        return f"{x['p50_ms']:.0f}/{x['p99_ms']:.0f}" if x else "-"

    counts = row["counts"]
    failed = sum(v for k, v in counts.items() if k.endswith("failed"))
    return (
        f"{row['minute']:5.1f} min  RSS {row['rss_mb']:6.1f} MB  fds {row['fds']:3d}  threads {row['threads']:2d}  "
        f"CPU {row['cpu_pct']:3.0f} %  Read {p('Read')}  call {p('call')}  HistoryRead {p('HistoryRead events')}  "
        f"HMI history {p('HMI history')} ms (p50/p99)  PubSub {counts.get('PubSub messages', 0)}  failed {failed}"
    )


def verdicts(result: dict[str, Any]) -> list[tuple[str, str, str, float | None, str, bool]]:
    """(measure, value, reference, ratio, target, passed) of each target."""
    rows = result["windows"]
    half = rows[len(rows) // 2 - 1 :] if len(rows) >= 2 else rows
    out = []
    growth = half[-1]["rss_mb"] - half[0]["rss_mb"]
    per_min = slope([(r["minute"], r["rss_mb"]) for r in half])
    out.append(
        (
            "soak: RSS growth over the second half",
            f"{growth:+.1f} MB ({per_min:+.2f} MB/min; {rows[0]['rss_mb']:.0f} -> {rows[-1]['rss_mb']:.0f} MB)",
            f"{RSS_GROWTH_MB:.0f} MB",
            growth / RSS_GROWTH_MB,
            "< 1x",
            growth < RSS_GROWTH_MB,
        )
    )
    minutes = half[-1]["minute"] - half[0]["minute"]
    for key, room in FLAT.items():
        fitted = slope([(r["minute"], r[key]) for r in half]) * minutes
        out.append(
            (
                f"soak: {key} over the second half",
                f"{half[0][key]} -> {half[-1][key]} (fit {fitted:+.1f})",
                f"+{room}",
                fitted / room,
                "<= 1x",
                fitted <= room,
            )
        )
    for kind in ("Read", "call"):
        first, last = rows[0].get(kind), rows[-1].get(kind)
        if first and last and first["p99_ms"]:
            ratio = last["p99_ms"] / first["p99_ms"]
            value = f"last window p99 {last['p99_ms']:.1f} ms"
            out.append(
                (
                    f"soak: {kind} p99, last window / first",
                    value,
                    f"first {first['p99_ms']:.1f} ms",
                    ratio,
                    f"<= {P99_GROWTH}x",
                    ratio <= P99_GROWTH,
                )
            )
    errors = len(result["errors"])
    out.append(("soak: ERROR lines in the server's log", str(errors), "0", float(errors), "0", errors == 0))
    # a load that did not run measures nothing: every request of it is answered (the HMI's got 401
    # for a while, unnoticed, when the web session came to need its token)
    failures: dict[str, str] = {}
    for r in rows:
        for kind, why in r.get("failures", {}).items():
            failures.setdefault(kind, why)
    failed = sum(v for r in rows for k, v in r["counts"].items() if k.endswith(" failed"))
    first = "; ".join(f"{kind}: {why}" for kind, why in failures.items())
    out.append(("soak: requests of the load that failed", str(failed), first or "0", float(failed), "0", failed == 0))
    return out


def soak_section(report: Any, peers: Any, args: argparse.Namespace) -> None:
    """The soak, as a section of ``python -m benchmarks`` (``report.add`` gets each target)."""
    minutes = float(args.minutes)
    print(
        f"== soak: {minutes:g} min of mixed load on 4 fillers and 4 robots (windows of {minutes * 6:.0f} s)", flush=True
    )
    if not (shutil.which("mosquitto") or Path("/usr/sbin/mosquitto").exists()):
        print("  (mosquitto is missing: make mosquitto installs it; the soak needs its PubSub)", flush=True)
        return
    tmp = Path(peers.tmp) / "soak"
    tmp.mkdir()
    result = soak(minutes, tmp)
    report.raw["soak"] = result
    for measure, value, reference, ratio, target, passed in verdicts(result):
        report.add(measure, value, reference, ratio, target, lambda _x, ok=passed: ok)
    for error in result["errors"][:5]:
        print(f"  ! server log: {error}", flush=True)


def main() -> int:
    """``python -m benchmarks.soak [--minutes N]``: the soak alone, its figures as JSON on the last line."""
    parser = argparse.ArgumentParser(prog="python -m benchmarks.soak")
    parser.add_argument("--minutes", type=float, default=20.0)
    args = parser.parse_args()
    with tempfile.TemporaryDirectory(prefix="uacell-soak-") as tmp:
        result = soak(args.minutes, Path(tmp))
    for measure, value, reference, _ratio, target, passed in verdicts(result):
        print(f"{measure}: {value} (reference {reference}, target {target}) {'PASS' if passed else 'FAIL'}")
    print(json.dumps(result, default=str))
    return 0


if __name__ == "__main__":
    sys.exit(main())
