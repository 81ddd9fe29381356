"""HistoryRead from node-opcua: raw values through continuation points, events with a filter, and
ReadProcessedDetails compared with node-opcua-aggregates on the same raw values (docs/history.md)."""

from __future__ import annotations

import asyncio
from datetime import UTC, datetime, timedelta

import pytest
from asyncua import Client, ua
from asyncua.ua.ua_binary import variant_to_binary
from conftest import run_node

from uacell.history.backends import VALUE
from uacell.history.service import to_micros
from uacell.server import UacellServer

pytestmark = pytest.mark.interop

CELL = "urn:uacell:cell"
F = "Filler1"
BAD = ua.StatusCodes.BadSensorFailure


def samples(base: datetime) -> list[tuple[datetime, float, int]]:
    """10 minutes of a speed: a value every 0.25 s in steps, two values sharing each 30th timestamp,
    a Bad value in minute 3, nothing in minute 7."""
    out: list[tuple[datetime, float, int]] = []
    for i in range(2400):
        t = base + timedelta(milliseconds=250 * i)
        if 420 <= i * 0.25 < 480:
            continue
        status = BAD if i == 800 else 0
        out.append((t, float((i * 37) % 101), status))
        if i % 30 == 0:
            out.append((t, float(i % 7), 0))
    return out


def expected_at(points: list[tuple[datetime, float, int]], t: datetime, simple: bool) -> tuple[float | None, int]:
    """The value and StatusCode at ``t`` as OPC 10000-11 6.5.5 with OPC 10000-13 3.1.8/3.1.9 give them for
    Stepped data where only Good values count."""
    raw_bits, interpolated = 0x400, 0x402
    skipped = False
    for when, value, status in reversed([p for p in points if p[0] <= t]):  # newest first, last written first
        if status:
            if simple:
                return None, ua.StatusCodes.BadNoData
            skipped = True
            continue
        if when == t:
            return value, raw_bits
        return value, (ua.StatusCodes.UncertainDataSubNormal if skipped else 0) | interpolated
    return None, ua.StatusCodes.BadNoData


def stepped_time_average(points: list[tuple[datetime, float, int]], a: datetime, b: datetime) -> float | None:
    before = [p for p in points if p[0] < a]
    inside = [p for p in points if a <= p[0] < b]
    steps = before[-1:] + inside
    total = covered = 0.0
    for k, (t, v, s) in enumerate(steps):
        t0 = max(t, a)
        t1 = min(steps[k + 1][0] if k + 1 < len(steps) else b, b)
        if t1 <= t0 or s != 0:
            continue
        total += v * (t1 - t0).total_seconds()
        covered += (t1 - t0).total_seconds()
    return total / covered if covered else None


async def test_node_opcua_reads_raw_processed_and_events(app: UacellServer) -> None:
    # a plain client (no data type definitions to load), keep-alives every 5 s: on a loaded machine
    # the in-process server and client share one loop
    async with Client(app.endpoint, timeout=30, watchdog_intervall=5.0) as client:
        await _reads(app, client)


