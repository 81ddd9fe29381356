"""The history section of ``make bench`` (docs/performance.md, "History").

- SetMachSpeed calls/s with history on vs off (the same demo cell, side by side, rotated rounds);
- 5,000 values/s recorded through the history service (encoding, queue, writer thread, SQLite): the
  process's CPU time over the wall time, as a fraction of one core;
- a raw read of 1,000,000 values through continuation points over OPC UA (asyncua client): none
  repeated, none missing;
- store growth per PackML unit per day: the demo Filler1 producing (Execute) for a while, the bytes
  and rows history.sqlite gained, scaled to a day;
- other clients while history is read: a ``uacell serve`` peer with 30,000 stored events, a probing
  client's Reads of CurrentTime (p99) alone and while two clients read every event through
  continuation points, each client its own process and connection (issue 39).
"""

from __future__ import annotations

import argparse
import asyncio
import json
import subprocess
import sys
import tempfile
import time
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from benchmarks.harness import SET_SPEED, Peers, Report, free_port, loaded, rotated, running

ROOT = Path(__file__).resolve().parents[1]

READ_VALUES = 1_000_000
INGEST_RATE = 5_000


HISTORY_SESSIONS = (8, 32)  # history on against off, at these sessions


def history_section(report: Report, peers: Peers, args: argparse.Namespace) -> None:

    print("== history (SetMachSpeed with history on vs off, ingest CPU, 1M values, growth, other clients)", flush=True)
    raw: dict[str, Any] = {}
    report.raw["history"] = raw
    on, off = peers.uacell(), peers.uacell(history=False)
    with running(on, off):
        for n in HISTORY_SESSIONS:
            for r in range(args.rounds):
                for p in rotated([on, off], r):
                    spec = {"mode": "calls", "sessions": n, "seconds": args.seconds, "steps": SET_SPEED}
                    raw.setdefault(f"{p.name} x{n}", []).append(loaded(p, spec))
    for n in HISTORY_SESSIONS:
        ours, theirs = raw[f"{on.name} x{n}"], raw[f"{off.name} x{n}"]
        report.add_rates(f"SetMachSpeed calls/s, {n} sessions, history on", ours, theirs, "history off", 0.95)
        # what history costs a call, steadier than the rates on a shared machine (no target of its own)
        report.add_cpu(f"SetMachSpeed CPU per call, {n} sessions, history on", ours, theirs, "history off")
    seconds = 3.0 if args.quick else 10.0
    cpu = asyncio.run(ingest_cpu(INGEST_RATE, seconds))
    raw["ingest"] = cpu
    report.add(
        f"history ingest {INGEST_RATE} values/s, CPU of one core",
        f"{cpu['core_fraction'] * 100:.1f} % ({cpu['values']} values in {cpu['seconds']:.1f} s)",
        f"20 % of one core (idle server {cpu['idle_core_fraction'] * 100:.1f} % besides)",
        cpu["core_fraction"] / 0.20,
        "<= 1.00x",
        lambda x: x <= 1.0,
    )
    read = asyncio.run(read_million(READ_VALUES))
    raw["read"] = read
    report.add(
        f"raw HistoryRead of {READ_VALUES:,} values through continuation points",
        f"{read['values']:,} values, {read['pages']} pages, {read['rate']:.0f} values/s,"
        f" {read['duplicates']} duplicates, {read['gaps']} gaps",
        "every value once, in order",
        1.0 if read["exact"] else 0.0,
        "== 1.00x",
        lambda x: x == 1.0,
    )
    growth = asyncio.run(store_growth(20.0 if args.quick else 60.0))
    raw["growth"] = growth
    report.add(
        "history store growth, one PackML unit producing",
        f"{growth['mb_per_day']:.1f} MB/day ({growth['rows_per_day']:,.0f} rows/day)",
        f"measured over {growth['seconds']:.0f} s",
        None,
    )
    stall_row(report, peers, args, raw)


