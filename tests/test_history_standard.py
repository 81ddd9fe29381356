"""History as OPC 10000-4, -11 and -13 answer it (issue 44), from asyncua clients over TCP: the
aggregates' status bits and Count of an empty interval, EventNotifier's HistoryRead bit after
transitions, HistoryUpdate per item, continuation points bound to their session and released,
``[history] enabled = false`` (docs/history.md)."""

from __future__ import annotations

import asyncio
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

import pytest
import pytest_asyncio
from asyncua import Client, ua
from asyncua.ua.ua_binary import nodeid_from_binary, struct_from_binary, variant_to_binary
from asyncua.ua.uaerrors import UaStatusCodeError
from conftest import fast_config, start_app
from helpers import until, wait_until

from uacell.history.backends import EVENT, VALUE
from uacell.history.processed import aggregate
from uacell.history.service import encode_fields, event_plan, to_micros
from uacell.security.users import UserStore
from uacell.server import UacellServer

module_loop = pytest.mark.asyncio(loop_scope="module")

CELL = "urn:uacell:cell"
PASSWORD = "pw-history-1"
SPEED = "Filler1.Status.CurMachSpeed"
MACHINE = "Filler1.BaseStateMachine.MachineState"
CTRL = "Robot1.Controllers.Controller1"
SO = f"{CTRL}.SystemOperation.SystemOperationStateMachine"
TC = f"{CTRL}.TaskControls.TaskControl1.TaskControlOperation.TaskControlStateMachine"
SC = ua.StatusCodes
MINUTE = timedelta(minutes=1)
HOUR = timedelta(hours=1)
DAY = timedelta(days=1)
GOOD_CALCULATED = 0x401  # Good, InfoType DataValue (0x400), HistorianBits Calculated (0x1)
GOOD_CALCULATED_PARTIAL = 0x405  # and Partial (0x4)


@pytest_asyncio.fixture(scope="module", loop_scope="module")
async def app(tmp_path_factory: pytest.TempPathFactory):
    data = tmp_path_factory.mktemp("history-standard") / "data"
    UserStore.in_data_dir(data).add("ada", "admin", PASSWORD)
    programs = data / "programs" / "Robot1" / "Controller1"
    programs.mkdir(parents=True)
    (programs / "short.robot").write_text("program Short version 1\nmove 10 0 0 0 0 0\nwait 1\n")
    server = await start_app(fast_config(data))
    yield server
    await server.stop()


async def connect(app: UacellServer, user: str | None = None) -> tuple[Client, int]:
    client = Client(app.endpoint, timeout=30)
    if user:
        client.set_user(user)
        client.set_password(PASSWORD)
    await client.connect()
    return client, await client.get_namespace_index(CELL)


def params(
    details: object, node: ua.NodeId, cp: bytes | None = None, release: bool = False
) -> ua.HistoryReadParameters:
    return ua.HistoryReadParameters(
        HistoryReadDetails=details,
        TimestampsToReturn=ua.TimestampsToReturn.Both,
        ReleaseContinuationPoints=release,
        NodesToRead=[ua.HistoryReadValueId(NodeId=node, ContinuationPoint=cp)],
    )


def raw(start: datetime, end: datetime, count: int) -> ua.ReadRawModifiedDetails:
    return ua.ReadRawModifiedDetails(
        IsReadModified=False, StartTime=start, EndTime=end, NumValuesPerNode=count, ReturnBounds=False
    )


def processed(start: datetime, end: datetime, aggregate_id: int) -> ua.ReadProcessedDetails:
    return ua.ReadProcessedDetails(
        StartTime=start, EndTime=end, ProcessingInterval=60_000.0, AggregateType=[ua.NodeId(aggregate_id)]
    )


async def store_values(app: UacellServer, node: ua.NodeId, values: list[tuple[datetime, float]]) -> None:
    assert app.history is not None
    key = app.history.values[node]
    for t, v in values:
        app.history.store.record(
            key, to_micros(t), VALUE, 0, "", variant_to_binary(ua.Variant(v, ua.VariantType.Double))
        )
    await app.history.store.flush()