async def _reads(app: UacellServer, client: Client) -> None:
    ns = await client.get_namespace_index(CELL)
    speed = ua.NodeId(f"{F}.Status.CurMachSpeed", ns)
    assert app.history is not None
    base = datetime.now(UTC).replace(microsecond=0) - timedelta(days=2)
    data = samples(base)
    key = app.history.values[speed]
    for t, v, s in data:
        app.history.store.record(
            key, to_micros(t), VALUE, s, "", variant_to_binary(ua.Variant(v, ua.VariantType.Double))
        )
    machine = client.get_node(ua.NodeId(f"{F}.BaseStateMachine.MachineState", ns))
    await machine.call_method(ua.NodeId(f"{F}.BaseStateMachine.MachineState.Reset", ns))
    await app.history.store.flush()
    end = base + timedelta(minutes=10)
    bound_start, bound_end = base - timedelta(minutes=1), base + timedelta(milliseconds=600)
    # at a kept time, between two, before the first, just after the Bad value of i = 800
    instants = [base + timedelta(milliseconds=t) for t in (250, 100, -1000, 200_100, 0)]
    out = await asyncio.to_thread(
        run_node,
        "history.js",
        app.endpoint,
        speed.to_string(),
        base.isoformat(),
        end.isoformat(),
        "60000",
        bound_start.isoformat(),
        bound_end.isoformat(),
        ",".join(t.isoformat() for t in instants),
    )

    # raw: every value, in order, through continuation points
    assert [r["value"] for r in out["raw"]] == [v for _, v, _ in data]
    assert out["pages"] == len(data) // 1000 + 1
    assert out["raw"][800 + 800 // 30 + 1]["status"] == BAD

    # bounds (OPC 10000-11 4.4): nothing before StartTime, so an empty bound there; the values of the
    # window; the first value at or after EndTime. Two a page, the same sequence.
    def iso(t: datetime) -> str:  # as node-opcua prints a DateTime
        return t.isoformat(timespec="milliseconds").replace("+00:00", "Z")

    inside = [(iso(t), v) for t, v, _ in data if bound_start <= t < bound_end]
    after = next((iso(t), v) for t, v, _ in data if t >= bound_end)
    sequence = [(iso(bound_start), None), *inside, after]
    got = out["bounded"]["values"]
    assert [(r["time"], r["value"]) for r in got] == sequence
    assert got[0]["status"] == ua.StatusCodes.BadBoundNotFound and got[0]["serverTime"] == iso(bound_start)
    assert all(r["status"] == 0 for r in got[1:])
    assert out["bounded"]["pages"] == 1
    assert out["boundedPaged"]["values"] == got and out["boundedPaged"]["pages"] == (len(sequence) + 1) // 2

    # values at instants (OPC 10000-11 6.5.5), by OPC 10000-13's bounds on stepped data with only Good
    # values counting: the value kept at the instant (Raw), else the last one before it (Interpolated);
    # simple bounds give Bad_NoData for a Bad value before, interpolated ones skip it (Uncertain)
    for mode in ("simple", "interpolated"):
        got_at = out["atTime"][mode]
        assert got_at["status"] == "Good"
        want_at = [expected_at(data, t, simple=mode == "simple") for t in instants]
        assert [(r["value"], r["status"], r["time"]) for r in got_at["values"]] == [
            (v, s, iso(t)) for (v, s), t in zip(want_at, instants, strict=True)
        ], mode

    # processed: uacell against node-opcua-aggregates, interval by interval
    for name in ("Average", "Minimum", "Maximum", "Count"):
        ours, ref = out["processed"][name]["values"], out["reference"][name]
        assert out["processed"][name]["status"] == "Good"
        assert len(ours) == len(ref) == 10
        for k, (o, r) in enumerate(zip(ours, ref, strict=True)):
            where = f"{name} interval {k}: uacell {o}, node-opcua {r}"
            if name == "Count" and k == 7:
                # no raw value in minute 7: Part 13 counts 0, Good (node-opcua-aggregates: Bad_NoData)
                assert (o["value"], o["status"]) == (0, 0x401), where
                continue
            assert (o["status"] >> 30) == (r["status"] >> 30), where  # Good / Uncertain / Bad alike
            assert o["status"] & 0xFFFF in (0x401, 0x405) or o["status"] >> 31, where  # DataValue, Calculated
            if r["value"] is None or r["status"] >> 31:
                assert o["value"] is None or o["status"] >> 31, where
            else:
                assert o["value"] == pytest.approx(r["value"]), where
    # Interpolative, each interval starting 0.1 s after a kept time (two values share each whole
    # minute here, where node-opcua-aggregates takes the first written and uacell the last, which is
    # the one a Stepped variable holds): the value before, as node-opcua-aggregates interpolates it
    ours, ref = out["processed"]["InterpolativeShifted"]["values"], out["reference"]["InterpolativeShifted"]
    assert len(ours) == len(ref) == 10
    for k, (o, r) in enumerate(zip(ours, ref, strict=True)):
        assert (o["value"], o["status"], o["time"]) == (r["value"], 0x402, r["time"]), (k, o, r)
    # TimeAverage is not in node-opcua-aggregates: against the stepped definition (Part 13)
    for k, o in enumerate(out["processed"]["TimeAverage"]["values"]):
        a = base + timedelta(minutes=k)
        want = stepped_time_average(data, a, a + timedelta(minutes=1))
        assert want is not None and o["value"] == pytest.approx(want), (k, o, want)

    # events: the transitions the Reset caused, through the Server object, filtered by type
    assert out["eventStatus"] == "Good"
    assert {e["type"] for e in out["events"]} == {"ns=0;i=2311"}
    assert {"Running", "Idle"} <= {e["toState"] for e in out["events"]}