async def _server(data: Path, **history: Any) -> Any:
    from uacell.config import Config
    from uacell.server import UacellServer

    config = Config()
    config.server.port = free_port()
    config.server.data_dir = data
    config.packml.acting_time = 0.05
    for key, value in history.items():
        setattr(config.history, key, value)
    app = UacellServer(config)
    await app.setup()
    await app.start()
    await app.snapshot_written()  # its CPU (a forked child, after a first start) is not history's
    return app


async def ingest_cpu(rate: int, seconds: float) -> dict[str, Any]:
    """Values recorded through the service's own path (the DataValue the address space hands its
    change callback: encoded, queued, committed by the writer thread). The figure is the process's CPU
    time while ingesting minus its CPU time over as long a time idle (the served demo cell's own work),
    over the wall time."""
    from asyncua import ua

    with tempfile.TemporaryDirectory(prefix="uacell-bench-history-") as tmp:
        app = await _server(Path(tmp) / "data")
        try:
            service = app.history
            assert service is not None
            await service.store.flush()
            keys = [f"ns=9;s=bench.{i}" for i in range(50)]
            now = datetime.now(UTC)
            values = [
                ua.DataValue(ua.Variant(float(i), ua.VariantType.Double), SourceTimestamp=now) for i in range(rate)
            ]
            batch = rate // 100

            async def paced(ingest: bool) -> tuple[float, float, int]:
                t0, c0 = time.perf_counter(), time.process_time()
                sent = tick = 0
                while time.perf_counter() - t0 < seconds:
                    if ingest:
                        for k in range(batch):
                            service._record_value(keys[k % len(keys)], values[(sent + k) % rate])
                        sent += batch
                    tick += 1
                    # 100 batches a second, paced against the clock (not by sleeping a fixed time)
                    await asyncio.sleep(max(0.0, t0 + tick / 100 - time.perf_counter()))
                await service.store.flush()
                return time.perf_counter() - t0, time.process_time() - c0, sent

            idle_wall, idle_cpu, _ = await paced(False)
            wall, cpu, sent = await paced(True)
            idle_wall2, idle_cpu2, _ = await paced(False)  # before and after: the mean idle rate
        finally:
            await app.stop()
    idle_wall, idle_cpu = idle_wall + idle_wall2, idle_cpu + idle_cpu2
    extra = cpu - idle_cpu * wall / idle_wall
    return {
        "values": sent,
        "seconds": wall,
        "cpu_seconds": cpu,
        "idle_cpu_seconds": idle_cpu,
        "idle_core_fraction": idle_cpu / idle_wall,
        "core_fraction": max(0.0, extra) / wall,
        "rate": sent / wall,
    }