def test_aggregate_status_bits_pure() -> None:
    """Part 13 / Part 4 7.39: Calculated aggregates carry InfoType DataValue + Calculated (0x401), the
    shorter last interval Partial too (0x405); Count of an interval with no value is 0, Good."""
    m = 60_000_000
    points = [(0, 1.0, 0), (m // 2, 3.0, 0), (2 * m + 1, 5.0, 0)]
    average = aggregate("Average", points, 0, 2 * m + m // 2, m)
    assert [(iv.value, iv.status) for iv in average] == [
        (2.0, GOOD_CALCULATED),
        (None, SC.BadNoData),  # no raw value: no average (Part 13)
        (5.0, GOOD_CALCULATED_PARTIAL),
    ]
    count = aggregate("Count", points, 0, 2 * m + m // 2, m)
    assert [(iv.value, iv.status, iv.integer) for iv in count] == [
        (2, GOOD_CALCULATED, True),
        (0, GOOD_CALCULATED, True),
        (1, GOOD_CALCULATED_PARTIAL, True),
    ]
    uncertain = aggregate("Maximum", [(0, 1.0, 0), (1, 7.0, SC.BadSensorFailure)], 0, m, m)
    assert uncertain[0].status == SC.UncertainDataSubNormal | GOOD_CALCULATED


@module_loop
async def test_processed_values_carry_calculated_and_partial_bits(app: UacellServer) -> None:
    client, ns = await connect(app)
    try:
        speed = ua.NodeId(SPEED, ns)
        base = datetime.now(UTC).replace(microsecond=0) - timedelta(days=3)
        # minute 0: 10, 20; minute 1: nothing; minute 2 (half of it asked): 30
        await store_values(app, speed, [(base, 10.0), (base + MINUTE / 2, 20.0), (base + 2 * MINUTE, 30.0)])
        end = base + 2 * MINUTE + MINUTE / 2
        (avg,) = await client.uaclient.history_read(
            params(processed(base, end, ua.ObjectIds.AggregateFunction_Average), speed)
        )
        got: list[tuple[Any, ...]] = [
            (dv.Value.Value if dv.Value is not None else None, dv.StatusCode.value) for dv in avg.HistoryData.DataValues
        ]
        assert got == [(15.0, GOOD_CALCULATED), (None, SC.BadNoData), (30.0, GOOD_CALCULATED_PARTIAL)]
        (count,) = await client.uaclient.history_read(
            params(processed(base, end, ua.ObjectIds.AggregateFunction_Count), speed)
        )
        got = [(dv.Value.Value, dv.Value.VariantType, dv.StatusCode.value) for dv in count.HistoryData.DataValues]
        assert got == [
            (2, ua.VariantType.UInt32, GOOD_CALCULATED),
            (0, ua.VariantType.UInt32, GOOD_CALCULATED),  # empty: 0, Good, Calculated (not Bad_NoData)
            (1, ua.VariantType.UInt32, GOOD_CALCULATED_PARTIAL),
        ]
        assert [dv.SourceTimestamp for dv in count.HistoryData.DataValues] == [base, base + MINUTE, base + 2 * MINUTE]
        # Interpolative (Part 13 5.4.3.4): the value at each interval's start, Raw when kept at that
        # time, else the Stepped value before it, Interpolated; Bad_NoData before the first
        (interpolative,) = await client.uaclient.history_read(
            params(processed(base - MINUTE, end, ua.ObjectIds.AggregateFunction_Interpolative), speed)
        )
        got = [
            (dv.Value.Value if dv.Value is not None else None, dv.StatusCode.value, dv.SourceTimestamp)
            for dv in interpolative.HistoryData.DataValues
        ]
        assert got == [
            (None, SC.BadNoData, base - MINUTE),
            (10.0, 0x400, base),
            (20.0, 0x402, base + MINUTE),
            (30.0, 0x400, base + 2 * MINUTE),
        ]
    finally:
        await client.disconnect()


@module_loop
async def test_event_notifiers_keep_their_history_read_bit_after_transitions(app: UacellServer) -> None:
    """A machine's first transition caused by a call makes its audit event emitter: the HistoryRead
    bit that history set stays (5 = SubscribeToEvents | HistoryRead, before and after)."""
    client, ns = await connect(app)
    machines = [MACHINE, f"{MACHINE}.ExecuteState", TC, SO]

    async def notifiers() -> list[int]:
        return [
            (await client.get_node(ua.NodeId(m, ns)).read_attribute(ua.AttributeIds.EventNotifier)).Value.Value
            for m in machines
        ]

    try:
        assert await notifiers() == [5, 5, 5, 5]
        calls = [
            (MACHINE, "Reset", []),
            (SO, "GetReady", []),
            (TC, "LoadByName", [ua.Variant("short", ua.VariantType.String)]),
        ]
        for obj, method, args in calls:
            node = client.get_node(ua.NodeId(obj, ns))
            await node.call_method(ua.NodeId(f"{obj}.{method}", ns), *args)
        execute = client.get_node(ua.NodeId(f"{MACHINE}.ExecuteState.CurrentState", ns))

        async def idle() -> bool:
            return (await execute.read_value()).Text == "Idle"

        await until(idle, True)  # Resetting takes its acting time and the units' next tick
        assert await notifiers() == [5, 5, 5, 5]
        # and the audit emitters exist now (the rewrite happened at their creation)
        binding = app.server.iserver.aspace
        assert binding.read_attribute_value(ua.NodeId(SO, ns), ua.AttributeIds.EventNotifier).Value.Value == 5
    finally:
        await client.disconnect()


@module_loop
@pytest.mark.parametrize("user", [None, "ada"])
async def test_history_update_answers_unsupported_per_item(app: UacellServer, user: str | None) -> None:
    """No service fault, not Bad_UserAccessDenied (an operator and an admin alike): each item
    Bad_HistoryOperationUnsupported (history is what happened: nothing rewrites it)."""
    client, ns = await connect(app, user)
    try:
        speed = ua.NodeId(SPEED, ns)
        update = ua.UpdateDataDetails(
            NodeId=speed,
            PerformInsertReplace=ua.PerformUpdateType.Insert,
            UpdateValues=[ua.DataValue(ua.Variant(1.0, ua.VariantType.Double), SourceTimestamp=datetime.now(UTC))],
        )
        delete = ua.DeleteRawModifiedDetails(
            NodeId=speed, IsDeleteModified=False, StartTime=datetime.now(UTC) - MINUTE, EndTime=datetime.now(UTC)
        )
        results = await client.uaclient.history_update(
            ua.HistoryUpdateParameters(HistoryUpdateDetails=[update, delete])
        )
        assert [r.StatusCode.value for r in results] == [SC.BadHistoryOperationUnsupported] * 2
        # no item: Bad_NothingToDo, as for every service with a list of operations (asyncua: no results)
        with pytest.raises(UaStatusCodeError) as nothing:
            await client.uaclient.history_update(ua.HistoryUpdateParameters(HistoryUpdateDetails=[]))
        assert nothing.value.code == SC.BadNothingToDo
    finally:
        await client.disconnect()


@module_loop
async def test_continuation_points_belong_to_their_session_and_are_released(app: UacellServer) -> None:
    """Part 4 7.9: a point from another session, or after ReleaseContinuationPoints, is
    Bad_ContinuationPointInvalid; releasing answers Good with no data."""
    first, ns = await connect(app)
    second, _ = await connect(app)
    try:
        speed = ua.NodeId(SPEED, ns)
        base = datetime.now(UTC).replace(microsecond=0) - timedelta(days=5)
        await store_values(app, speed, [(base + i * MINUTE, float(i)) for i in range(30)])
        window = raw(base, base + 30 * MINUTE, 10)
        (page,) = await first.uaclient.history_read(params(window, speed))
        assert [dv.Value.Value for dv in page.HistoryData.DataValues] == [float(i) for i in range(10)]
        cp = page.ContinuationPoint
        assert cp
        (other,) = await second.uaclient.history_read(params(window, speed, cp))
        assert other.StatusCode.value == SC.BadContinuationPointInvalid
        (other,) = await second.uaclient.history_read(params(window, speed, cp, release=True))
        assert other.StatusCode.value == SC.BadContinuationPointInvalid  # not its point to release
        (again,) = await first.uaclient.history_read(params(window, speed, cp))  # still valid for its own
        assert [dv.Value.Value for dv in again.HistoryData.DataValues] == [float(i) for i in range(10, 20)]
        (released,) = await first.uaclient.history_read(params(window, speed, cp, release=True))
        assert released.StatusCode.value == SC.Good and not released.HistoryData.DataValues
        assert not released.ContinuationPoint
        (after,) = await first.uaclient.history_read(params(window, speed, cp))
        assert after.StatusCode.value == SC.BadContinuationPointInvalid
        # events' points alike
        events = ua.ReadEventDetails(StartTime=base, EndTime=datetime.now(UTC) + MINUTE, NumValuesPerNode=1)
        events.Filter = ua.EventFilter(SelectClauses=[ua.SimpleAttributeOperand(BrowsePath=[ua.QualifiedName("Time")])])
        server = ua.NodeId(ua.ObjectIds.Server)
        assert app.history is not None
        plan = event_plan({"Time": ua.VariantType.DateTime, "Message": ua.VariantType.LocalizedText})
        for i in range(2):
            t = base + i * MINUTE
            data = encode_fields({"Time": t, "Message": ua.LocalizedText(f"event {i}")}, plan)
            app.history.store.record(app.history.notifiers[server], to_micros(t), EVENT, 0, "i=2041", data)
        await app.history.store.flush()
        (ev,) = await first.uaclient.history_read(params(events, server))
        assert len(ev.HistoryData.Events) == 1 and ev.ContinuationPoint
        (other,) = await second.uaclient.history_read(params(events, server, ev.ContinuationPoint))
        assert other.StatusCode.value == SC.BadContinuationPointInvalid
        (released,) = await first.uaclient.history_read(params(events, server, ev.ContinuationPoint, release=True))
        assert released.StatusCode.value == SC.Good
        (after,) = await first.uaclient.history_read(params(events, server, ev.ContinuationPoint))
        assert after.StatusCode.value == SC.BadContinuationPointInvalid
    finally:
        await first.disconnect()
        await second.disconnect()
    # a closed session's release list goes with it
    assert app.history is not None
    await wait_until(lambda: not app.history._released)  # type: ignore[union-attr]


@module_loop
async def test_history_disabled_answers_unsupported(tmp_path: Path) -> None:
    """``[history] enabled = false``: every HistoryRead and HistoryUpdate item is
    Bad_HistoryOperationUnsupported, never Good with no values."""
    config = fast_config(tmp_path / "data")
    config.history.enabled = False
    server = await start_app(config)
    try:
        assert server.history is None
        client, ns = await connect(server)
        try:
            speed = ua.NodeId(SPEED, ns)
            now = datetime.now(UTC)
            events = ua.ReadEventDetails(StartTime=now - MINUTE, EndTime=now)
            events.Filter = ua.EventFilter(
                SelectClauses=[ua.SimpleAttributeOperand(BrowsePath=[ua.QualifiedName("Time")])]
            )
            for details, node in (
                (raw(now - MINUTE, now, 0), speed),
                (processed(now - MINUTE, now, ua.ObjectIds.AggregateFunction_Average), speed),
                (events, ua.NodeId(ua.ObjectIds.Server)),
            ):
                (res,) = await client.uaclient.history_read(params(details, node))
                assert res.StatusCode.value == SC.BadHistoryOperationUnsupported, details
            delete = ua.DeleteRawModifiedDetails(
                NodeId=speed, IsDeleteModified=False, StartTime=now - MINUTE, EndTime=now
            )
            results = await client.uaclient.history_update(ua.HistoryUpdateParameters(HistoryUpdateDetails=[delete]))
            assert [r.StatusCode.value for r in results] == [SC.BadHistoryOperationUnsupported]
        finally:
            await client.disconnect()
    finally:
        await server.stop()


@module_loop
async def test_bounding_values_as_part_11_returns_them(app: UacellServer) -> None:
    """OPC 10000-11 4.4 (4.6 in 1.05), ReadRawModifiedDetails.returnBounds: the value at or before
    StartTime and the one at or after EndTime come with the values; where there is none, a DataValue
    with no value, Bad_BoundNotFound and the requested time. asyncua's ``read_raw_history`` asks for
    bounds by default. StartTime = EndTime reads the values at that instant. uacell ignored
    returnBounds and answered an instant with Good_NoData."""
    client, ns = await connect(app)
    try:
        speed = ua.NodeId(SPEED, ns)
        base = datetime.now(UTC).replace(microsecond=0) - timedelta(days=9)  # nothing else stored near it
        await store_values(app, speed, [(base + m * MINUTE, float(m)) for m in (0, 2, 3, 5, 6)])

        def bounded(start: datetime | None, end: datetime | None, count: int) -> ua.ReadRawModifiedDetails:
            none = ua.get_win_epoch()
            return ua.ReadRawModifiedDetails(
                IsReadModified=False, StartTime=start or none, EndTime=end or none, NumValuesPerNode=count
            )

        async def read(details: ua.ReadRawModifiedDetails, cp: bytes | None = None) -> ua.HistoryReadResult:
            (result,) = await client.uaclient.history_read(params(details, speed, cp))
            return result

        def values(result: ua.HistoryReadResult) -> list[float | None]:
            return [dv.Value.Value if dv.Value is not None else None for dv in result.HistoryData.DataValues]

        # asyncua's own call, bounds by default: 0 before StartTime, 5 after EndTime
        node = client.get_node(speed)
        got = await node.read_raw_history(base + MINUTE, base + 4 * MINUTE)
        assert [dv.Value.Value for dv in got] == [0.0, 2.0, 3.0, 5.0]
        assert [dv.SourceTimestamp for dv in got] == [base + m * MINUTE for m in (0, 2, 3, 5)]

        # no value before StartTime: an empty bound at StartTime; after EndTime, the next value kept
        # (the server's own, from today)
        start, end = base - MINUTE, base + 7 * MINUTE
        result = await read(bounded(start, end, 0))
        assert result.StatusCode.value == SC.Good
        assert values(result)[:-1] == [None, 0.0, 2.0, 3.0, 5.0, 6.0]
        first, last = result.HistoryData.DataValues[0], result.HistoryData.DataValues[-1]
        assert first.StatusCode.value == SC.BadBoundNotFound
        assert (first.SourceTimestamp, first.ServerTimestamp) == (start, start)
        assert all(dv.StatusCode.value == SC.Good for dv in result.HistoryData.DataValues[1:])
        assert last.Value is not None and last.SourceTimestamp > base + DAY
        # nothing at or after EndTime (values kept in the future, of a counter no other test reads)
        counter = ua.NodeId("Filler1.Admin.ProdDefectiveCount", ns)
        future = datetime.now(UTC).replace(microsecond=0) + timedelta(days=9)
        await store_values(app, counter, [(future + m * MINUTE, float(m)) for m in (0, 2, 3)])
        (ahead,) = await client.uaclient.history_read(params(bounded(future + MINUTE, future + HOUR, 0), counter))
        assert [dv.Value.Value if dv.Value is not None else None for dv in ahead.HistoryData.DataValues] == [
            0.0,
            2.0,
            3.0,
            None,
        ]
        assert ahead.HistoryData.DataValues[-1].StatusCode.value == SC.BadBoundNotFound
        assert ahead.HistoryData.DataValues[-1].SourceTimestamp == future + HOUR

        # one a page, through continuation points: the bounds are part of the sequence
        paged: list[float | None] = []
        cp = None
        for _ in range(10):
            page = await read(bounded(base + MINUTE, base + 4 * MINUTE, 1), cp)
            paged += values(page)
            cp = page.ContinuationPoint
            if not cp:
                break
        assert paged == [0.0, 2.0, 3.0, 5.0]

        # newest first, and EndTime alone: the bound at the read's beginning, then the empty one past the data
        assert values(await read(bounded(base + 4 * MINUTE, base + MINUTE, 0))) == [5.0, 3.0, 2.0, 0.0]
        alone = await read(bounded(None, base + MINUTE / 2, 5))
        assert values(alone) == [2.0, 0.0, None]
        assert alone.HistoryData.DataValues[-1].SourceTimestamp == base - timedelta(seconds=1)

        # StartTime = EndTime: the value at that instant; with bounds, the next one too
        assert values(await read(raw(base + 2 * MINUTE, base + 2 * MINUTE, 0))) == [2.0]
        assert values(await read(bounded(base + 2 * MINUTE, base + 2 * MINUTE, 0))) == [2.0, 3.0]
        between = await read(raw(base + MINUTE, base + MINUTE, 0))
        assert between.StatusCode.value == SC.GoodNoData and not between.HistoryData.DataValues
    finally:
        await client.disconnect()


@module_loop
async def test_read_at_time_gives_each_instant_its_value(app: UacellServer, monkeypatch: pytest.MonkeyPatch) -> None:
    """OPC 10000-11 6.5.5, ReadAtTimeDetails: a value for each requested time, in the request's order; a
    value kept at that time is Raw, else the Stepped value before it, Interpolated (OPC 10000-13 3.1.8,
    3.1.9; Good values only, TreatUncertainAsBad); before any value Bad_NoData; with simple bounds a Bad
    value before the time is Bad_NoData, with interpolated bounds it is skipped and the value Uncertain.
    uacell answered Bad_HistoryOperationUnsupported."""
    client, ns = await connect(app)
    try:
        speed = ua.NodeId(SPEED, ns)
        assert app.history is not None
        key = app.history.values[speed]
        base = datetime.now(UTC).replace(microsecond=0) - timedelta(days=11)  # nothing else stored near it
        for m, v, status in ((0, 1.0, SC.Good), (2, 2.0, SC.BadSensorFailure), (4, 4.0, SC.Good)):
            data = variant_to_binary(ua.Variant(v, ua.VariantType.Double))
            app.history.store.record(key, to_micros(base + m * MINUTE), VALUE, status, "", data)
        await app.history.store.flush()
        times = [base + m * MINUTE for m in (4, -1, 1, 3, 4)]

        async def at_times(simple: bool, cp: bytes | None = None) -> ua.HistoryReadResult:
            details = ua.ReadAtTimeDetails(ReqTimes=times, UseSimpleBounds=simple)
            (result,) = await client.uaclient.history_read(params(details, speed, cp))
            return result

        def seen(result: ua.HistoryReadResult) -> list[tuple[float | None, int]]:
            return [
                (dv.Value.Value if dv.Value is not None else None, dv.StatusCode.value)
                for dv in result.HistoryData.DataValues
            ]

        raw_bits, interpolated = 0x400, 0x402  # InfoType DataValue; HistorianBits Raw / Interpolated
        simple = await at_times(True)
        assert simple.StatusCode.value == SC.Good and not simple.ContinuationPoint
        assert seen(simple) == [
            (4.0, raw_bits),
            (None, SC.BadNoData),
            (1.0, interpolated),
            (None, SC.BadNoData),
            (4.0, raw_bits),
        ]
        assert [dv.SourceTimestamp for dv in simple.HistoryData.DataValues] == times
        assert [dv.ServerTimestamp for dv in simple.HistoryData.DataValues] == times
        interpolating = await at_times(False)
        assert seen(interpolating) == [
            (4.0, raw_bits),
            (None, SC.BadNoData),
            (1.0, interpolated),
            (1.0, SC.UncertainDataSubNormal | interpolated),
            (4.0, raw_bits),
        ]

        # two a page: the same values through continuation points
        monkeypatch.setattr(app.history, "max_per_request", 2)
        paged: list[tuple[float | None, int]] = []
        cp = None
        for _ in range(5):
            page = await at_times(False, cp)
            paged += seen(page)
            cp = page.ContinuationPoint
            if not cp:
                break
        assert paged == seen(interpolating)
        # a raw read's point is not an instant's
        (first,) = await client.uaclient.history_read(params(raw(base, base + 5 * MINUTE, 1), speed))
        assert (await at_times(False, first.ContinuationPoint)).StatusCode.value == SC.BadContinuationPointInvalid
        times[1] = ua.get_win_epoch()
        assert (await at_times(True)).StatusCode.value == SC.BadInvalidTimestampArgument
    finally:
        await client.disconnect()


@module_loop
async def test_history_read_applies_the_index_range(app: UacellServer) -> None:
    """OPC 10000-11 6.4.2 (HistoryReadValueId.indexRange, NumericRange as in OPC 10000-4 7.27): each value
    read is cut to the range; a range that does not parse is Bad_IndexRangeInvalid for the node. uacell's
    history returned whole values."""
    client, ns = await connect(app)
    try:
        speed = ua.NodeId(SPEED, ns)
        assert app.history is not None
        key = app.history.values[speed]
        base = datetime.now(UTC).replace(microsecond=0) - timedelta(
            days=7
        )  # a window no other test of the module stores in
        for i, v in enumerate(([1.0, 2.0, 3.0], [4.0, 5.0, 6.0])):
            variant = ua.Variant(v, ua.VariantType.Double)
            app.history.store.record(key, to_micros(base + i * MINUTE), VALUE, 0, "", variant_to_binary(variant))
        await app.history.store.flush()

        async def read(rng: str) -> ua.HistoryReadResult:
            request = params(raw(base, base + 2 * MINUTE, 0), speed)
            request.NodesToRead[0].IndexRange = rng
            (result,) = await client.uaclient.history_read(request)
            return result

        cut = await read("1:2")
        assert cut.StatusCode.is_good()
        assert [dv.Value.Value for dv in cut.HistoryData.DataValues] == [[2.0, 3.0], [5.0, 6.0]]
        beyond = await read("7")
        assert [dv.StatusCode.value for dv in beyond.HistoryData.DataValues] == [SC.BadIndexRangeNoData] * 2
        assert (await read("2:1")).StatusCode.value == SC.BadIndexRangeInvalid
    finally:
        await client.disconnect()


@module_loop
async def test_cancel_ends_a_history_read_under_way(app: UacellServer, monkeypatch: pytest.MonkeyPatch) -> None:
    """OPC 10000-4 5.7.5: Cancel names a request under way by its RequestHandle; the request is answered
    Bad_RequestCancelledByClient and CancelCount counts it; a handle not under way counts nothing.
    asyncua answered every Cancel Bad_ServiceUnsupported. The store's read is held (it waits for the test)
    so that the history read is under way when the Cancel arrives."""
    client, ns = await connect(app)
    assert app.history is not None
    store = app.history.store
    entered, gate = asyncio.Event(), asyncio.Event()
    original = store.read

    async def held(query: Any) -> Any:
        entered.set()
        await gate.wait()
        return await original(query)

    monkeypatch.setattr(store, "read", held)
    try:
        protocol = client.uaclient.protocol
        now = datetime.now(UTC)
        request = ua.HistoryReadRequest(Parameters=params(raw(now - MINUTE, now, 0), ua.NodeId(SPEED, ns)))
        answered = protocol._send_request(request, timeout=30)  # not awaited: it is to be cancelled
        await asyncio.wait_for(entered.wait(), 30)

        async def cancel(handle: int) -> int:
            cancel = ua.CancelRequest(Parameters=ua.CancelParameters(RequestHandle=handle))
            return int(
                struct_from_binary(ua.CancelResponse, await protocol.send_request(cancel)).Parameters.CancelCount
            )

        assert await cancel(request.RequestHeader.RequestHandle) == 1
        body = await asyncio.wait_for(answered, 30)
        assert nodeid_from_binary(body) == ua.NodeId(ua.ObjectIds.ServiceFault_Encoding_DefaultBinary)
        assert struct_from_binary(ua.ResponseHeader, body).ServiceResult.value == SC.BadRequestCancelledByClient
        assert await cancel(request.RequestHeader.RequestHandle) == 0  # no longer under way
        monkeypatch.setattr(store, "read", original)
        (after,) = await client.uaclient.history_read(params(raw(now - MINUTE, now, 0), ua.NodeId(SPEED, ns)))
        assert after.StatusCode.is_good()  # the session goes on
    finally:
        gate.set()
        await client.disconnect()