async def read_million(count: int) -> dict[str, Any]:
    from asyncua import Client, ua
    from asyncua.ua.ua_binary import variant_to_binary

    from uacell.history.backends import VALUE
    from uacell.history.service import to_micros

    with tempfile.TemporaryDirectory(prefix="uacell-bench-history-") as tmp:
        app = await _server(Path(tmp) / "data", max_values_per_request=10_000)
        try:
            service = app.history
            assert service is not None
            node = next(n for n in service.values if str(n.Identifier).endswith("Status.CurMachSpeed"))
            key = service.values[node]
            base = datetime.now(UTC) - timedelta(days=3)
            for i in range(count):  # 10 values per millisecond: many share a timestamp
                t = to_micros(base) + (i // 10) * 1000
                service.store.record(
                    key, t, VALUE, 0, "", variant_to_binary(ua.Variant(float(i), ua.VariantType.Double))
                )
                if i % 100_000 == 0:
                    await asyncio.sleep(0)
            await service.store.flush()
            seen: list[float] = []
            pages = 0
            t0 = time.perf_counter()
            async with Client(app.endpoint, timeout=120) as client:
                cp: bytes | None = None
                while True:
                    params = ua.HistoryReadParameters()
                    details = ua.ReadRawModifiedDetails()
                    details.IsReadModified = False
                    details.StartTime = base - timedelta(seconds=1)
                    details.EndTime = base + timedelta(days=1)
                    details.NumValuesPerNode = 0
                    details.ReturnBounds = False  # the values alone, each once
                    params.HistoryReadDetails = details
                    params.TimestampsToReturn = ua.TimestampsToReturn.Source
                    params.ReleaseContinuationPoints = False
                    params.NodesToRead = [ua.HistoryReadValueId(NodeId=node, ContinuationPoint=cp)]
                    (res,) = await client.uaclient.history_read(params)
                    pages += 1
                    seen += [dv.Value.Value for dv in res.HistoryData.DataValues]
                    cp = res.ContinuationPoint
                    if not cp:
                        break
            elapsed = time.perf_counter() - t0
        finally:
            await app.stop()
    numbers = [int(v) for v in seen]
    duplicates = len(numbers) - len(set(numbers))
    gaps = len(set(range(count)) - set(numbers))
    return {
        "values": len(seen),
        "pages": pages,
        "seconds": elapsed,
        "rate": len(seen) / elapsed,
        "duplicates": duplicates,
        "gaps": gaps,
        "exact": numbers == list(range(count)),
    }


async def store_growth(seconds: float) -> dict[str, Any]:
    """Filler1 in Execute (producing, its speed changed once a minute), the demo robot idle."""
    from uacell.packml import EXECUTE, MACHINE
    from uacell.packml.binding import UNITS

    with tempfile.TemporaryDirectory(prefix="uacell-bench-history-") as tmp:
        data = Path(tmp) / "data"
        app = await _server(data)
        try:
            service = app.history
            assert service is not None
            unit = app.registry(UNITS)["Filler1"].unit
            unit.command(MACHINE, "Reset")
            deadline = time.monotonic() + 30
            while unit.state != "Idle" and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            unit.command(EXECUTE, "Start", [])
            while unit.state != "Execute" and time.monotonic() < deadline:
                await asyncio.sleep(0.05)
            await service.store.flush()
            db = data / "history.sqlite"
            rows0, size0 = service.store.written, _size(db)
            t0 = time.monotonic()
            while time.monotonic() - t0 < seconds:
                await asyncio.sleep(1.0)
            await service.store.flush()
            rows, size, elapsed = service.store.written - rows0, _size(db) - size0, time.monotonic() - t0
            state = unit.state
            by_node = _rows_by_node(db)
        finally:
            await app.stop()
    day = 86_400 / elapsed
    return {
        "seconds": elapsed,
        "rows": rows,
        "bytes": size,
        "rows_per_day": rows * day,
        "mb_per_day": size * day / 1e6,
        "state_at_end": state,
        "rows_by_node": by_node,
    }


def _rows_by_node(db: Path) -> dict[str, int]:
    import sqlite3

    con = sqlite3.connect(db)
    try:
        rows = con.execute("SELECT node, COUNT(*) FROM samples GROUP BY node ORDER BY 2 DESC").fetchall()
    finally:
        con.close()
    return {str(n): int(c) for n, c in rows}


def _size(db: Path) -> int:
    import sqlite3

    con = sqlite3.connect(db)
    try:
        pages = con.execute("PRAGMA page_count").fetchall()[0][0]
        free = con.execute("PRAGMA freelist_count").fetchall()[0][0]
        size = con.execute("PRAGMA page_size").fetchall()[0][0]
    finally:
        con.close()
    return int((pages - free) * size)


# --- other clients while history is read (issue 39, docs/history.md "Other clients") ---------------
STALL_EVENTS = 30_000
STALL_READERS = 2
STALL_TARGET_MS = 50.0


def fill_events(service: Any, count: int) -> None:
    """``count`` TransitionEvents of Filler1's MachineState kept with the Server object, one a
    millisecond up to an hour ago (queued for the store's writer thread; flush to wait for them)."""
    from asyncua import ua

    from uacell.history.backends import EVENT
    from uacell.history.service import encode_fields, event_plan, to_micros

    vt = ua.VariantType
    types = {
        "EventId": vt.ByteString, "EventType": vt.NodeId, "SourceNode": vt.NodeId, "SourceName": vt.String,
        "Time": vt.DateTime, "ReceiveTime": vt.DateTime, "Message": vt.LocalizedText, "Severity": vt.UInt16,
        "FromState": vt.LocalizedText, "ToState": vt.LocalizedText, "ToState/Id": vt.NodeId,
    }  # fmt: skip
    plan = event_plan(types)
    key = service.notifiers[ua.NodeId(ua.ObjectIds.Server)]
    source = ua.NodeId("Filler1.BaseStateMachine.MachineState", 1)
    first = datetime.now(UTC) - timedelta(hours=1, milliseconds=count)
    for i in range(count):
        t = first + timedelta(milliseconds=i)
        fields: dict[str, Any] = {
            "EventId": b"bench" + i.to_bytes(11, "big"), "EventType": ua.NodeId(ua.ObjectIds.TransitionEventType),
            "SourceNode": source, "SourceName": "MachineState", "Time": t, "ReceiveTime": t,
            "Message": ua.LocalizedText(f"Transition {i}"), "Severity": 500,
            "FromState": ua.LocalizedText("Idle"), "ToState": ua.LocalizedText("Starting"),
            "ToState/Id": ua.NodeId("Starting", 1),
        }  # fmt: skip
        service.store.record(key, to_micros(t), EVENT, 0, "i=2311", encode_fields(fields, plan))


def stall_row(report: Report, peers: Peers, args: argparse.Namespace, raw: dict[str, Any]) -> None:
    """A probing client (its own process and connection) reads CurrentTime every 5 ms, first alone,
    then while ``STALL_READERS`` clients (each its own process) read every stored event through
    continuation points, again and again."""

    seconds = 10.0 if args.quick else 30.0
    with running(peers.uacell(history_events=STALL_EVENTS)) as (peer,):
        alone = _probe(peer.endpoint, seconds)
        readers = [_spawn("read", peer.endpoint) for _ in range(STALL_READERS)]
        try:
            for r in readers:  # connected, first page read
                assert r.stdout is not None
                line = r.stdout.readline()
                if line.strip() != "ready":
                    raise RuntimeError(f"a history reader did not start: {line!r}")
            loaded = _probe(peer.endpoint, seconds)
        finally:
            reads = []
            for r in readers:
                try:
                    out, _ = r.communicate("stop\n", timeout=120)
                    reads.append(json.loads(out.strip().splitlines()[-1]))
                except (subprocess.TimeoutExpired, json.JSONDecodeError, IndexError):
                    r.kill()
                    r.wait()
                    reads.append({"passes": 0, "events": 0, "complete": False, "seconds": 0.0, "max_page": 0})
    raw["stall"] = {"events_stored": STALL_EVENTS, "alone": alone, "loaded": loaded, "readers": reads}
    passes = sum(r["passes"] for r in reads)
    events = sum(r["events"] for r in reads)
    report.add(
        f"CurrentTime Read p99 while {STALL_READERS} clients read {STALL_EVENTS:,} events",
        f"p50 {_ms(loaded, 'p50_ms')} ms p99 {_ms(loaded, 'p99_ms')} ms max {_ms(loaded, 'max_ms')} ms"
        f" ({loaded['reads']} reads)",
        f"no history read: p50 {_ms(alone, 'p50_ms')} ms p99 {_ms(alone, 'p99_ms')} ms",
        loaded["p99_ms"] / STALL_TARGET_MS,
        "<= 1x (50 ms)",
        lambda x: x <= 1.0,
    )
    report.add(
        "  events those clients read meanwhile",
        f"{events:,} events, {passes} full passes, {events / max(1e-9, max(r['seconds'] for r in reads)):,.0f}/s",
        f"every pass all {STALL_EVENTS:,}, pages <= 1,000",
        1.0 if passes and all(r["complete"] and r["max_page"] <= 1000 for r in reads) else 0.0,
        "== 1x",
        lambda x: x == 1.0,
    )


def _ms(result: dict[str, Any], key: str) -> str:
    return f"{result[key]:.1f}"


def _spawn(role: str, endpoint: str, *extra: str) -> subprocess.Popen[str]:
    return subprocess.Popen(
        [sys.executable, "-m", "benchmarks.history", role, endpoint, *extra],
        cwd=ROOT,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        stderr=subprocess.DEVNULL,
        text=True,
    )


def _probe(endpoint: str, seconds: float) -> dict[str, Any]:
    proc = _spawn("probe", endpoint, str(seconds))
    try:
        out, _ = proc.communicate(timeout=seconds + 120)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
        raise RuntimeError("the probing client did not finish") from None
    lines = out.strip().splitlines()
    if proc.returncode != 0 or not lines:
        raise RuntimeError(f"the probing client failed (exit {proc.returncode})")
    result: dict[str, Any] = json.loads(lines[-1])
    return result


async def probe(endpoint: str, seconds: float) -> dict[str, Any]:
    """Reads of the Server's CurrentTime, one every 5 ms (the next 5 ms after the last answer)."""
    from asyncua import Client, ua

    latencies: list[float] = []
    # keep-alives every 5 s, not asyncua's 1 s: a shared machine may hold the probe for a second
    async with Client(endpoint, timeout=60, watchdog_intervall=5.0) as client:
        node = client.get_node(ua.ObjectIds.Server_ServerStatus_CurrentTime)
        await node.read_value()
        t_end = time.perf_counter() + seconds
        while time.perf_counter() < t_end:
            t0 = time.perf_counter()
            await node.read_value()
            latencies.append((time.perf_counter() - t0) * 1000)
            await asyncio.sleep(0.005)
    latencies.sort()
    return {
        "reads": len(latencies),
        "p50_ms": latencies[len(latencies) // 2],
        "p99_ms": latencies[max(0, int(len(latencies) * 0.99) - 1)],
        "max_ms": latencies[-1],
    }


async def read_events(endpoint: str) -> dict[str, Any]:
    """Every event the Server object keeps, newest first through continuation points, pass after
    pass until ``stop`` arrives on stdin (the current pass is finished)."""
    import threading

    from asyncua import Client, ua

    stop = threading.Event()

    def until_stop() -> None:
        sys.stdin.readline()
        stop.set()

    threading.Thread(target=until_stop, daemon=True).start()
    passes = events = max_page = 0
    complete = True
    t0 = time.perf_counter()
    async with Client(endpoint, timeout=120, watchdog_intervall=5.0) as client:
        details = ua.ReadEventDetails(
            StartTime=datetime.now(UTC) + timedelta(hours=1), EndTime=datetime.now(UTC) - timedelta(days=1)
        )
        details.NumValuesPerNode = 0  # as many as the server gives in one page
        details.Filter = ua.EventFilter(
            SelectClauses=[
                ua.SimpleAttributeOperand(BrowsePath=[ua.QualifiedName(n)])
                for n in ("EventId", "EventType", "SourceNode", "SourceName", "Time", "Message", "Severity", "ToState")
            ]
        )
        while not stop.is_set():
            cp = None
            ids: set[bytes] = set()
            while True:
                params = ua.HistoryReadParameters(
                    HistoryReadDetails=details,
                    TimestampsToReturn=ua.TimestampsToReturn.Both,
                    ReleaseContinuationPoints=False,
                    NodesToRead=[ua.HistoryReadValueId(NodeId=ua.NodeId(ua.ObjectIds.Server), ContinuationPoint=cp)],
                )
                (res,) = await client.uaclient.history_read(params)
                page = res.HistoryData.Events if res.StatusCode.is_good() else []
                max_page = max(max_page, len(page))
                ids.update(e.EventFields[0].Value for e in page if e.EventFields[0].Value.startswith(b"bench"))
                if passes == 0 and cp is None:
                    print("ready", flush=True)
                cp = res.ContinuationPoint
                if not cp:
                    break
            passes += 1
            events += len(ids)
            complete = complete and len(ids) == STALL_EVENTS
    return {
        "passes": passes,
        "events": events,
        "complete": complete,
        "max_page": max_page,
        "seconds": time.perf_counter() - t0,
    }


def main() -> int:
    """``python -m benchmarks.history probe ENDPOINT SECONDS`` or ``read ENDPOINT``: one client of
    the stall row, its figures as a JSON line."""
    role, endpoint = sys.argv[1], sys.argv[2]
    if role == "probe":
        result = asyncio.run(probe(endpoint, float(sys.argv[3])))
    else:
        result = asyncio.run(read_events(endpoint))
    print(json.dumps(result), flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
